"""Training and inference: the unsupervised recipe, resumable checkpoints with the best
validation score, test-time adaptation, evaluation with the classical metrics, and
DistributedDataParallel training (gloo on CPU, NCCL on GPU; each rank on its own device).

:func:`train` takes the user's network (any :class:`~torchfmap.nn.networks.FeatureNetwork`),
loss, optimiser, scheduler and device; :class:`TrainConfig` and :func:`build_model` are the
reference recipe used by ``torchfmap train``.
"""

from __future__ import annotations

import copy
import io
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from .._files import load_checked_bytes, save_checked_bytes
from ..bases import Basis, laplacian_eigenbasis
from ..errors import ParameterError
from ..eval import geodesic_errors
from ..fmap.convert import nearest_neighbor, p2p_to_fmap, values_to_p2p
from ..fmap.refine import zoomout
from ..mesh import Mesh
from .data import (
    PairDataset,
    ShapeBatch,
    ShapeDataset,
    class_pairs,
    collate_pairs,
    precompute_shape,
    shape_item,
)
from .modules import RegularizedFMSolver, UnsupervisedFMLoss
from .networks import DiffusionNet


@dataclass
class TrainConfig:
    """The reference recipe (saved in checkpoints): data, network, solver, loss and optimiser."""

    k: int = 50
    k_net: int = 96
    n_wks: int = 32
    basis: str = "laplacian"
    inputs: str = "wks"
    width: int = 48
    c_out: int = 64
    n_blocks: int = 4
    dropout: float = 0.0
    gradients: bool = True
    lr: float = 1e-3
    epochs: int = 5
    minutes: float = 0.0
    batch_size: int = 1
    w_lap: float = 1e-3
    seed: int = 0
    loss_weights: dict = field(
        default_factory=lambda: {"w_bij": 1.0, "w_orth": 1.0, "w_couple": 1.0, "n_samples": 1000, "tau": 0.07}
    )

    def dataset_kwargs(self) -> dict:
        """Keyword arguments of :class:`~torchfmap.nn.data.ShapeDataset` for this recipe."""
        return dict(k=self.k, n_wks=self.n_wks, k_net=self.k_net, basis=self.basis, inputs=self.inputs)


def build_model(config: TrainConfig) -> tuple[DiffusionNet, RegularizedFMSolver, UnsupervisedFMLoss]:
    """``(network, solver, loss)`` of the recipe, the network seeded by ``config.seed``."""
    torch.manual_seed(config.seed)
    c_in = config.n_wks if config.inputs == "wks" else 3
    net = DiffusionNet(c_in, config.c_out, config.width, config.n_blocks, config.dropout, config.gradients)
    return net, RegularizedFMSolver(w_lap=config.w_lap), UnsupervisedFMLoss(**config.loss_weights)


def random_rigid(
    xyz: torch.Tensor, generator: torch.Generator | None = None, scale=(0.9, 1.1)
) -> torch.Tensor:
    """Augmentation for XYZ inputs: a random rotation and scaling per shape, ``(B, V, 3)``."""
    B = xyz.shape[0]
    q, r = torch.linalg.qr(torch.randn(B, 3, 3, generator=generator, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1))[:, None, :]
    q[torch.linalg.det(q) < 0, :, 0] *= -1  # proper rotations only: reflections change the shape
    s = torch.empty(B, 1, 1, dtype=torch.float64).uniform_(*scale, generator=generator)
    return xyz @ (s * q).to(xyz)


def features(net, shape: ShapeBatch) -> torch.Tensor:
    """The network's features of a :class:`~torchfmap.nn.data.ShapeBatch`: ``(B, V, D)``."""
    return net(shape.inputs, shape.net_basis, shape.grad)


def forward_pair(net, solver, batch: dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Features and both maps of a collated batch: ``(feat_x, feat_y, C_xy, C_yx)``."""
    x, y = batch["x"], batch["y"]
    feat_x, feat_y = features(net, x), features(net, y)
    C_xy, C_yx = solver(feat_x, feat_y, x.basis, y.basis)
    return feat_x, feat_y, C_xy, C_yx


def pair_loss(net, solver, loss_fn, batch: dict) -> dict[str, torch.Tensor]:
    """The loss terms of a collated batch (``loss_fn(C_xy, C_yx, feat_x, feat_y, basis_x, basis_y)``)."""
    feat_x, feat_y, C_xy, C_yx = forward_pair(net, solver, batch)
    return loss_fn(C_xy, C_yx, feat_x, feat_y, batch["x"].basis, batch["y"].basis)


class CosineByTime:
    """Learning-rate factor for ``LambdaLR``: cosine from 1 to ``floor`` over a time budget.

    Counts the time between its calls in this process; ``LambdaLR.state_dict`` saves the time
    counted so far, and after ``load_state_dict`` in another process the clock continues from
    there (the gap between the runs is not counted).
    """

    def __init__(self, minutes: float, floor: float = 0.02) -> None:
        if minutes <= 0:
            raise ParameterError(f"the time budget must be positive, got {minutes} minutes.")
        self.seconds, self.floor = 60.0 * minutes, floor
        self.counted, self.last, self.pid = 0.0, None, os.getpid()

    def __call__(self, step: int) -> float:
        now = time.perf_counter()
        if self.last is not None and self.pid == os.getpid():
            self.counted += now - self.last
        self.last, self.pid = now, os.getpid()
        frac = min(self.counted / self.seconds, 1.0)
        return self.floor + (1 - self.floor) * 0.5 * (1 + math.cos(math.pi * frac))


def unsupervised_score(shapes: ShapeDataset, pairs, solver, loss_fn: UnsupervisedFMLoss, device="cpu"):
    """``score(net) -> float``: the mean unsupervised loss on ``pairs`` with full (not sampled)
    soft maps, in eval mode, for :func:`train`'s ``validate`` (no ground truth)."""
    full = copy.deepcopy(loss_fn)
    full.n_samples = 0
    batches = [collate_pairs([(shapes[a], shapes[b])]) for a, b in pairs]

    @torch.no_grad()
    def score(net) -> float:
        net.eval()
        total = 0.0
        for batch in batches:
            batch = {**batch, "x": batch["x"].to(device), "y": batch["y"].to(device)}
            total += float(pair_loss(net, solver, full, batch)["total"])
        return total / max(len(batches), 1)

    return score


@dataclass
class TrainState:
    """What :func:`train` returns and checkpoints: per-step losses, epochs, times, best score."""

    step: int = 0
    epoch: int = 0
    seconds: float = 0.0
    losses: list = field(default_factory=list)
    epoch_seconds: list = field(default_factory=list)
    scores: list = field(default_factory=list)  # (step, validation score)
    best_score: float = math.inf


def save_checkpoint(path, net, config: TrainConfig | dict, **extra) -> Path:
    """Atomic, checksummed checkpoint: weights, config and extras
    (:func:`~torchfmap._files.save_checked_bytes`); read it with :func:`read_checkpoint`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cfg = asdict(config) if isinstance(config, TrainConfig) else config
    ckpt = {"state_dict": net.state_dict(), "config": cfg, **extra}
    buffer = io.BytesIO()
    torch.save(ckpt, buffer)
    return save_checked_bytes(path, buffer.getvalue())


def read_checkpoint(path, map_location="cpu") -> dict:
    """The checkpoint dict, checksum verified and unpickled with ``weights_only=True`` (tensors
    and plain containers only: a file cannot run code). Raises
    :class:`~torchfmap.errors.CorruptFileError` for a truncated or altered file."""
    payload = load_checked_bytes(path, "checkpoint")
    return torch.load(io.BytesIO(payload), map_location=map_location, weights_only=True)


def load_checkpoint(path, best: bool = True) -> tuple[DiffusionNet, TrainConfig, dict]:
    """``(reference network in eval mode, config, the whole checkpoint dict)``; ``best``: the
    weights with the best validation score when the checkpoint has them."""
    ckpt = read_checkpoint(path)
    config = TrainConfig(**ckpt["config"])
    net = build_model(config)[0]
    state = ckpt.get("best_state_dict") if best and ckpt.get("best_state_dict") else ckpt["state_dict"]
    net.load_state_dict(state)
    return net.eval(), config, ckpt


def train(
    net: torch.nn.Module,
    data: PairDataset,
    loss_fn: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    *,
    solver: torch.nn.Module | None = None,
    scheduler=None,
    device: str | torch.device = "cpu",
    epochs: int = 1,
    minutes: float = 0.0,
    max_steps: int = 0,
    batch_size: int = 1,
    augment: bool = False,
    validate=None,
    validate_every: int = 0,
    checkpoint: str | os.PathLike | None = None,
    config: TrainConfig | dict | None = None,
    resume: bool = False,
    seed: int = 0,
    progress: bool = True,
    rank: int = 0,
    world_size: int = 1,
) -> TrainState:
    """Unsupervised training of ``net`` on the pairs of ``data``; returns the :class:`TrainState`.

    Stops after ``epochs`` epochs, ``minutes`` of training (0: no limit; a resumed run counts
    the time of the earlier runs) or ``max_steps`` steps (0: no limit), whichever comes first.
    ``net`` is moved to ``device`` and every batch with it.
    ``augment``: random rigid motion and scaling of XYZ inputs. ``validate(net) -> score``
    (lower is better) runs every ``validate_every`` steps and at the end; the best weights are
    kept in the checkpoint as ``best_state_dict``. ``checkpoint`` is written atomically at each
    epoch end, each validation and the end (by rank 0); ``resume=True`` continues from it
    (weights, optimiser, scheduler, step and the time already spent). With ``world_size > 1``
    (inside an initialised process group) the network is wrapped in DistributedDataParallel
    and each rank trains on its share of the same pairs.
    """
    device = torch.device(device)
    solver = solver if solver is not None else RegularizedFMSolver()
    net.to(device)
    state = TrainState()
    best_state = None
    if resume and checkpoint is not None and Path(checkpoint).exists():
        ckpt = read_checkpoint(checkpoint, map_location=device)
        net.load_state_dict(ckpt["state_dict"])
        optimizer.load_state_dict(ckpt["optimizer"])
        if scheduler is not None and ckpt.get("scheduler") is not None:
            scheduler.load_state_dict(ckpt["scheduler"])
        state = TrainState(**ckpt["train_state"])
        best_state = ckpt.get("best_state_dict")
    model = net
    sampler = None
    if world_size > 1:
        model = torch.nn.parallel.DistributedDataParallel(
            net, device_ids=[device] if device.type == "cuda" else None
        )
        sampler = torch.utils.data.distributed.DistributedSampler(
            data, num_replicas=world_size, rank=rank, shuffle=True, seed=seed
        )
    generator = torch.Generator().manual_seed(seed + state.epoch)
    loader = torch.utils.data.DataLoader(
        data,
        batch_size=batch_size,
        shuffle=sampler is None,
        sampler=sampler,
        collate_fn=collate_pairs,
        generator=generator,
    )
    t_start = time.perf_counter() - state.seconds
    main = rank == 0

    def out_of_budget() -> bool:
        over_time = minutes > 0 and time.perf_counter() - t_start >= 60 * minutes
        return over_time or (max_steps > 0 and state.step >= max_steps)

    def save() -> None:
        if checkpoint is None or not main:
            return
        extra = {
            "optimizer": optimizer.state_dict(),
            "scheduler": None if scheduler is None else scheduler.state_dict(),
            "train_state": asdict(state),
            "best_state_dict": best_state,
        }
        save_checkpoint(checkpoint, net, config if config is not None else {}, **extra)

    def run_validation() -> None:
        nonlocal best_state
        if validate is None:
            return
        score = float(validate(net))
        net.train()
        state.scores.append((state.step, score))
        if score < state.best_score:
            state.best_score = score
            best_state = {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}

    net.train()
    stop = out_of_budget()
    bar = tqdm(total=None if minutes else epochs * len(loader), disable=not progress or not main, unit="step")
    while state.epoch < epochs and not stop:
        if sampler is not None:
            sampler.set_epoch(state.epoch)
        t_epoch = time.perf_counter()
        for batch in loader:
            batch = {**batch, "x": batch["x"].to(device), "y": batch["y"].to(device)}
            if augment:
                for side in ("x", "y"):
                    s = batch[side]
                    batch[side] = s._replace(inputs=random_rigid(s.inputs))
            terms = pair_loss(model, solver, loss_fn, batch)
            optimizer.zero_grad(set_to_none=True)
            terms["total"].backward()
            optimizer.step()
            if scheduler is not None:
                scheduler.step()
            state.step += 1
            state.losses.append({k: float(v.detach()) for k, v in terms.items()})
            bar.update()
            bar.set_postfix(epoch=state.epoch + 1, loss=f"{state.losses[-1]['total']:.3f}")
            if validate_every and state.step % validate_every == 0:
                run_validation()
                save()
            if out_of_budget():
                stop = True
                break
        else:
            state.epoch += 1
            state.epoch_seconds.append(time.perf_counter() - t_epoch)
        state.seconds = time.perf_counter() - t_start
        save()
    bar.close()
    if validate is not None and (not state.scores or state.scores[-1][0] != state.step):
        run_validation()
    state.seconds = time.perf_counter() - t_start
    save()
    return state


def _single(item: dict, device) -> ShapeBatch:
    return collate_pairs([(item, item)])["x"].to(device)


@torch.no_grad()
def predict_p2p(
    net, solver, x: dict, y: dict, *, mode: str = "fmap", p2p_mode: str = "orthogonal", device="cpu"
) -> np.ndarray:
    """``p2p_yx`` of one pair of dataset items (:class:`~torchfmap.nn.data.ShapeDataset`).

    ``mode='fmap'``: learned features -> ``C_xy`` -> point map by ``p2p_mode``:
    ``'orthogonal'`` (default: nearest neighbour of each row of ``Φ_y`` among the rows of
    ``Φ_x C_xyᵀ``; the recipe's orthogonality loss makes ``C_xy`` near-orthogonal, and this is
    the rule :func:`torchfmap.fmap.fmap_to_p2p` uses for such maps) or ``'pullback'``
    (rows of ``Φ_y C_xy`` among those of ``Φ_x``). ``mode='features'``: nearest neighbours in
    the (normalised) feature space.
    """
    net.eval()
    sx, sy = _single(x, device), _single(y, device)
    fx, fy = features(net, sx), features(net, sy)
    if mode == "features":
        a = torch.nn.functional.normalize(fy[0], dim=-1).double().cpu().numpy()
        b = torch.nn.functional.normalize(fx[0], dim=-1).double().cpu().numpy()
        return nearest_neighbor(a, b, precision="single")
    if mode != "fmap":
        raise ParameterError(f"unknown mode {mode!r}. Fix: 'fmap' or 'features'.")
    if p2p_mode not in ("orthogonal", "pullback"):
        raise ParameterError(f"unknown p2p_mode {p2p_mode!r}. Fix: 'orthogonal' or 'pullback'.")
    C_xy, _ = solver(fx, fy, sx.basis, sy.basis)
    C = C_xy[0].double().cpu().numpy()
    return values_to_p2p(C, x["values"].double().numpy(), y["values"].double().numpy(), mode=p2p_mode)


def adapt(net, solver, loss_fn, x: dict, y: dict, *, steps: int = 10, lr: float = 1e-4, device="cpu"):
    """Unsupervised test-time adaptation: a copy of ``net`` after ``steps`` Adam steps of
    ``loss_fn`` on the pair ``(x, y)`` itself (no ground truth). ``net`` is left unchanged."""
    if steps < 0:
        raise ParameterError(f"steps must be >= 0, got {steps}.")
    tuned = copy.deepcopy(net).to(device).train()
    opt = torch.optim.Adam(tuned.parameters(), lr=lr)
    batch = collate_pairs([(x, y), (y, x)])
    batch = {**batch, "x": batch["x"].to(device), "y": batch["y"].to(device)}
    for _ in range(steps):
        terms = pair_loss(tuned, solver, loss_fn, batch)
        opt.zero_grad(set_to_none=True)
        terms["total"].backward()
        opt.step()
    return tuned.eval()


def evaluate(
    net, shapes: ShapeDataset, pairs, gts, solver=None, *, mode: str = "fmap", max_points=500, device="cpu"
) -> float:
    """Mean normalised geodesic error over ``pairs`` (index pairs) with ground truths ``gts``."""
    solver = solver if solver is not None else RegularizedFMSolver()
    errors = []
    for (a, b), gt in zip(pairs, gts, strict=True):
        x, y = shapes[a], shapes[b]
        p2p = predict_p2p(net, solver, x, y, mode=mode, device=device)
        mesh_x = Mesh(x["vertices"].numpy(), x["faces"].numpy(), validate=False)
        errors.append(geodesic_errors(mesh_x, p2p, gt, max_points=max_points).mean())
    return float(np.mean(errors))


def ddp_worker(rank: int, world_size: int, port: int, files, cache_dir, config_dict: dict, out_path) -> None:
    """One rank of a DDP run of the reference recipe (gloo on CPU, NCCL with one GPU per rank).

    The same pairs as one process (:func:`~torchfmap.nn.data.class_pairs`); rank 0 shows
    progress and writes the checkpoint ``out_path``; every rank writes its final weights to
    ``<out_path folder>/rank{r}.pt`` so they can be compared.
    """
    cuda = torch.cuda.is_available() and torch.cuda.device_count() >= world_size
    backend = "nccl" if cuda else "gloo"
    device = torch.device(f"cuda:{rank}") if cuda else torch.device("cpu")
    os.environ.setdefault("MASTER_ADDR", "127.0.0.1")
    os.environ["MASTER_PORT"] = str(port)
    torch.distributed.init_process_group(backend, rank=rank, world_size=world_size)
    try:
        config = TrainConfig(**config_dict)
        shapes = ShapeDataset(
            files, cache_dir, **config.dataset_kwargs(), rank=rank, world_size=world_size, progress=False
        )
        net, solver, loss_fn = build_model(config)
        opt = torch.optim.Adam(net.parameters(), lr=config.lr)
        train(
            net,
            PairDataset(shapes, class_pairs(shapes.names)),
            loss_fn,
            opt,
            solver=solver,
            device=device,
            epochs=config.epochs,
            checkpoint=out_path,
            config=config,
            seed=config.seed,
            progress=rank == 0,
            rank=rank,
            world_size=world_size,
        )
        torch.save(net.state_dict(), Path(out_path).parent / f"rank{rank}.pt")
    finally:
        torch.distributed.destroy_process_group()


def refine_p2p(
    mesh_x: Mesh,
    mesh_y: Mesh,
    p2p_yx: np.ndarray,
    k0: int = 50,
    k_final: int = 200,
    *,
    bases: tuple[Basis, Basis] | None = None,
) -> np.ndarray:
    """ZoomOut in the Laplacian eigenbases from a point map: ``p2p_yx`` -> ``C_xy (k0, k0)``
    -> ``k_final``; returns the refined ``p2p_yx``. Both sizes are capped for small meshes.
    Point maps are converted by the orthogonal rule (nearest neighbours of ``Φ_y`` in
    ``Φ_x C_xyᵀ``), the classical choice in eigenbases, as in :func:`torchfmap.match`.

    ``bases``: the meshes' Laplacian eigenbases (:func:`~torchfmap.laplacian_eigenbasis`, at
    least ``k_final`` columns each), to reuse them across pairs; computed here when None.

    Raises:
        ParameterError: ``bases`` that are not eigenbases of these meshes' sizes, or have fewer
            than ``k_final`` columns.
    """
    k_final = min(k_final, mesh_x.n_vertices - 1, mesh_y.n_vertices - 1)
    k0 = min(k0, k_final)
    if bases is None:
        bx, by = laplacian_eigenbasis(mesh_x, k_final), laplacian_eigenbasis(mesh_y, k_final)
    else:
        bx, by = bases
        for name, basis, mesh in (("x", bx, mesh_x), ("y", by, mesh_y)):
            if (
                getattr(basis, "eigenvalues", None) is None
                or basis.n_vertices != mesh.n_vertices
                or basis.k < k_final
            ):
                raise ParameterError(
                    f"bases[{name}] must be the Laplacian eigenbasis of mesh_{name} ({mesh.n_vertices} "
                    f"vertices) with >= {k_final} columns. Fix: laplacian_eigenbasis(mesh_{name}, {k_final})."
                )
        bx, by = bx.truncated(k_final), by.truncated(k_final)
    C_xy = p2p_to_fmap(p2p_yx, bx, by, k0, k0)
    return zoomout(C_xy, bx, by, k_final, step=max(1, k0 // 10), mode="orthogonal")[1]


def match_with_network(
    net,
    config: TrainConfig,
    mesh_x: Mesh,
    mesh_y: Mesh,
    *,
    adapt_steps: int = 0,
    adapt_lr: float = 1e-4,
    refine: bool = False,
    mode: str = "fmap",
    device="cpu",
) -> np.ndarray:
    """``p2p_yx`` of two meshes with a trained network: no dataset folder, no cache.

    Precomputes both shapes as in training (:func:`~torchfmap.nn.data.precompute_shape`),
    optionally adapts the network to the pair (:func:`adapt`), predicts (:func:`predict_p2p`)
    and optionally refines with ZoomOut (:func:`refine_p2p`).
    """
    items = [
        shape_item(
            precompute_shape(m, config.k, config.n_wks, k_net=config.k_net, basis=config.basis),
            config.inputs,
            name=m.name or "",
            index=i,
        )
        for i, m in enumerate((mesh_x, mesh_y))
    ]
    _, solver, loss_fn = build_model(config)
    if adapt_steps:
        net = adapt(net, solver, loss_fn, items[0], items[1], steps=adapt_steps, lr=adapt_lr, device=device)
    p2p = predict_p2p(net, solver, items[0], items[1], mode=mode, device=device)
    return refine_p2p(mesh_x, mesh_y, p2p) if refine else p2p
