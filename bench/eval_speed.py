"""Benchmark: evaluating a collection (``torchfmap eval``): per-shape preparation, local workers.

Run by hand from the repository root (table to stdout and ``bench/results/eval_speed.md``)::

    python3 bench/eval_speed.py                                  # dev pairs + 100 synthetic shapes
    python3 bench/eval_speed.py --baseline-pairs 4 --synthetic 20 --synthetic-v 1000   # quick

Rows, all in this process (the pool's workers are child processes), same ``match`` settings
(``eval``'s defaults: the default basis, ``k = 50``, no refinement, every ground-truth point):

- ``per pair``: each pair evaluated on its own (``evaluate_pairs([pair])``), so both meshes are
  prepared again for every pair, as ``eval`` did before shapes were prepared once. It runs on
  the first ``--baseline-pairs`` pairs only; its cost is linear in the number of pairs by
  construction, so the time for all pairs is extrapolated from the time per pair (marked ``*``).
- ``prepared, 1 process``: ``evaluate_pairs(pairs, workers=1)``: each mesh prepared once, with
  this process's threads (all CPUs);
- ``1 process, T threads``: the same with ``threads=T``, ``T = max(1, CPUs // N)``;
- ``prepared, N workers``: ``workers=N`` (``--workers``, a local process pool), ``T`` threads
  each (``evaluate_pairs``'s default for a pool).

Speed-ups are against ``per pair`` (extrapolated) and, for the pool, against both one-process
runs; the pool's results are checked to equal, bit for bit, those of the one-process run with
the same ``T`` threads (per-point errors; the thread count sets the order of BLAS's parallel
sums, so runs with different thread counts may differ in near-tied points). Data:
the 58 test pairs of ``../shared/data/tosca5k_dev`` (14 shapes), and a synthetic collection of ``--synthetic``
copies of ``bench_mesh(--synthetic-v)``, each bent by its own angle about the x axis (vertex ids
kept, identity ground truth; consecutive pairs as ``discover_pairs`` forms them).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import Report, data_path, load1, load_note, log, versions
from _meshes import bench_mesh

from torchfmap import Mesh, save_mesh
from torchfmap.collection import evaluate_pairs, pool_threads
from torchfmap.eval import discover_pairs


def synthetic_collection(folder: Path, n_shapes: int, n_vertices: int) -> Path:
    base = bench_mesh(n_vertices)
    v = base.vertices
    x = (v[:, 0] - v[:, 0].min()) / np.ptp(v[:, 0])
    for i in range(n_shapes):
        angle = np.deg2rad(60.0 * i / max(n_shapes - 1, 1)) * x  # twist about x, growing along it
        c, s = np.cos(angle), np.sin(angle)
        bent = np.stack([v[:, 0], c * v[:, 1] - s * v[:, 2], s * v[:, 1] + c * v[:, 2]], axis=1)
        save_mesh(Mesh(bent, base.faces), folder / f"shape{i:03d}.off")
    return folder


def run(label: str, pairs: list, args, rows: list) -> None:
    log(f"{label}: {len(pairs)} pairs")
    n_base = min(args.baseline_pairs, len(pairs))
    t0 = time.perf_counter()
    for pair in pairs[:n_base]:
        evaluate_pairs([pair])
    per_pair = (time.perf_counter() - t0) / max(n_base, 1)
    log(f"  per pair: {per_pair:.2f} s/pair on {n_base} pairs")
    t0 = time.perf_counter()
    one = evaluate_pairs(pairs, workers=1)
    t_one = time.perf_counter() - t0
    log(f"  prepared, 1 process: {t_one:.1f} s")
    threads = pool_threads(args.workers)
    t0 = time.perf_counter()
    one_t = evaluate_pairs(pairs, workers=1, threads=threads)
    t_one_t = time.perf_counter() - t0
    log(f"  prepared, 1 process, {threads} thread(s): {t_one_t:.1f} s")
    t0 = time.perf_counter()
    pool = evaluate_pairs(pairs, workers=args.workers, threads=threads)
    t_pool = time.perf_counter() - t0
    log(f"  prepared, {args.workers} workers x {threads} thread(s): {t_pool:.1f} s")
    same = all(np.array_equal(a.errors, b.errors) for a, b in zip(one_t, pool, strict=True))
    same_default = all(np.array_equal(a.errors, b.errors) for a, b in zip(one, pool, strict=True))
    shapes = len({p[0] for p in pairs} | {p[1] for p in pairs})
    base = per_pair * len(pairs)
    rows.append(
        {
            "collection": label,
            "pairs": len(pairs),
            "shapes": shapes,
            "per pair [s]": f"{base:.0f}*",
            "prepared, 1 process [s]": t_one,
            f"1 process, {threads} thread(s) [s]": t_one_t,
            f"prepared, {args.workers} workers x {threads} [s]": t_pool,
            "speed-up, 1 process": base / t_one,
            f"{args.workers} workers / 1 process": t_one / t_pool,
            f"{args.workers} workers / 1 process ({threads} thread(s))": t_one_t / t_pool,
            f"pool == 1 process ({threads} thread(s))": "yes" if same else "NO",
            "pool == 1 process (all threads)": "yes" if same_default else "no",
            "mean error": float(np.mean([r.errors.mean() for r in one])),
            "load1": load1(),
        }
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline-pairs", type=int, default=8)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--no-dev", action="store_true", help="skip the dev pairs")
    parser.add_argument("--synthetic", type=int, default=100, help="synthetic shapes (0: none)")
    parser.add_argument("--synthetic-v", type=int, default=1000)
    args = parser.parse_args()
    report = Report("eval_speed")
    report.add(f"# Evaluating collections ({versions('scipy')}; {load_note()} at start)")
    rows: list = []
    dev = data_path("tosca5k_dev")
    if dev is not None and not args.no_dev:
        run("tosca5k_dev test pairs", list(discover_pairs(dev)), args, rows)
    if args.synthetic:
        with tempfile.TemporaryDirectory() as tmp:
            folder = synthetic_collection(Path(tmp), args.synthetic, args.synthetic_v)
            run(
                f"synthetic, {args.synthetic} x {args.synthetic_v} V",
                list(discover_pairs(folder)),
                args,
                rows,
            )
    report.table(
        "Wall time of the whole collection",
        rows,
        note=f"* per pair: extrapolated from the first {args.baseline_pairs} pairs. {load_note()} at end.",
    )
    report.save()


if __name__ == "__main__":
    main()
