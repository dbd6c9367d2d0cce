"""Unsupervised training on TOSCA (dev split) with the reference recipe
(``torchfmap.nn.Trainer.from_config``: everything from ``TrainConfig``, the same code as
``torchfmap train`` and each DDP rank), then errors on the test pairs. A network, loss or
optimiser of your own goes through the ``Trainer`` constructor (README, "Learning").

Trains on every mesh of ``../shared/data/tosca5k_dev`` (pairs within classes, no ground truth),
keeps the weights with the best validation score (the mean unsupervised loss on the test
pairs, no ground truth), then prints the mean geodesic error of the test pairs before training
and with the best weights. The checkpoint stays whole (best weights, optimiser, schedule: it
resumes); the errors are recorded in it. This is transductive: the test shapes are among the
(unsupervised) training shapes, as in ``torchfmap train FOLDER``.

    python examples/train.py --minutes 5 --out examples/out/fmnet.ckpt
    python examples/train.py --minutes 5 --device cuda            # cpu, cuda or auto
    python examples/train.py --epochs 1 --world-size 2            # DDP (gloo on CPU, NCCL on GPUs)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from torchfmap.eval import gt_from_vts
from torchfmap.io import mesh_files, read_test_pairs, read_vts
from torchfmap.nn.checkpoints import load_checkpoint
from torchfmap.nn.config import Budget, TrainConfig, build_model, build_solver
from torchfmap.nn.data import ShapeDataset
from torchfmap.nn.devices import resolve_device
from torchfmap.nn.inference import evaluate
from torchfmap.nn.train import unsupervised_score
from torchfmap.nn.trainer import Trainer, spawn_ddp

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tosca5k_dev"


def test_pairs(names: list[str], folder: Path, limit: int) -> tuple[list, list]:
    rows = read_test_pairs(folder / "test_pairs.txt")
    pairs, gts = [], []
    for a, b in rows[:limit]:
        pairs.append((names.index(a), names.index(b)))
        gts.append(gt_from_vts(*(read_vts(folder / "corres" / f"{n}.vts") for n in (a, b))))
    return pairs, gts


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--minutes", type=float, default=5.0)
    parser.add_argument("--epochs", type=int, default=None, help="default: the time budget alone")
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto")
    parser.add_argument("--cache", type=Path, default=None, help="default: the per-user cache")
    parser.add_argument("--out", type=Path, default=Path("examples/out/fmnet.ckpt"))
    parser.add_argument("--eval-pairs", type=int, default=8)
    parser.add_argument("--validate-every", type=int, default=100)
    parser.add_argument("--world-size", type=int, default=1, help="> 1: DDP over that many processes")
    parser.add_argument("--config", type=Path, default=None, help="a recipe file (TrainConfig as JSON)")
    args = parser.parse_args(argv)
    if not args.data.exists():
        raise SystemExit(f"data folder {args.data} not found: this example needs ../shared/data/tosca5k_dev")
    recipe = TrainConfig.from_json(args.config) if args.config else TrainConfig()
    config = recipe.with_budget(Budget(epochs=args.epochs, minutes=args.minutes))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.world_size > 1:
        files = mesh_files(args.data)
        weights = spawn_ddp(config, files, args.out, world_size=args.world_size, cache_dir=args.cache)
        print(f"DDP run over {len(weights)} ranks finished; checkpoint {args.out}")
        return
    device = resolve_device(args.device)
    shapes = ShapeDataset(args.data, args.cache, **config.dataset_kwargs())
    pairs, gts = test_pairs(shapes.names, args.data, args.eval_pairs)
    solver, loss_fn = build_solver(config)
    untrained, _, _ = build_model(config)  # the recipe's network before training (same seed)
    before = evaluate(untrained.to(device), shapes, pairs, gts, solver, device=device)
    validate = unsupervised_score(shapes, pairs, solver, loss_fn, device=device)  # no ground truth
    trainer = Trainer.from_config(
        config, shapes, device=device, validate=validate, validate_every=args.validate_every,
        checkpoint=args.out,
    )  # fmt: skip
    t0 = time.perf_counter()
    state = trainer.fit()
    best = load_checkpoint(args.out)[0]  # the weights of the best validation score
    after = evaluate(best.to(device), shapes, pairs, gts, solver, device=device)
    trainer.save(error_before=before, error_after=after)  # the whole checkpoint again, with the errors
    print(f"trained {state.step} steps ({state.epoch} epochs) in {time.perf_counter() - t0:.0f} s")
    print(f"mean geodesic error on {len(pairs)} test pairs: untrained {before:.4f} -> trained {after:.4f}")


if __name__ == "__main__":
    main()
