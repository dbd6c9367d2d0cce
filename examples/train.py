"""Unsupervised training on TOSCA (dev split) with the reference recipe
(``torchfmap.nn.train_recipe``: everything from ``TrainConfig``, the same code as ``torchfmap
train`` and each DDP rank), then errors on the test pairs. A network, loss or optimiser of your
own goes through ``torchfmap.nn.train`` (README, "Learning").

Trains on every mesh of ``../shared/data/tosca5k_dev`` (pairs within classes, no ground truth),
keeps the weights with the best validation score (the mean unsupervised loss on the test
pairs, no ground truth), then prints the mean geodesic error of the test pairs before and
after training. This is transductive: the test shapes are among the (unsupervised) training
shapes, as in ``torchfmap train FOLDER``.

    python examples/train.py --minutes 5 --out examples/out/fmnet.ckpt
    python examples/train.py --minutes 5 --device cuda            # any torch device
    python examples/train.py --epochs 1 --world-size 2            # DDP (gloo on CPU, NCCL on GPUs)
"""

from __future__ import annotations

import argparse
import socket
import time
from dataclasses import asdict
from pathlib import Path

import torch

from torchfmap.eval import gt_from_vts
from torchfmap.io import mesh_files, read_test_pairs, read_vts
from torchfmap.nn.checkpoints import save_checkpoint
from torchfmap.nn.config import TrainConfig, build_model, build_solver
from torchfmap.nn.data import ShapeDataset
from torchfmap.nn.inference import evaluate
from torchfmap.nn.train import ddp_worker, train_recipe, unsupervised_score

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tosca5k_dev"


def test_pairs(names: list[str], folder: Path, limit: int) -> tuple[list, list]:
    rows = read_test_pairs(folder / "test_pairs.txt")
    pairs, gts = [], []
    for a, b in rows[:limit]:
        pairs.append((names.index(a), names.index(b)))
        gts.append(gt_from_vts(*(read_vts(folder / "corres" / f"{n}.vts") for n in (a, b))))
    return pairs, gts


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--minutes", type=float, default=5.0)
    parser.add_argument("--epochs", type=int, default=None, help="default: the time budget alone")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--cache", type=Path, default=None, help="default: the per-user cache")
    parser.add_argument("--out", type=Path, default=Path("examples/out/fmnet.ckpt"))
    parser.add_argument("--eval-pairs", type=int, default=8)
    parser.add_argument("--world-size", type=int, default=1, help="> 1: DDP over that many processes")
    args = parser.parse_args()
    if not args.data.exists():
        raise SystemExit(f"data folder {args.data} not found: this example needs ../shared/data/tosca5k_dev")
    config = TrainConfig(epochs=args.epochs, minutes=args.minutes)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.world_size > 1:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        files = mesh_files(args.data)
        torch.multiprocessing.spawn(
            ddp_worker,
            args=(args.world_size, port, files, args.cache, asdict(config), args.out),
            nprocs=args.world_size,
        )
        print(f"DDP run finished; checkpoint {args.out}")
        return
    shapes = ShapeDataset(args.data, args.cache, **config.dataset_kwargs())
    pairs, gts = test_pairs(shapes.names, args.data, args.eval_pairs)
    solver, loss_fn = build_solver(config)
    untrained, _, _ = build_model(config)  # the recipe's network before training (same seed)
    before = evaluate(untrained, shapes, pairs, gts, solver, device=args.device)
    validate = unsupervised_score(shapes, pairs, solver, loss_fn, device=args.device)  # no ground truth
    t0 = time.perf_counter()
    state, net = train_recipe(
        config, shapes, out=args.out, validate=validate, validate_every=100, device=args.device
    )
    after = evaluate(net, shapes, pairs, gts, solver, device=args.device)
    save_checkpoint(args.out, net, config, train_state=asdict(state), error_before=before, error_after=after)
    print(f"trained {state.step} steps ({state.epoch} epochs) in {time.perf_counter() - t0:.0f} s")
    print(f"mean geodesic error on {len(pairs)} test pairs: untrained {before:.4f} -> trained {after:.4f}")


if __name__ == "__main__":
    main()
