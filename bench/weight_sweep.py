"""Benchmark: mean geodesic error of ``match`` vs the Laplacian-commutativity weight, per basis.

Run by hand from the repository root (prints one line per run and a summary to stdout)::

    python bench/weight_sweep.py
    python bench/weight_sweep.py --pairs cat0-cat1,cat-lion --w-lap 1e-2,1 --bases stack

Pairs and landmarks are those of ``bench/accuracy.py`` (``--L`` ground-truth landmarks spread by
farthest-point sampling on TOSCA pairs, the 20 given pairs on cat-lion); every other argument of
``match`` keeps its default, no refinement. The summary is the mean over pairs of the mean
normalised geodesic error; it is how ``torchfmap.pipeline.W_LAP`` was chosen.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import Pair  # noqa: E402

from torchfmap.pipeline import match  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default="cat0-cat1,cat2-cat8,wolf0-wolf1,cat-lion")
    parser.add_argument("--w-lap", default="1e-3,1e-1,1,10")
    parser.add_argument("--bases", default="harmonic,diffusion,stack,laplacian")
    parser.add_argument("--L", type=int, default=10, help="landmarks on TOSCA pairs")
    parser.add_argument("--k", type=int, default=50)
    args = parser.parse_args()
    pairs = args.pairs.split(",")
    weights = [float(w) for w in args.w_lap.split(",")]
    bases = args.bases.split(",")
    err: dict[tuple[str, str, float], float] = {}
    for name in pairs:
        pair = Pair(name)
        lmk = pair.landmarks(args.L)
        for basis in bases:
            for w in weights:
                res = match(pair.x, pair.y, landmarks=lmk, basis=basis, k=args.k, w_lap=w)
                e = err[(name, basis, w)] = float(pair.errors(res.p2p_yx).mean())
                print(f"{name:12s} {basis:9s} w_lap={w:<6g} mean error {e:.4f}  K={res.basis_x.k}")
    print(f"\n| basis | {' | '.join(f'w_lap={w:g}' for w in weights)} |")
    print("|---|" + "---|" * len(weights))
    for basis in bases:
        means = [np.mean([err[(p, basis, w)] for p in pairs]) for w in weights]
        print(f"| {basis} | {' | '.join(f'{m:.4f}' for m in means)} |")


if __name__ == "__main__":
    main()
