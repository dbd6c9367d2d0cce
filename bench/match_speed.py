"""Benchmark: the whole matching pipeline at ~17K vertices (ours vs pyFM) and 50K x 50K point-map conversion.

Run by hand from the repository root (prints markdown tables to stdout, progress to stderr)::

    python bench/match_speed.py                           # subdivided TOSCA wolf pair, k=100; NN 50K
    python bench/match_speed.py --pair synthetic --n 20000 --repeats 3
    python bench/match_speed.py --no-nn                   # or --no-match

(a) Whole pipeline. The pair (identity ground truth, ``x`` the source, ``y`` the target):

- ``wolf`` (default): ``tosca_hires_wolf`` wolf0 (x) and wolf1 (y), which share their
  connectivity, each refined by one step of Loop subdivision (``trimesh.remesh.subdivide_loop``);
  the new vertices depend on the connectivity only, so vertex i still matches vertex i
  (17,370 vertices).
- ``synthetic``: ``bench_mesh(n)`` and a copy twisted by 40 degrees about the x axis over its
  length (near-isometric, same vertices).

Same settings on both sides: ``k`` (100) eigenfunctions, the same number of WKS descriptors
(``--n-descr``) from the same number of eigenpairs (``--k-descr``; both default to ``match``'s
own defaults), no landmarks (``--landmarks L`` adds L farthest-point pairs ``(i, i)``), no
refinement; then a second, separate full run with ZoomOut from ``k`` to ``2k`` in steps of
``k // 10``; then a third with the same ZoomOut iterated on ``--zoomout-samples`` (2000)
farthest-point samples per shape (``zoomout-sub``; the final point map uses every vertex):

- ours: ``match(Mesh(V_x, F), Mesh(V_y, F), basis='laplacian', k=k, refine=None | 'zoomout',
  n_descriptors=n_descr, k_descriptors=k_descr, zoomout_samples=None | N)``, other weights at
  their defaults (printed), fresh ``Mesh`` objects in every run (construction and validation
  are timed).
- pyFM (``bench/_pyfm.py``): ``TriMesh`` from the same arrays, ``preprocess(n_descr, k_descr,
  descr_type='WKS', k_process=max(k or 2k, k_descr))``, ``fit(K=(k, k))`` with the weights of
  pyFM's README example (descriptor commutativity w_dcomm=0.1, no orientation term),
  ``get_p2p()`` and, in the second run, ``zoomout_refine(nit=10, step=k // 10)``, in the
  third ``zoomout_refine(nit=10, step=k // 10, subsample=N)``.

One warm-up of both pipelines runs on a small ``bench_mesh`` pair first (imports, first calls);
then ``--repeats`` rounds, each in the order ours, pyFM, ours+ZoomOut, pyFM+ZoomOut (then the
subsampled pair), and every
cell is the median over rounds. ``pyFM / ours`` is the ratio of those medians (target: >= 3).
Errors: mean normalised geodesic error (heat method on x) and AUC on the same ``--eval-points``
random vertices of y for all maps (distance rows computed once). The 1-minute load average is
recorded with every run: another job may share the CPUs.

(b) Point-map conversion: ``torchfmap.fmap.nearest_neighbor(query, reference, method='brute')``
with ``--nn-n`` (50,000) x 50,000 points in ``--nn-dim`` (100) dimensions (reference Gaussian,
query a shuffled copy plus 1e-3 noise, so the answer is known) for ``block_bytes`` 32 MiB and
128 MiB: wall time and peak resident memory (``VmHWM`` reset through ``/proc/self/clear_refs``)
of one untraced call, and the tracemalloc peak of a second call, against the size of the naive
full ``(M, N)`` float64 distance matrix (not allocated). pyFM's brute-force
``knn_query`` (scikit-learn, ``working_memory`` 1024 MB) is timed the same way as a reference.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import inspect
import os
import statistics
import sys
import time
import tracemalloc
from collections.abc import Callable
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import load1, log  # noqa: E402
from _meshes import bench_mesh, real_mesh_path  # noqa: E402
from _pyfm import PYFM_FIT, run_pyfm  # noqa: E402

import torchfmap  # noqa: E402
from torchfmap.eval import auc  # noqa: E402
from torchfmap.fmap import nearest_neighbor  # noqa: E402
from torchfmap.pipeline import W_LAP, match  # noqa: E402

MiB = 2**20
WOLVES = ("tosca_hires_wolf/wolf0.off", "tosca_hires_wolf/wolf1.off")


def fmt(x: Any) -> str:
    if isinstance(x, float):
        if x == 0.0:
            return "0"
        return f"{x:.2e}" if abs(x) < 1e-3 else f"{x:.3f}" if abs(x) < 100 else f"{x:.0f}"
    if isinstance(x, (int, np.integer)):
        return f"{x:,}"
    return str(x)


def markdown(rows: list[dict], columns: list[str]) -> str:
    def cell(x: Any) -> str:
        return fmt(x).replace("|", "\\|")

    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    lines += ["| " + " | ".join(cell(r.get(c, "")) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


# -- (a) whole pipeline --------------------------------------------------------------------------
def wolf_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """Loop-subdivided TOSCA wolf0 / wolf1 (shared connectivity: identity ground truth)."""
    import trimesh

    paths = [real_mesh_path(name) for name in WOLVES]
    if any(p is None for p in paths):
        raise SystemExit(f"{WOLVES} not found under {real_mesh_path('')}; use --pair synthetic")
    a, b = (torchfmap.load_mesh(p) for p in paths)
    if not np.array_equal(a.faces, b.faces):
        raise SystemExit("wolf0 and wolf1 do not share their connectivity: no identity ground truth")
    va, fa = trimesh.remesh.subdivide_loop(a.vertices, a.faces, iterations=1)
    vb, fb = trimesh.remesh.subdivide_loop(b.vertices, b.faces, iterations=1)
    if not np.array_equal(fa, fb):
        raise SystemExit("subdivision changed the connectivity of one wolf")
    return np.asarray(va), np.asarray(vb), np.asarray(fa, dtype=np.int64), "wolf0/wolf1 Loop x1"


def synthetic_pair(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """``bench_mesh(n)`` and a copy twisted by 40 degrees about x over its length."""
    m = bench_mesh(n)
    v = m.vertices
    s = (v[:, 0] - v[:, 0].min()) / np.ptp(v[:, 0])
    a = np.deg2rad(40.0) * (s - 0.5)
    vy = v.copy()
    vy[:, 1] = np.cos(a) * v[:, 1] - np.sin(a) * v[:, 2]
    vy[:, 2] = np.sin(a) * v[:, 1] + np.cos(a) * v[:, 2]
    return v, vy, m.faces, f"bench_mesh({n}) / twisted copy"


def match_defaults() -> dict[str, Any]:
    """Keyword defaults of ``torchfmap.pipeline.match`` (descriptor counts and energy weights)."""
    return {
        name: p.default
        for name, p in inspect.signature(match).parameters.items()
        if p.default is not inspect.Parameter.empty and name not in ("landmarks", "basis", "refine", "times")
    }


def run_ours(vx, vy, f, args, refine: str | None, landmarks) -> tuple[np.ndarray, float, dict]:
    samples = args.zoomout_samples if refine == "zoomout-sub" else None
    refine = "zoomout" if refine == "zoomout-sub" else refine
    t0 = time.perf_counter()
    x, y = torchfmap.Mesh(vx.copy(), f.copy()), torchfmap.Mesh(vy.copy(), f.copy())
    res = match(
        x,
        y,
        landmarks=landmarks,
        basis="laplacian",
        k=args.k,
        refine=refine,
        n_descriptors=args.n_descr,
        k_descriptors=args.k_descr,
        zoomout_samples=samples,
    )
    return res.p2p_yx, time.perf_counter() - t0, res.timings


def warm_up() -> None:
    log("warm-up on bench_mesh(1500) pairs")
    m = bench_mesh(1500)
    x = torchfmap.Mesh(m.vertices, m.faces)
    y = torchfmap.Mesh(m.vertices * np.array([1.0, 1.05, 0.95]), m.faces)
    for refine in (None, "zoomout"):
        match(x, y, basis="laplacian", k=20, refine=refine)
        run_pyfm(x, y, k=20, refine=("zoomout",) if refine else ())


class IdentityErrors:
    """Normalised geodesic errors at a fixed random subset of y's vertices (identity ground truth)."""

    def __init__(self, vx: np.ndarray, f: np.ndarray, n_points: int, seed: int = 0) -> None:
        self.mesh = torchfmap.Mesh(vx, f)
        n = self.mesh.n_vertices
        self.rows = np.sort(np.random.default_rng(seed).choice(n, min(n_points, n), replace=False))
        t0 = time.perf_counter()
        self.dist = torchfmap.GeodesicSolver(self.mesh).distances(self.rows)
        log(f"  {len(self.rows)} geodesic distance rows in {time.perf_counter() - t0:.1f} s")

    def __call__(self, p2p_yx: np.ndarray) -> np.ndarray:
        pred = np.asarray(p2p_yx)[self.rows]
        err = np.maximum(self.dist[np.arange(len(self.rows)), pred], 0.0)
        err[pred == self.rows] = 0.0
        return err / np.sqrt(self.mesh.area)


def short_phases(phases: dict[str, float]) -> str:
    return ", ".join(f"{key} {val:.1f}" for key, val in phases.items())


def bench_match(args) -> None:
    vx, vy, f, label = wolf_pair() if args.pair == "wolf" else synthetic_pair(args.n)
    n = len(vx)
    log(f"pair {label}: {n} vertices, {len(f)} faces")
    landmarks = None
    if args.landmarks:
        seeds = torchfmap.farthest_point_sampling(torchfmap.Mesh(vx, f), args.landmarks, metric="euclidean")
        landmarks = np.stack([seeds, seeds], axis=1)
    warm_up()
    runs: dict[tuple[str, str], list[dict]] = {}
    for rep in range(args.repeats):
        for refine in (None, "zoomout", "zoomout-sub"):
            tag = refine or "none"
            log(f"round {rep + 1}/{args.repeats}: ours, refine={tag} (load {load1():.1f})")
            p2p, sec, phases = run_ours(vx, vy, f, args, refine, landmarks)
            eig = max(args.k, args.k_descr, 2 * args.k if refine else 0)
            runs.setdefault(("ours", tag), []).append(
                {"p2p": p2p, "time": sec, "phases": phases, "load": load1(), "eig": eig}
            )
            log(f"  {sec:.1f} s: {short_phases(phases)}")
            log(f"round {rep + 1}/{args.repeats}: pyFM, refine={tag} (load {load1():.1f})")
            extra = (refine,) if refine else ()
            pf = run_pyfm(
                torchfmap.Mesh(vx, f),
                torchfmap.Mesh(vy, f),
                k=args.k,
                landmarks=landmarks,
                refine=extra,
                n_descr=args.n_descr,
                k_descr=args.k_descr,
                zoomout_samples=args.zoomout_samples,
            )
            run = {"p2p": pf.p2p[refine], "time": pf.times[refine], "phases": pf.phases, "load": load1()}
            runs.setdefault(("pyFM", tag), []).append(run | {"n_descr": pf.n_descr, "eig": pf.k_process})
            log(f"  {pf.times[refine]:.1f} s: {short_phases(pf.phases)}")

    log(f"errors on {args.eval_points} vertices")
    errors = IdentityErrors(vx, f, args.eval_points)
    rows = []
    for (method, tag), rs in runs.items():
        err = errors(rs[-1]["p2p"])
        best = min(rs, key=lambda r: r["time"])
        rows.append(
            {
                "method": method,
                "refine": tag,
                "V": n,
                "k": args.k,
                "eigenpairs": rs[-1]["eig"],
                "descriptors": rs[-1].get("n_descr", args.n_descr + 2 * args.landmarks),
                "time [s] (median)": statistics.median(r["time"] for r in rs),
                "min": best["time"],
                "phases of the fastest run [s]": short_phases(best["phases"]),
                "mean err": float(err.mean()),
                "AUC": auc(err),
                "load": "/".join(f"{r['load']:.1f}" for r in rs),
            }
        )
    cols = list(rows[0])
    print(
        f"## (a) Whole pipeline on {label}: {n:,} vertices, k={args.k}, "
        f"{args.landmarks or 'no'} landmarks, median of {args.repeats} round(s)\n"
    )
    print(markdown(rows, cols))
    med = {(r["method"], r["refine"]): r["time [s] (median)"] for r in rows}
    ratio_rows = []
    for tag in ("none", "zoomout", "zoomout-sub"):
        ratio = med[("pyFM", tag)] / med[("ours", tag)]
        ratio_rows.append(
            {
                "refine": tag,
                "ours [s]": med[("ours", tag)],
                "pyFM [s]": med[("pyFM", tag)],
                "pyFM / ours": ratio,
                ">= 3x": "yes" if ratio >= 3 else "NO",
            }
        )
    print("\n" + markdown(ratio_rows, list(ratio_rows[0])))
    ours = {key: val for key, val in match_defaults().items() if key.startswith("w_")}
    ours["w_lap"] = ours["w_lap"] if ours["w_lap"] is not None else W_LAP["laplacian"]
    print(
        f"\nours: match weights {ours}, {args.n_descr} WKS from {args.k_descr} eigenpairs"
        f"{' + 2 heat descriptors per landmark' if args.landmarks else ''}. pyFM: fit weights {PYFM_FIT}, "
        f"{args.n_descr} WKS from {args.k_descr} eigenpairs"
        f"{f' + {args.n_descr} landmark WKS per landmark' if args.landmarks else ''}. "
        "Phases: ours = match().timings, pyFM = preprocess (eigenpairs + WKS), fit, p2p, zoomout "
        "(refinement + its p2p). Errors: mean normalised "
        f"geodesic error and AUC at the same {len(errors.rows)} random vertices of y (last round's map). "
        "load = 1-min load average after each round's run.\n"
    )


# -- (b) nearest neighbours ----------------------------------------------------------------------
def traced_peak(fn: Callable[[], Any]) -> tuple[float, Any]:
    """tracemalloc peak (MiB) above the current allocations during one call of ``fn``."""
    gc.collect()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        out = fn()
        return (tracemalloc.get_traced_memory()[1] - base) / MiB, out
    finally:
        tracemalloc.stop()


def _status_mib(key: str) -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _malloc_trim() -> None:
    """Give freed heap memory back to the OS (glibc), so that a call reusing it counts in RSS."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def timed_rss(fn: Callable[[], Any]) -> tuple[float, float, Any]:
    """Wall time of one call and its peak resident memory above the start (MiB; Linux, else nan).

    Freed heap memory is first given back to the OS (``malloc_trim``) and the high-water mark
    ``VmHWM`` reset through ``/proc/self/clear_refs``, so the peak counts everything the call
    touches: numpy, BLAS buffers, scikit-learn's C++ buffers.
    """
    gc.collect()
    _malloc_trim()
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        start = _status_mib("VmRSS")
    except OSError:
        start = float("nan")
    t0 = time.perf_counter()
    out = fn()
    sec = time.perf_counter() - t0
    return sec, _status_mib("VmHWM") - start, out


def bench_nn(args) -> None:
    from pyFM.spectral.nearest_neighbor import knn_query

    n, d = args.nn_n, args.nn_dim
    rng = np.random.default_rng(args.seed)
    log(f"nearest neighbours: {n} x {n} in {d} dimensions")
    reference = rng.standard_normal((n, d))
    perm = rng.permutation(n)
    query = reference[perm] + 1e-3 * rng.standard_normal((n, d))
    naive = n * n * 8
    cases: list[tuple[str, Callable[[], np.ndarray]]] = [
        (
            f"ours block_bytes={mb} MiB",
            lambda mb=mb: nearest_neighbor(query, reference, method="brute", block_bytes=mb * MiB),
        )
        for mb in args.nn_blocks
    ]
    cases.append(("pyFM knn_query brute (sklearn)", lambda: knn_query(reference, query, method="brute")))
    rows = []
    for name, fn in cases:
        log(f"  {name}: timed call (load {load1():.1f})")
        sec, rss, idx = timed_rss(fn)
        correct = float(np.mean(idx == perm))
        del idx
        log(f"  {name}: {sec:.1f} s; traced call")
        peak, _ = traced_peak(fn)
        rows.append(
            {
                "method": name,
                "M x N x D": f"{n:,} x {n:,} x {d}",
                "time [s]": sec,
                "tracemalloc peak [MiB]": peak,
                "peak RSS [MiB]": rss,
                "RSS / naive": rss * MiB / naive,
                "correct": correct,
                "load": load1(),
            }
        )
    print(f"## (b) p2p conversion: nearest neighbour of {n:,} queries among {n:,} points, {d} dims\n")
    print(markdown(rows, list(rows[0])))
    print(
        f"\nNaive full (M, N) float64 distance matrix: {naive / 2**30:.1f} GiB ({naive / 1e9:.1f} GB), "
        f"not allocated. Inputs: two {n * d * 8 / MiB:.0f} MiB arrays, not counted. tracemalloc peak: "
        "above the inputs during a second, traced call; it sees numpy allocations only (not BLAS "
        "buffers, not scikit-learn's C++ chunk buffers). peak RSS: resident-memory high-water mark "
        "(VmHWM, reset before the call) minus the resident memory at the start of the timed call: "
        "everything touched. correct = fraction of queries whose known nearest neighbour was found.\n"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pair", choices=("wolf", "synthetic"), default="wolf")
    parser.add_argument("--n", type=int, default=20000, help="vertices of the synthetic pair")
    parser.add_argument("--k", type=int, default=100)
    parser.add_argument("--landmarks", type=int, default=0, help="farthest-point landmark pairs (i, i)")
    defaults = match_defaults()
    parser.add_argument("--n-descr", type=int, default=defaults["n_descriptors"], help="WKS descriptors")
    parser.add_argument("--k-descr", type=int, default=defaults["k_descriptors"], help="eigenpairs of WKS")
    parser.add_argument(
        "--zoomout-samples", type=int, default=2000, help="FPS samples per shape of 'zoomout-sub'"
    )
    parser.add_argument("--repeats", type=int, default=1, help="rounds of the four runs (median)")
    parser.add_argument("--eval-points", type=int, default=2000, help="vertices of y scored")
    parser.add_argument("--nn-n", type=int, default=50000)
    parser.add_argument("--nn-dim", type=int, default=100)
    parser.add_argument("--nn-blocks", default="32,128", help="block_bytes in MiB, comma-separated")
    parser.add_argument("--no-match", action="store_true")
    parser.add_argument("--no-nn", action="store_true")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.nn_blocks = [int(b) for b in args.nn_blocks.split(",") if b]
    t_start, load_start = time.perf_counter(), os.getloadavg()
    print(
        f"# Matching speed ({os.cpu_count()} CPUs; numpy {np.__version__}, scipy {version('scipy')}, "
        f"pyfmaps {version('pyfmaps')}, scikit-learn {version('scikit-learn')}; load average "
        f"1/5/15 min at start {'/'.join(f'{x:.1f}' for x in load_start)})\n"
    )
    if not args.no_match:
        bench_match(args)
    if not args.no_nn:
        bench_nn(args)
    print(
        f"Load average at end {'/'.join(f'{x:.1f}' for x in os.getloadavg())}; total "
        f"{time.perf_counter() - t_start:.0f} s."
    )


if __name__ == "__main__":
    main()
