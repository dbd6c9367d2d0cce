"""Benchmark: harmonic and diffusion bases vs a Laplacian eigenbasis (``eigsh``), timing and accuracy.

Run by hand from the repository root (prints markdown tables to stdout, progress to stderr)::

    python bench/bases.py                                # 5K, 50K, 200K vertices
    python bench/bases.py --sizes 5000 --repeats 5 --eigsh-k 50,100

All meshes are ``bench_mesh(n)`` (irregular, closed, genus 0); ``(L, B)`` is
``torchfmap.laplacian(mesh)`` (cotan + lumped voronoi mass). Seeds are 50 Euclidean
farthest-point samples (``farthest_point_sampling(mesh, 50, metric='euclidean')``), so that
seed selection is not part of any basis timing; geodesic FPS (heat method) is timed on its own.

Timings: one warm-up of every operation runs first on a small mesh (the dense check below), then
each cell is the median of ``--repeats`` calls (one call at or above ``--large`` vertices, and
one call whenever the first call took longer than ``--max-repeat-s``). All in the same process.

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
- Table 2 (accuracy, one ``--accuracy-size`` mesh): every heat method on the Table 1 problem vs a
  reference; the error of a column (seed, time) is ``max|K - K_ref| / max|K_ref|``, reported as
  max and median over the 200 columns. The reference is ``heat_kernels(..., method='rational',
  tol=1e-12)`` if it passes the dense check: on a ``--dense-size`` mesh, against the dense
  ``expm(-t B⁻¹L)[:, seeds] / B[seeds, seeds]`` (``scipy.linalg.expm``) to better than 1e-9 at
  every time. Otherwise it is the exact kernel from a dense ``np.linalg.eigh`` of
  ``D^-1/2 L D^-1/2`` (itself checked against expm in the same table; ~1 min at 5K), and
  rational tol 1e-12 becomes one of the rows.
- Table 3 (small times 1e-5, 1e-4, at ``--small-time-sizes``): krylov tol 1e-6 with
  ``local=False`` vs ``local='auto'``, their column-wise relative difference, and the mean
  fraction of vertices where the local kernels are non-zero.
"""

from __future__ import annotations

import argparse
import gc
import os
import statistics
import sys
import time
import traceback
import tracemalloc
from collections.abc import Callable
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as ssla

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import log  # noqa: E402
from _meshes import bench_mesh  # noqa: E402

import torchfmap  # noqa: E402
from torchfmap.bases import concatenate, heat_kernels, orthonormalize  # noqa: E402

N_SEEDS = 50
TIMES = (1e-3, 3e-3, 1e-2, 3e-2)
SMALL_TIMES = (1e-5, 1e-4)
HEAT_TOL = 1e-6
REF_TOL = 1e-12
DENSE_LIMIT = 1e-9  # the rational reference must match the dense expm to this
EIGSH_RATIO_K = 100


def mesh_name(n: int) -> str:
    return f"bench{n // 1000}K" if n % 1000 == 0 else f"bench{n}"


class Failed(str):
    """A table cell for an operation that raised (the traceback goes to stderr)."""


def attempt(label: str, fn: Callable[[], Any]) -> Any:
    """``fn()``, or a :class:`Failed` cell with the traceback logged if it raises."""
    try:
        return fn()
    except Exception as exc:  # noqa: BLE001 - a benchmark reports failures and carries on
        log(f"  !! {label} raised {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
        return Failed(f"ERROR {type(exc).__name__}")


def timed(fn: Callable[[], Any], repeats: int, max_repeat_s: float) -> tuple[float, int, Any]:
    """Median wall time of up to ``repeats`` calls (just one if the first exceeds ``max_repeat_s``)."""
    times: list[float] = []
    out = None
    for _ in range(repeats):
        out = None  # free the previous result before the next call
        gc.collect()
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
        if times[0] > max_repeat_s:
            break
    return statistics.median(times), len(times), out


def run_timed(label: str, fn: Callable[[], Any], repeats: int, max_repeat_s: float) -> tuple[Any, Any]:
    """``(median time, last result)`` of :func:`timed`, or ``(Failed cell, None)`` if ``fn`` raises."""
    res = attempt(label, lambda: timed(fn, repeats, max_repeat_s))
    return (res, None) if isinstance(res, Failed) else (res[0], res[2])


def rel_diff(K: np.ndarray, K_ref: np.ndarray) -> float:
    """Max over columns of ``max|K - K_ref| / max|K_ref|`` for ``(V, C)`` arrays."""
    return float((np.abs(K - K_ref).max(axis=0) / np.abs(K_ref).max(axis=0)).max())


def peak_mib(fn: Callable[[], Any]) -> float:
    """tracemalloc peak (MiB) of one call of ``fn`` (numpy allocations only)."""
    gc.collect()
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def column_errors(K: np.ndarray, K_ref: np.ndarray) -> np.ndarray:
    """``max|K - K_ref| / max|K_ref|`` for every (time, seed) column of ``(T, V, S)`` arrays."""
    return np.abs(K - K_ref).max(axis=1) / np.abs(K_ref).max(axis=1)


def eigsh(L, B, k: int):
    return ssla.eigsh(L, k=k, M=B, sigma=-1e-8, which="LM")


# -- the dense check of the reference (also the warm-up of every operation) ---------------------
def dense_eigh_kernels(L, B, seeds: np.ndarray, times_abs: np.ndarray) -> np.ndarray:
    """Exact ``(T, V, S)`` delta kernels from a dense symmetric eigendecomposition (lumped ``B``).

    With ``D = diag(B)`` and ``D^{-1/2} L D^{-1/2} = U Λ Uᵀ``:
    ``exp(-tA) D⁻¹ e_p = D^{-1/2} U exp(-tΛ) Uᵀ e_p / sqrt(d_p)``.
    """
    d = B.diagonal()
    s = 1.0 / np.sqrt(d)
    lam, U = np.linalg.eigh(s[:, None] * L.toarray() * s[None, :])
    Us = U[seeds].T * s[seeds]  # (V, S)
    return np.stack([s[:, None] * (U @ (np.exp(-t * lam)[:, None] * Us)) for t in times_abs])


def dense_check(n: int, seed: int) -> tuple[list[dict], bool]:
    """Rational (``REF_TOL``) and dense-eigh kernels vs ``scipy.linalg.expm``; also warms everything up.

    Returns the table rows and whether the rational reference passed (``< DENSE_LIMIT`` at every t).
    """
    mesh = bench_mesh(n, seed)
    L, B = torchfmap.laplacian(mesh)
    d = B.diagonal()
    seeds = torchfmap.farthest_point_sampling(mesh, 10, metric="euclidean")
    times = np.array(SMALL_TIMES + TIMES)
    log(f"dense check on {mesh_name(n)}: rational tol {REF_TOL:g} and dense eigh vs scipy.linalg.expm")
    t0 = time.perf_counter()
    K = heat_kernels((L, B), seeds, times * mesh.area, method="rational", tol=REF_TOL)
    t_rat = time.perf_counter() - t0
    K_eigh = dense_eigh_kernels(L, B, seeds, times * mesh.area)
    A = L.toarray() / d[:, None]
    rows = []
    passed = True
    for ti, t in enumerate(times):
        t0 = time.perf_counter()
        K_dense = sla.expm(-t * mesh.area * A)[:, seeds] / d[seeds]
        t_dense = time.perf_counter() - t0
        err = column_errors(K[ti][None], K_dense[None])[0].max()
        err_eigh = column_errors(K_eigh[ti][None], K_dense[None])[0].max()
        passed &= bool(err < DENSE_LIMIT)
        rows.append(
            {
                "mesh": mesh_name(n),
                "V": n,
                "seeds": len(seeds),
                "t (rel.)": f"{t:g}",
                f"rational tol={REF_TOL:g}: max col. rel. err": float(err),
                f"< {DENSE_LIMIT:g}": "yes" if err < DENSE_LIMIT else "**NO**",
                "dense eigh: max col. rel. err": float(err_eigh),
                "expm [s]": t_dense,
                "rational, all t [s]": t_rat if ti == 0 else "",
            }
        )
    # warm-up of everything timed later (first-call overheads: imports, ARPACK, CHOLMOD, ...)
    log("warm-up of every timed operation on the dense-check mesh")
    s50 = torchfmap.farthest_point_sampling(mesh, 50, metric="euclidean")
    torchfmap.farthest_point_sampling(mesh, 5, metric="geodesic")
    h = torchfmap.harmonic_basis(mesh, s50, operators=(L, B))
    for method in ("krylov", "rational", "backward_euler", "spectral"):
        heat_kernels((L, B), s50[:5], times[:2] * mesh.area, method=method, tol=HEAT_TOL)
    dg = torchfmap.diffusion_basis(mesh, s50, TIMES, "krylov", operators=(L, B), tol=HEAT_TOL, local=False)
    torchfmap.diffusion_basis(mesh, s50, TIMES, "krylov", operators=(L, B), tol=HEAT_TOL, local="auto")
    for m in ("mgs", "cholqr"):
        orthonormalize(concatenate([dg, h]), m)
    eigsh(L, B, 50)
    return rows, passed


# -- table 1 ----------------------------------------------------------------------------------
def time_geodesic_fps(mesh, limit_s: float, repeats: int, max_repeat_s: float) -> Any:
    """Geodesic FPS of 50 seeds, if the extrapolation from 1 and 6 seeds says it takes < ``limit_s``."""
    t0 = time.perf_counter()
    torchfmap.farthest_point_sampling(mesh, 1, metric="geodesic")
    t1 = time.perf_counter() - t0
    t0 = time.perf_counter()
    torchfmap.farthest_point_sampling(mesh, 6, metric="geodesic")
    t6 = time.perf_counter() - t0
    est = t1 + (t6 - t1) * (N_SEEDS - 1) / 5
    if est > limit_s:
        return f"skipped (est. {est:.0f} s)"
    t, _, _ = timed(lambda: torchfmap.farthest_point_sampling(mesh, N_SEEDS, metric="geodesic"), repeats, 10)
    return t


def bench_size(n: int, args: argparse.Namespace) -> tuple[dict, dict, dict | None]:
    name = mesh_name(n)
    large = n >= args.large
    reps = 1 if large else args.repeats
    mrs = args.max_repeat_s
    row: dict[str, Any] = {"mesh": name, "V": n, "repeats": reps}
    log(f"{name}: building mesh")
    mesh = bench_mesh(n, args.seed)
    log(f"{name}: laplacian")
    row["(L, B) [s]"], _, (L, B) = timed(lambda: torchfmap.laplacian(mesh), reps, mrs)
    log(f"{name}: seeds (euclidean FPS)")
    row["seeds eucl. [s]"], _, seeds = timed(
        lambda: torchfmap.farthest_point_sampling(mesh, N_SEEDS, metric="euclidean"), reps, mrs
    )
    log(f"{name}: seeds (geodesic FPS)")
    row["seeds geod. [s]"] = attempt(
        "geodesic FPS", lambda: time_geodesic_fps(mesh, args.geodesic_limit_s, reps, mrs)
    )

    # eigsh baseline
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
        res = attempt(f"eigsh k={k}", lambda k=k: timed(lambda: eigsh(L, B, k), reps, mrs)[0])
        row[col] = eig_t[k] = res
        if isinstance(res, float):
            prev = (k, res)

    log(f"{name}: harmonic basis")
    row["harmonic [s]"], harm = run_timed(
        "harmonic", lambda: torchfmap.harmonic_basis(mesh, seeds, operators=(L, B)), reps, mrs
    )

    diffs: dict[str, Any] = {}
    for local in (False, "auto"):
        col = f"diffusion local={local} [s]"
        log(f"{name}: diffusion basis krylov local={local}")
        row[col], diffs[str(local)] = run_timed(
            f"diffusion local={local}",
            lambda local=local: torchfmap.diffusion_basis(
                mesh, seeds, TIMES, "krylov", operators=(L, B), tol=HEAT_TOL, local=local
            ),
            reps,
            mrs,
        )
    dg, da = diffs["False"], diffs["auto"]
    if dg is not None and da is not None:
        row["max rel. diff auto vs global"] = rel_diff(da.values, dg.values)
    else:
        row["max rel. diff auto vs global"] = "n/a"

    if dg is not None and harm is not None:
        stack = concatenate([dg, harm])
        for m in ("mgs", "cholqr"):
            log(f"{name}: orthonormalize {stack.values.shape[1]} columns, {m}")
            t, ortho = run_timed(f"orthonormalize {m}", lambda m=m: orthonormalize(stack, m), reps, mrs)
            if ortho is None:
                row[f"{m} [s] (kept)"] = t
                row[f"{m} |QᵀBQ-I|"] = "n/a"
            else:
                Q = ortho.values
                row[f"{m} [s] (kept)"] = f"{fmt(t)} ({Q.shape[1]})"
                row[f"{m} |QᵀBQ-I|"] = float(np.abs(Q.T @ (B @ Q) - np.eye(Q.shape[1])).max())
    else:
        for m in ("mgs", "cholqr"):
            row[f"{m} [s] (kept)"] = "n/a"
            row[f"{m} |QᵀBQ-I|"] = "n/a"

    # ratios and memory
    ratio: dict[str, Any] = {"mesh": name, "V": n}
    e100 = eig_t.get(EIGSH_RATIO_K)
    for col, denom in (
        ("eigsh100 / harmonic", row["harmonic [s]"]),
        ("eigsh100 / diffusion global", row["diffusion local=False [s]"]),
        ("eigsh100 / diffusion auto", row["diffusion local=auto [s]"]),
    ):
        ok = isinstance(e100, float) and isinstance(denom, float)
        ratio[col] = e100 / denom if ok else "n/a"
    if not args.no_memory:
        log(f"{name}: tracemalloc peaks")
        ratio["peak MiB harmonic"] = attempt(
            "peak harmonic", lambda: peak_mib(lambda: torchfmap.harmonic_basis(mesh, seeds, operators=(L, B)))
        )
        ratio["peak MiB diffusion global"] = attempt(
            "peak diffusion",
            lambda: peak_mib(
                lambda: torchfmap.diffusion_basis(
                    mesh, seeds, TIMES, "krylov", operators=(L, B), tol=HEAT_TOL, local=False
                )
            ),
        )
        ratio["peak MiB eigsh100"] = attempt(
            "peak eigsh", lambda: peak_mib(lambda: eigsh(L, B, EIGSH_RATIO_K))
        )
        ratio["values MiB (V x 250)"] = n * 250 * 8 / 2**20
    del dg, da, harm, diffs

    small = None
    if n in args.small_time_sizes:
        small = bench_small_times(mesh, (L, B), seeds, reps, mrs)
    return row, ratio, small


# -- table 3 ----------------------------------------------------------------------------------
def bench_small_times(mesh, ops, seeds, reps: int, mrs: float) -> dict:
    name = mesh_name(mesh.n_vertices)
    times = ", ".join(f"{t:g}" for t in SMALL_TIMES)
    row: dict[str, Any] = {"mesh": name, "V": mesh.n_vertices, "t (rel.)": times}
    out = {}
    for local in (False, "auto"):
        log(f"{name}: small times krylov local={local}")
        row[f"local={local} [s]"], out[str(local)] = run_timed(
            f"small times local={local}",
            lambda local=local: torchfmap.diffusion_basis(
                mesh, seeds, SMALL_TIMES, "krylov", operators=ops, tol=HEAT_TOL, local=local
            ),
            reps,
            mrs,
        )
    g, a = out["False"], out["auto"]
    if g is not None and a is not None:
        row["speed-up"] = row["local=False [s]"] / row["local=auto [s]"]
        row["max rel. diff"] = rel_diff(a.values, g.values)
        row["local support (mean % of V)"] = 100.0 * float((a.values != 0).mean())
    return row


# -- table 2 ----------------------------------------------------------------------------------
ACCURACY_METHODS: list[tuple[str, str, Any, dict]] = [
    # (label, method, tol, extra kwargs)
    ("krylov", "krylov", 1e-6, {}),
    ("krylov", "krylov", 1e-8, {}),
    ("rational", "rational", 1e-6, {}),
    ("backward_euler (n_steps=1)", "backward_euler", None, {}),
    ("spectral (n_eigen=200)", "spectral", None, {"n_eigen": 200}),
    ("krylov local='auto'", "krylov", 1e-6, {"local": "auto"}),
]


def bench_accuracy(n: int, args: argparse.Namespace, rational_ok: bool) -> tuple[list[dict], str]:
    """Table 2; the reference is rational tol ``REF_TOL`` if it passed the dense check, else dense eigh."""
    name = mesh_name(n)
    log(f"accuracy on {name}")
    mesh = bench_mesh(n, args.seed)
    L, B = torchfmap.laplacian(mesh)
    seeds = torchfmap.farthest_point_sampling(mesh, N_SEEDS, metric="euclidean")
    times = np.array(TIMES) * mesh.area
    reps = args.repeats
    methods = list(ACCURACY_METHODS)
    if rational_ok:
        reference = f"rational tol {REF_TOL:g}"
        log(f"  reference: {reference}")
        t_ref, _, K_ref = timed(
            lambda: heat_kernels((L, B), seeds, times, method="rational", tol=REF_TOL),
            reps,
            args.max_repeat_s,
        )
    else:
        reference = "dense eigh (np.linalg.eigh of D^-1/2 L D^-1/2)"
        log(f"  rational tol {REF_TOL:g} failed the dense check; reference: {reference} (one call)")
        t_ref, _, K_ref = timed(lambda: dense_eigh_kernels(L, B, seeds, times), 1, 0.0)
        methods.insert(0, ("rational", "rational", REF_TOL, {}))
    rows = [
        {
            "method": f"{reference} (reference)",
            "tol": f"{REF_TOL:g}" if rational_ok else "n/a",
            "time [s]": t_ref,
            "max col. rel. err": "—",
            "median col. rel. err": "—",
            "max err ≤ tol": "—",
        }
    ]
    for label, method, tol, extra in methods:
        log(f"  {label} tol={tol}")
        kw = dict(extra)
        if kw.get("local"):
            kw["vertices"] = mesh.vertices
        t, K = run_timed(
            label,
            lambda method=method, tol=tol, kw=kw: heat_kernels(
                (L, B), seeds, times, method=method, tol=tol if tol is not None else HEAT_TOL, **kw
            ),
            reps,
            args.max_repeat_s,
        )
        row: dict[str, Any] = {
            "method": label,
            "tol": f"{tol:g}" if tol is not None else "n/a",
            "time [s]": t,
        }
        if K is not None:
            err = column_errors(K, K_ref)
            row["max col. rel. err"] = float(err.max())
            row["median col. rel. err"] = float(np.median(err))
            row["max err ≤ tol"] = "n/a" if tol is None else ("yes" if err.max() <= tol else "**NO**")
            row["worst column (t rel., seed)"] = worst_column(err, seeds)
        rows.append(row)
    rows[0]["worst column (t rel., seed)"] = "—"
    return rows, reference


def worst_column(err: np.ndarray, seeds: np.ndarray) -> str:
    ti, si = np.unravel_index(int(np.argmax(err)), err.shape)
    return f"{TIMES[ti]:g}, {int(seeds[si])}"


# -- output -----------------------------------------------------------------------------------
def fmt(x: Any) -> str:
    if isinstance(x, float):
        if x == 0.0:
            return "0"
        return f"{x:.2e}" if abs(x) < 1e-3 else f"{x:.3f}" if abs(x) < 100 else f"{x:.0f}"
    if isinstance(x, (int, np.integer)):
        return f"{x:,}"
    return str(x)


def markdown(rows: list[dict], columns: list[str] | None = None) -> str:
    if columns is None:
        columns = list(dict.fromkeys(c for r in rows for c in r))

    def cell(x: Any) -> str:
        return fmt(x).replace("|", "\\|")  # a literal pipe would split the cell

    lines = ["| " + " | ".join(cell(c) for c in columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    lines += ["| " + " | ".join(cell(r.get(c, "")) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def int_list(text: str) -> list[int]:
    return [int(s) for s in text.split(",") if s.strip()]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="5000,50000,200000", help="comma-separated vertex counts")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (median)")
    parser.add_argument("--large", type=int, default=100_000, help="time only once from this size")
    parser.add_argument("--max-repeat-s", type=float, default=30.0, help="no repeats if a call takes longer")
    parser.add_argument("--eigsh-k", default="50,100,200", help="comma-separated eigsh k (ascending)")
    parser.add_argument(
        "--eigsh-budget", type=float, default=300.0, help="skip an eigsh k estimated to take longer (s)"
    )
    parser.add_argument(
        "--geodesic-limit-s", type=float, default=60.0, help="skip geodesic FPS estimated to take longer"
    )
    parser.add_argument("--small-time-sizes", default="50000,200000", help="sizes of table 3 (among --sizes)")
    parser.add_argument("--accuracy-size", type=int, default=5000, help="mesh size of table 2 (0: skip)")
    parser.add_argument("--dense-size", type=int, default=1000, help="mesh size of the dense expm check")
    parser.add_argument("--no-memory", action="store_true", help="skip the tracemalloc peaks")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    sizes = int_list(args.sizes)
    args.eigsh_k = sorted(int_list(args.eigsh_k))
    args.small_time_sizes = set(int_list(args.small_time_sizes))
    start = time.perf_counter()

    check_rows, rational_ok = dense_check(args.dense_size, args.seed)
    acc_rows, reference = (
        bench_accuracy(args.accuracy_size, args, rational_ok) if args.accuracy_size else ([], "")
    )
    t1_rows, ratio_rows, small_rows = [], [], []
    for n in sizes:
        row, ratio, small = bench_size(n, args)
        t1_rows.append(row)
        ratio_rows.append(ratio)
        if small is not None:
            small_rows.append(small)
        gc.collect()
    log(f"done in {time.perf_counter() - start:.0f} s")

    print(
        f"## Bases vs eigsh: {N_SEEDS} seeds (Euclidean FPS), diffusion t = "
        f"{', '.join(f'{t:g}' for t in TIMES)} (relative), tol {HEAT_TOL:g}\n\n({os.cpu_count()} CPUs; "
        f"numpy {np.__version__}, scipy "
        f"{version('scipy')}, solver backends {', '.join(torchfmap.available_backends())}; median of "
        f"`repeats` calls, one call when the first exceeded {args.max_repeat_s:g} s)\n"
    )
    print(markdown(t1_rows))
    print(
        "\neigsh: `scipy.sparse.linalg.eigsh(L, k, M=B, sigma=-1e-8, which='LM')` (SuperLU shift-invert). "
        f"'skipped (est.)': extrapolated as t(k_prev)·(k/k_prev)² > {args.eigsh_budget:g} s. "
        "Orthonormalisation of concatenate([diffusion global (200 cols), harmonic (50 cols)]), "
        "default drop tolerances (mgs 1e-8, cholqr 1e-7); kept columns in brackets. "
        "'max rel. diff auto vs global': max over columns of max|ΔK| / max|K_global|.\n"
    )
    print("## Ratios (same run) and tracemalloc peaks (numpy allocations only)\n")
    print(markdown(ratio_rows))
    print(
        "\nPeaks are of one untimed call each; memory inside CHOLMOD / SuperLU / ARPACK Fortran is not "
        "seen by tracemalloc. 'values MiB' is the size of a dense V x 250 float64 basis, for scale.\n"
    )
    print("## Dense check of the references vs expm(-t B⁻¹L)[:, seeds] / B[seeds, seeds]\n")
    print(markdown(check_rows))
    print(
        f"\nrational: heat_kernels(method='rational', tol={REF_TOL:g}); dense eigh: the exact kernels from "
        "np.linalg.eigh of D^-1/2 L D^-1/2 (D = diag B). Errors: max over seeds of max|K - K_expm| / "
        f"max|K_expm|. Table 2 uses rational tol {REF_TOL:g} as its reference only if it passes here "
        "at every t, else dense eigh.\n"
    )
    if acc_rows:
        print(
            f"## Accuracy on {mesh_name(args.accuracy_size)}: heat_kernels (delta kernel), "
            f"{N_SEEDS} seeds x {len(TIMES)} times, vs {reference}\n"
        )
        print(markdown(acc_rows))
        print(
            "\nColumn error = max_v |K - K_ref| / max_v |K_ref| for one (seed, time); max / median over the "
            f"{N_SEEDS * len(TIMES)} columns. krylov's tol is a relative B-norm convergence test, not this "
            "max-norm error. Median of `--repeats` calls.\n"
        )
    if small_rows:
        print(f"## Small times: diffusion_basis krylov tol {HEAT_TOL:g}, {N_SEEDS} seeds, local False/auto\n")
        print(markdown(small_rows))
        print(
            "\n'local support': mean over columns of the fraction of vertices where the local kernel is "
            "non-zero (its patch). 'max rel. diff': max over columns of max|ΔK| / max|K_global|.\n"
        )


if __name__ == "__main__":
    main()
