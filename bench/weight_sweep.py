"""Benchmark: mean geodesic error of ``match`` vs the Laplacian-commutativity weight, per basis.

Run by hand from the repository root (prints one line per run and a summary to stdout; writes the
summary to ``bench/results/weight_sweep.md``)::

    python3 bench/weight_sweep.py
    python3 bench/weight_sweep.py --pairs cat0-cat1,cat-lion --w-lap 1e-2,1 --bases stack
    python3 bench/weight_sweep.py --pairs cat0-cat1 --w-lap 1 --bases laplacian   # quick check

Pairs and landmarks are those of ``bench/accuracy.py`` (``bench/_pairs.py``: ``--L`` ground-truth
landmarks spread by farthest-point sampling on TOSCA pairs, the 20 given pairs on cat-lion); every
other argument of ``match`` keeps its default, no refinement. The summary is the mean over pairs of the mean
normalised geodesic error; it is how ``torchfmap.fmap.defaults.W_LAP`` was chosen.
"""

from __future__ import annotations

import argparse

import numpy as np
from _common import Report, fmt, load_note, str_list
from _pairs import Pair

from torchfmap.pipeline import match


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default="cat0-cat1,cat2-cat8,wolf0-wolf1,cat-lion")
    parser.add_argument("--w-lap", default="1e-3,1e-1,1,10")
    parser.add_argument("--bases", default="harmonic,diffusion,stack,laplacian")
    parser.add_argument("--L", type=int, default=10, help="landmarks on TOSCA pairs")
    parser.add_argument("--k", type=int, default=50)
    args = parser.parse_args()
    pairs, bases = str_list(args.pairs), str_list(args.bases)
    weights = [float(w) for w in str_list(args.w_lap)]
    err: dict[tuple[str, str, float], float] = {}
    for name in pairs:
        pair = Pair(name)
        lmk = pair.landmarks(args.L)
        for basis in bases:
            for w in weights:
                res = match(pair.x, pair.y, landmarks=lmk, basis=basis, k=args.k, w_lap=w)
                e = err[(name, basis, w)] = float(pair.errors(res.p2p_yx).mean())
                print(f"{name:12s} {basis:9s} w_lap={w:<6g} mean error {e:.4f}  K={res.basis_x.k}")
    print()
    rows = [
        [basis, *(fmt(float(np.mean([err[(p, basis, w)] for p in pairs])), 4) for w in weights)]
        for basis in bases
    ]
    out = Report("weight_sweep")
    out.table(
        f"## Mean over {', '.join(pairs)} of the mean normalised geodesic error (k={args.k}, L={args.L})",
        rows,
        ["basis", *(f"w_lap={w:g}" for w in weights)],
        note=f"No refinement, other match arguments at their defaults; {load_note()} at end.",
    )
    out.save()


if __name__ == "__main__":
    main()
