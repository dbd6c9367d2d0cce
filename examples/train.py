"""Unsupervised training of the reference feature network on TOSCA (dev split), on the CPU.

Trains :class:`torchfmap.nn.FeatureNet` with the differentiable functional-map solver and the
unsupervised loss (bijectivity + orthogonality + functional/point-map coupling) on pairs of
``../shared/data/tosca5k_dev`` meshes of the same class, saves a checkpoint each epoch, and
evaluates the mean geodesic error of the standard test pairs before and after training.

    python examples/train.py --epochs 4 --out examples/out/fmnet.ckpt
    python examples/train.py --world-size 2        # DistributedDataParallel (gloo, loopback)
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import torch

from torchfmap.eval import gt_from_vts, read_vts
from torchfmap.nn.data import ShapeDataset
from torchfmap.nn.train import TrainConfig, build_model, ddp_worker, evaluate, save_checkpoint, train

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tosca5k_dev"


def class_pairs(names: list[str]) -> list[tuple[int, int]]:
    """Ordered pairs of shapes of the same class (cat-cat, wolf-wolf)."""
    kind = [n.rstrip("0123456789") for n in names]
    return [(i, j) for i in range(len(names)) for j in range(len(names)) if i != j and kind[i] == kind[j]]


def test_pairs(names: list[str], folder: Path, limit: int) -> tuple[list, list]:
    rows = [ln.split()[:2] for ln in (folder / "test_pairs.txt").read_text().splitlines() if ln.strip()]
    pairs, gts = [], []
    for a, b in rows:
        if a in names and b in names and len(pairs) < limit:
            pairs.append((names.index(a), names.index(b)))
            vts = [read_vts(folder / "corres" / f"{n}.vts") for n in (a, b)]
            gts.append(gt_from_vts(*vts))
    return pairs, gts


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--shapes", default="cat0,cat1,cat2,cat3,cat4,wolf0,wolf1,wolf2")
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--k", type=int, default=30)
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "torchfmap-cache")
    parser.add_argument("--out", type=Path, default=Path("examples/out/fmnet.ckpt"))
    parser.add_argument("--eval-pairs", type=int, default=4)
    parser.add_argument("--world-size", type=int, default=1, help="> 1: DDP over that many CPU processes")
    args = parser.parse_args()
    if not args.data.exists():
        raise SystemExit(f"data folder {args.data} not found: this example needs ../shared/data/tosca5k_dev")
    names = args.shapes.split(",")
    files = [args.data / f"{n}.off" for n in names]
    config = TrainConfig(epochs=args.epochs, k=args.k)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.world_size > 1:
        torch.multiprocessing.spawn(
            ddp_worker,
            args=(args.world_size, 29511, files, args.cache, asdict(config), args.out.parent),
            nprocs=args.world_size,
        )
        print(f"DDP run finished; checkpoint {args.out.parent / 'ddp.ckpt'}")
        return
    shapes = ShapeDataset(files, args.cache, k=config.k, n_wks=config.n_wks)
    pairs, gts = test_pairs(names, args.data, args.eval_pairs)
    before = evaluate(build_model(config)[0], shapes, pairs, gts, config)
    t0 = time.perf_counter()
    net, history = train(shapes, config, pairs=class_pairs(names), checkpoint=args.out)
    after = evaluate(net, shapes, pairs, gts, config)
    save_checkpoint(args.out, net, config, history=history, error_before=before, error_after=after)
    print(
        f"trained {args.epochs} epochs in {time.perf_counter() - t0:.0f} s; loss per epoch "
        + ", ".join(f"{h:.1f}" for h in history)
    )
    print(f"mean geodesic error on {len(pairs)} test pairs: untrained {before:.4f} -> trained {after:.4f}")
    print(f"checkpoint: {args.out}")


if __name__ == "__main__":
    main()
