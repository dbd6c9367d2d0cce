"""Training and inference helpers: unsupervised functional-map training, checkpoints, evaluation
with the classical metrics, and DistributedDataParallel training (gloo on CPU, NCCL on GPU)."""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from .._files import atomic_write
from ..eval import geodesic_errors
from ..fmap.convert import nearest_neighbor
from ..mesh import Mesh
from .data import PairDataset, ShapeDataset, collate_pairs
from .modules import FeatureNet, RegularizedFMSolver, UnsupervisedFMLoss


@dataclass
class TrainConfig:
    """Settings of :func:`train` (saved in checkpoints)."""

    k: int = 30
    n_wks: int = 32
    width: int = 64
    c_out: int = 64
    n_blocks: int = 3
    lr: float = 1e-3
    epochs: int = 5
    batch_size: int = 1
    w_lap: float = 1e-3
    seed: int = 0
    loss_weights: dict = field(
        default_factory=lambda: {"w_bij": 1.0, "w_orth": 1.0, "w_couple": 1.0, "n_samples": 1000}
    )


def build_model(config: TrainConfig) -> tuple[FeatureNet, RegularizedFMSolver, UnsupervisedFMLoss]:
    torch.manual_seed(config.seed)
    net = FeatureNet(config.n_wks, config.c_out, config.width, config.n_blocks)
    return net, RegularizedFMSolver(w_lap=config.w_lap), UnsupervisedFMLoss(**config.loss_weights)


def forward_pair(net, solver, batch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Features and both maps of a collated batch: ``(feat_x, feat_y, C_xy, C_yx)``."""
    (bx, fx, _), (by, fy, _) = batch["x"], batch["y"]
    feat_x, feat_y = net(fx, bx), net(fy, by)
    C_xy, C_yx = solver(feat_x, feat_y, bx, by)
    return feat_x, feat_y, C_xy, C_yx


def save_checkpoint(path: str | os.PathLike, net: FeatureNet, config: TrainConfig, **extra) -> Path:
    """Atomic checkpoint: weights, config and extras (:func:`~torchfmap._files.atomic_write`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ckpt = {"state_dict": net.state_dict(), "config": asdict(config), **extra}
    return atomic_write(path, lambda fh: torch.save(ckpt, fh))


def load_checkpoint(path: str | os.PathLike) -> tuple[FeatureNet, TrainConfig, dict]:
    """``(network in eval mode, config, the whole checkpoint dict)``."""
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    config = TrainConfig(**ckpt["config"])
    net = build_model(config)[0]
    net.load_state_dict(ckpt["state_dict"])
    return net.eval(), config, ckpt


def train(
    shapes: ShapeDataset,
    config: TrainConfig,
    *,
    pairs=None,
    checkpoint: str | os.PathLike | None = None,
    progress: bool = True,
    rank: int = 0,
    world_size: int = 1,
) -> tuple[FeatureNet, list[float]]:
    """Unsupervised training over pairs of ``shapes``; returns the network and per-epoch mean loss.

    With ``world_size > 1`` (inside an initialised process group) the model is wrapped in
    DistributedDataParallel and each rank sees its share of the pairs (DistributedSampler).
    """
    net, solver, loss_fn = build_model(config)
    model = net
    sampler = None
    data = PairDataset(shapes, pairs)
    if world_size > 1:
        model = torch.nn.parallel.DistributedDataParallel(net)
        sampler = torch.utils.data.distributed.DistributedSampler(
            data, num_replicas=world_size, rank=rank, shuffle=True, seed=config.seed
        )
    loader = torch.utils.data.DataLoader(
        data,
        batch_size=config.batch_size,
        shuffle=sampler is None,
        sampler=sampler,
        collate_fn=collate_pairs,
        generator=torch.Generator().manual_seed(config.seed),
    )
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    history = []
    for epoch in range(config.epochs):
        if sampler is not None:
            sampler.set_epoch(epoch)
        losses = []
        bar = tqdm(loader, desc=f"epoch {epoch + 1}/{config.epochs}", disable=not progress or rank != 0)
        for batch in bar:
            feat_x, feat_y, C_xy, C_yx = forward_pair(model, solver, batch)
            terms = loss_fn(C_xy, C_yx, feat_x, feat_y, batch["x"][0], batch["y"][0])
            opt.zero_grad()
            terms["total"].backward()
            opt.step()
            losses.append(float(terms["total"].detach()))
            bar.set_postfix(loss=f"{losses[-1]:.4f}")
        history.append(float(np.mean(losses)))
        if checkpoint is not None and rank == 0:
            save_checkpoint(checkpoint, net, config, epoch=epoch + 1, history=history)
    return net, history


@torch.no_grad()
def predict_p2p(net: FeatureNet, solver: RegularizedFMSolver, x: dict, y: dict) -> np.ndarray:
    """``p2p_yx`` of one pair of dataset items: learned features -> ``C_xy`` -> nearest neighbours."""
    batch = collate_pairs([(x, y)])
    _, _, C_xy, _ = forward_pair(net, solver, batch)
    phi_x = x["values"].double().numpy()
    phi_y = y["values"].double().numpy()
    return nearest_neighbor(phi_y @ C_xy[0].double().numpy(), phi_x, precision="single")


def evaluate(net: FeatureNet, shapes: ShapeDataset, pairs, gts, config: TrainConfig, max_points=500) -> float:
    """Mean normalised geodesic error over ``pairs`` (index pairs) with ground truths ``gts``."""
    solver = RegularizedFMSolver(w_lap=config.w_lap)
    errors = []
    for (a, b), gt in zip(pairs, gts, strict=True):
        x, y = shapes[a], shapes[b]
        p2p = predict_p2p(net.eval(), solver, x, y)
        mesh_x = Mesh(x["vertices"].numpy(), x["faces"].numpy(), validate=False)
        errors.append(geodesic_errors(mesh_x, p2p, gt, max_points=max_points).mean())
    net.train()
    return float(np.mean(errors))


def ddp_worker(rank: int, world_size: int, port: int, files, cache_dir, config_dict: dict, out_dir) -> None:
    """One rank of a CPU (gloo) or GPU (NCCL) DDP training run; rank 0 writes the checkpoint.

    Every rank also writes its final weights to ``out_dir/rank{r}.pt`` so they can be compared.
    """
    backend = "nccl" if torch.cuda.is_available() else "gloo"
    os.environ.setdefault("MASTER_ADDR", "127.0.0.1")
    os.environ["MASTER_PORT"] = str(port)
    torch.distributed.init_process_group(backend, rank=rank, world_size=world_size)
    try:
        config = TrainConfig(**config_dict)
        shapes = ShapeDataset(
            files, cache_dir, k=config.k, n_wks=config.n_wks, rank=rank, world_size=world_size, progress=False
        )
        net, _ = train(
            shapes,
            config,
            progress=False,
            rank=rank,
            world_size=world_size,
            checkpoint=Path(out_dir) / "ddp.ckpt",
        )
        torch.save(net.state_dict(), Path(out_dir) / f"rank{rank}.pt")
    finally:
        torch.distributed.destroy_process_group()
