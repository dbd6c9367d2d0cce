"""Benchmark: time of the landmark default of ``match`` over eigenbasis ZoomOut, same process.

Run by hand from the repository root (one heavy job at a time: the ratio is the target)::

    OMP_NUM_THREADS=1 python3 bench/landmark_timing.py
    python3 bench/landmark_timing.py --pairs cat0-cat1 --repeats 5

For each pair (real 5K pairs: a TOSCA near-isometric one and a SMAL_r one, 7 ground-truth
landmarks), the median wall time of ``match(x, y, landmarks, k=60, refine='zoomout')`` with the
default (it chooses the basis) and with ``basis='laplacian'``, from the meshes (preparation
included), after one warm-up call; writes ``bench/results/landmark_timing.md``.
"""

from __future__ import annotations

import argparse
import statistics
import time

from _common import Report, load_note, str_list
from _pairs import Pair

from torchfmap.pipeline import match


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", default="cat0-cat1,smal:fox-05+muybridge_075_04")
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()
    rows = []
    for spec in str_list(args.pairs):
        pair = Pair(spec)
        lm = pair.landmarks(7, use_fixed=False)
        match(pair.x, pair.y, landmarks=lm, k=60, refine="zoomout")  # warm-up: imports, caches
        times: dict[str, list[float]] = {"default": [], "laplacian": []}
        chosen = ""
        for _ in range(args.repeats):
            for name in times:
                t0 = time.perf_counter()
                res = match(
                    pair.x,
                    pair.y,
                    landmarks=lm,
                    k=60,
                    refine="zoomout",
                    basis=None if name == "default" else name,
                )
                times[name].append(time.perf_counter() - t0)
                chosen = res.kind if name == "default" else chosen
        d, e = (statistics.median(times[n]) for n in ("default", "laplacian"))
        rows.append(
            {"pair": spec, "chosen": chosen, "default s": d, "eigenbasis ZoomOut s": e, "ratio": d / e}
        )
    report = Report("landmark_timing")
    report.add(f"# Landmark default vs eigenbasis ZoomOut, median of {args.repeats} ({load_note()})")
    report.table("Wall time per 5K pair (from meshes), 7 landmarks, k = 60", rows)
    report.save()


if __name__ == "__main__":
    main()
