"""Benchmark: speed of the harmonic and diffusion bases vs a Laplacian eigenbasis (``eigsh``).

Run by hand from the repository root (prints markdown tables to stdout, progress to stderr, and
writes them to ``bench/results/bases.md``)::

    python3 bench/bases.py                                # 5K, 50K, 200K vertices
    python3 bench/bases.py --sizes 5000 --repeats 5 --eigsh-k 50,100
    python3 bench/bases.py --sizes 2000 --repeats 1 --eigsh-k 50 --no-memory   # quick check

Accuracy of the heat kernels: ``bench/heat_accuracy.py`` (was ``--accuracy-size``); small times
and local support: ``bench/heat_support.py`` (was ``--small-time-sizes``).

Meshes, operators and seeds: see ``bench/_bases.py`` (50 Euclidean FPS seeds, so that seed
selection is not part of any basis timing; geodesic FPS (heat method) is timed on its own).
Timings: one warm-up of every operation on a ``--warmup-size`` mesh first, then each cell is the
median of ``--repeats`` calls (one call at or above ``--large`` vertices, and one call whenever
the first took longer than ``--max-repeat-s``). All in the same process.

- Table 1 (per mesh size): ``eigsh(L, k=K, M=B, sigma=-1e-8, which='LM')`` for every K of
  ``--eigsh-k`` (a K is skipped when ``t(K_prev) (K / K_prev)^2`` exceeds ``--eigsh-budget``;
  the cell then gives the estimate); ``harmonic_basis`` (50 seeds: one factorisation + one block
  solve); ``diffusion_basis`` (50 seeds x relative times 1e-3, 3e-3, 1e-2, 3e-2, tol 1e-6,
  krylov) with ``local=False`` and ``local='auto'``; ``orthonormalize`` of the 250-column stack
  ``concatenate([diffusion (global), harmonic])`` with mgs and cholqr (kept columns in brackets).
- Table 1b: ratios ``eigsh(k=100) / harmonic`` and ``eigsh(k=100) / diffusion`` of the same run,
  and the tracemalloc peak (MiB) of one extra untimed call each of harmonic, diffusion (krylov
  global) and eigsh(k=100). tracemalloc sees numpy allocations only: memory held inside CHOLMOD,
  SuperLU or ARPACK's Fortran code is not counted.
"""

from __future__ import annotations

import argparse
import gc
import time
from typing import Any

import numpy as np
from _bases import EIGSH_RATIO_K, HEAT_TOL, N_SEEDS, TIMES, attempt, diffusion, eigsh, rel_diff, run_timed
from _bases import warm_up as warm_up_all
from _common import Report, fmt, int_list, load_note, log, timed, traced_peak_mib, versions
from _meshes import bench_mesh, mesh_name

import torchfmap
from torchfmap.bases import concatenate, orthonormalize


def time_geodesic_fps(mesh, limit_s: float, repeats: int) -> Any:
    """Geodesic FPS of 50 seeds, if the extrapolation from 1 and 6 seeds says it takes < ``limit_s``."""
    t1 = timed(lambda: torchfmap.farthest_point_sampling(mesh, 1, metric="geodesic"))[0]
    t6 = timed(lambda: torchfmap.farthest_point_sampling(mesh, 6, metric="geodesic"))[0]
    est = t1 + (t6 - t1) * (N_SEEDS - 1) / 5
    if est > limit_s:
        return f"skipped (est. {est:.0f} s)"
    fps = lambda: torchfmap.farthest_point_sampling(mesh, N_SEEDS, metric="geodesic")  # noqa: E731
    return timed(fps, repeats, max_repeat_s=10)[0]


def time_eigsh(name: str, L, B, row: dict, args, reps: int) -> dict[int, Any]:
    """``eigsh`` for every k of ``--eigsh-k``, skipping those estimated above ``--eigsh-budget``."""
    prev: tuple[int, float] | None = None
    eig_t: dict[int, Any] = {}
    for k in args.eigsh_k:
        col = f"eigsh k={k} [s]"
        if prev is not None and prev[1] * (k / prev[0]) ** 2 > args.eigsh_budget:
            est = prev[1] * (k / prev[0]) ** 2
            log(f"{name}: eigsh k={k} skipped (estimated {est:.0f} s > {args.eigsh_budget:g} s)")
            row[col] = eig_t[k] = f"skipped (est. {est:.0f} s)"
            continue
        log(f"{name}: eigsh k={k}")
        res = attempt(
            f"eigsh k={k}", lambda k=k: timed(lambda: eigsh(L, B, k), reps, max_repeat_s=args.max_repeat_s)[0]
        )
        row[col] = eig_t[k] = res
        if isinstance(res, float):
            prev = (k, res)
    return eig_t


def time_orthonormalize(name: str, stack, B, row: dict, reps: int, mrs: float) -> None:
    """mgs and cholqr of the diffusion + harmonic stack: time (kept columns) and ``max|QᵀBQ - I|``."""
    for m in ("mgs", "cholqr"):
        if stack is None:
            row[f"{m} [s] (kept)"] = row[f"{m} |QᵀBQ-I|"] = "n/a"
            continue
        log(f"{name}: orthonormalize {stack.values.shape[1]} columns, {m}")
        t, ortho = run_timed(f"orthonormalize {m}", lambda m=m: orthonormalize(stack, m), reps, mrs)
        if ortho is None:
            row[f"{m} [s] (kept)"], row[f"{m} |QᵀBQ-I|"] = t, "n/a"
            continue
        Q = ortho.values
        row[f"{m} [s] (kept)"] = f"{fmt(t)} ({Q.shape[1]})"
        row[f"{m} |QᵀBQ-I|"] = float(np.abs(Q.T @ (B @ Q) - np.eye(Q.shape[1])).max())


def ratios(n: int, row: dict, eig_t: dict[int, Any]) -> dict[str, Any]:
    """Table 1b: the eigsh(k=100) baseline over each basis of the same run."""
    ratio: dict[str, Any] = {"mesh": mesh_name(n), "V": n}
    e100 = eig_t.get(EIGSH_RATIO_K)
    for col, denom in (
        ("eigsh100 / harmonic", row["harmonic [s]"]),
        ("eigsh100 / diffusion global", row["diffusion local=False [s]"]),
        ("eigsh100 / diffusion auto", row["diffusion local=auto [s]"]),
    ):
        ok = isinstance(e100, float) and isinstance(denom, float)
        ratio[col] = e100 / denom if ok else "n/a"
    return ratio


def memory_peaks(mesh, L, B, seeds, ratio: dict) -> None:
    """tracemalloc peaks of one untimed call each of harmonic, diffusion (global) and eigsh(k=100)."""
    calls = {
        "peak MiB harmonic": lambda: torchfmap.harmonic_basis(mesh, seeds, operators=(L, B)),
        "peak MiB diffusion global": lambda: diffusion(mesh, seeds, (L, B), local=False),
        "peak MiB eigsh100": lambda: eigsh(L, B, EIGSH_RATIO_K),
    }
    for col, fn in calls.items():
        ratio[col] = attempt(col, lambda fn=fn: traced_peak_mib(fn)[0])
    ratio["values MiB (V x 250)"] = mesh.n_vertices * 250 * 8 / 2**20


def bench_size(n: int, args: argparse.Namespace) -> tuple[dict, dict]:
    """Table 1 row and Table 1b row of one mesh size."""
    name = mesh_name(n)
    reps, mrs = (1 if n >= args.large else args.repeats), args.max_repeat_s
    row: dict[str, Any] = {"mesh": name, "V": n, "repeats": reps}
    log(f"{name}: building mesh, laplacian, seeds")
    mesh = bench_mesh(n, args.seed)
    row["(L, B) [s]"], _, (L, B) = timed(lambda: torchfmap.laplacian(mesh), reps, max_repeat_s=mrs)
    eucl = lambda: torchfmap.farthest_point_sampling(mesh, N_SEEDS, metric="euclidean")  # noqa: E731
    row["seeds eucl. [s]"], _, seeds = timed(eucl, reps, max_repeat_s=mrs)
    row["seeds geod. [s]"] = attempt(
        "geodesic FPS", lambda: time_geodesic_fps(mesh, args.geodesic_limit_s, reps)
    )
    eig_t = time_eigsh(name, L, B, row, args, reps)
    log(f"{name}: harmonic basis")
    harmonic = lambda: torchfmap.harmonic_basis(mesh, seeds, operators=(L, B))  # noqa: E731
    row["harmonic [s]"], harm = run_timed("harmonic", harmonic, reps, mrs)
    diffs: dict[str, Any] = {}
    for local in (False, "auto"):
        log(f"{name}: diffusion basis krylov local={local}")
        fn = lambda local=local: diffusion(mesh, seeds, (L, B), local=local)  # noqa: E731
        row[f"diffusion local={local} [s]"], diffs[str(local)] = run_timed(
            f"diffusion local={local}", fn, reps, mrs
        )
    dg, da = diffs["False"], diffs["auto"]
    both = dg is not None and da is not None
    row["max rel. diff auto vs global"] = rel_diff(da.values, dg.values) if both else "n/a"
    stack = concatenate([dg, harm]) if dg is not None and harm is not None else None
    time_orthonormalize(name, stack, B, row, reps, mrs)
    del dg, da, harm, diffs, stack  # free the bases before the memory peaks
    ratio = ratios(n, row, eig_t)
    if not args.no_memory:
        log(f"{name}: tracemalloc peaks")
        memory_peaks(mesh, L, B, seeds, ratio)
    return row, ratio


def report(args, t1_rows: list[dict], ratio_rows: list[dict]) -> None:
    out = Report("bases")
    out.add(
        f"## Bases vs eigsh: {N_SEEDS} seeds (Euclidean FPS), diffusion t = "
        f"{', '.join(f'{t:g}' for t in TIMES)} (relative), tol {HEAT_TOL:g}",
        f"({versions('scipy')}, solver backends {', '.join(torchfmap.available_backends())}; median of "
        f"`repeats` calls, one call when the first exceeded {args.max_repeat_s:g} s; {load_note()} at end)",
    )
    out.table(
        "Table 1: wall time per mesh size",
        t1_rows,
        note="eigsh: `scipy.sparse.linalg.eigsh(L, k, M=B, sigma=-1e-8, which='LM')` (SuperLU shift-invert). "
        f"'skipped (est.)': extrapolated as t(k_prev)·(k/k_prev)² > {args.eigsh_budget:g} s. "
        "Orthonormalisation of concatenate([diffusion global (200 cols), harmonic (50 cols)]), "
        "default drop tolerances (mgs 1e-8, cholqr 1e-7); kept columns in brackets. "
        "'max rel. diff auto vs global': max over columns of max|ΔK| / max|K_global|.",
    )
    out.table(
        "Table 1b: ratios (same run) and tracemalloc peaks (numpy allocations only)",
        ratio_rows,
        note="Peaks are of one untimed call each; memory inside CHOLMOD / SuperLU / ARPACK Fortran is not "
        "seen by tracemalloc. 'values MiB' is the size of a dense V x 250 float64 basis, for scale.",
    )
    out.save()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="5000,50000,200000", help="comma-separated vertex counts")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (median)")
    parser.add_argument("--large", type=int, default=100_000, help="time only once from this size")
    parser.add_argument("--max-repeat-s", type=float, default=30.0, help="no repeats if a call takes longer")
    parser.add_argument("--eigsh-k", default="50,100,200", help="comma-separated eigsh k (ascending)")
    parser.add_argument(
        "--eigsh-budget", type=float, default=300.0, help="skip an eigsh k estimated longer (s)"
    )
    parser.add_argument(
        "--geodesic-limit-s", type=float, default=60.0, help="skip geodesic FPS estimated longer"
    )
    parser.add_argument("--warmup-size", type=int, default=1000, help="mesh size of the warm-up")
    parser.add_argument("--no-memory", action="store_true", help="skip the tracemalloc peaks")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.eigsh_k = sorted(int_list(args.eigsh_k))
    start = time.perf_counter()
    warm_up_all(args.warmup_size, args.seed)
    t1_rows, ratio_rows = [], []
    for n in int_list(args.sizes):
        row, ratio = bench_size(n, args)
        t1_rows.append(row)
        ratio_rows.append(ratio)
        gc.collect()
    log(f"done in {time.perf_counter() - start:.0f} s")
    report(args, t1_rows, ratio_rows)


if __name__ == "__main__":
    main()
