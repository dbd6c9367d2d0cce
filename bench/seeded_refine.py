"""Benchmark: the classical self-seeded second stage (``experimental.seeded.seeded_match``)
against ZoomOut, without landmarks, on validation pairs of FAUST_r and SMAL_r.

Run by hand from the repository root::

    python3 bench/seeded_refine.py --sets faust_val,smal_val --max-pairs 12

Pairs: ``learned.dev_set`` (FAUST_r tr_reg_070..079; the SMAL_r validation animals), the first
``--max-pairs`` of each. Both methods run on shapes prepared once per pair (shared), so the
time column compares the refinements, not the eigensolves. Errors: mean normalised geodesic
error x100 (``--max-points`` ground-truth points per pair).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import Report, log
from learned import dev_set

from torchfmap import load_mesh, match, prepare_shape
from torchfmap.eval import Correspondence, geodesic_errors
from torchfmap.experimental.seeded import seeded_match


def run(set_name: str, args) -> dict:
    files, _, pairs, gts = dev_set(set_name)
    pick = np.random.default_rng(0).choice(len(pairs), min(args.max_pairs, len(pairs)), replace=False)
    errors: dict[str, list[float]] = {}
    seconds: dict[str, float] = {}
    counts = []
    for n, i in enumerate(pick):
        (a, b), gt = pairs[i], gts[i]
        x, y = load_mesh(files[a]), load_mesh(files[b])
        shapes = (prepare_shape(x, 2 * args.k), prepare_shape(y, 2 * args.k))
        corr = Correspondence(*gt)
        for method in ("raw", "zoomout", "seeded"):
            t0 = time.perf_counter()
            if method == "seeded":
                result = seeded_match(x, y, k=args.k, shapes=shapes).result
            else:
                result = match(x, y, k=args.k, shapes=shapes, refine=None if method == "raw" else method)
            seconds[method] = seconds.get(method, 0.0) + time.perf_counter() - t0
            errors.setdefault(method, []).append(
                100 * geodesic_errors(x, result.p2p_yx, corr, max_points=args.max_points).mean()
            )
            if method == "seeded":
                counts.append(0 if result.seeds is None else len(result.seeds))
        log(
            f"{set_name} pair {n + 1}/{len(pick)}: "
            + ", ".join(f"{m} {v[-1]:.2f}" for m, v in errors.items())
        )
    mean = {m: float(np.mean(v)) for m, v in errors.items()}
    return dict(
        set=set_name, pairs=len(pick), raw=f"{mean['raw']:.3f}", zoomout=f"{mean['zoomout']:.3f}",
        seeded=f"{mean['seeded']:.3f}", seeded_over_zoomout=f"{mean['seeded'] / mean['zoomout']:.3f}",
        seeds=f"{np.mean(counts):.1f}", time_ratio=f"{seconds['seeded'] / seconds['zoomout']:.2f}",
    )  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sets", default="faust_val,smal_val")
    p.add_argument("--max-pairs", type=int, default=12)
    p.add_argument("--max-points", type=int, default=1000)
    p.add_argument("--k", type=int, default=50)
    args = p.parse_args()
    report = Report("seeded_refine")
    rows = [run(name, args) for name in args.sets.split(",")]
    report.table("Classical second stage: seeded_match vs ZoomOut, no landmarks (x100)", rows)
    report.save()


if __name__ == "__main__":
    main()
