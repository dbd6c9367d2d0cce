"""Benchmark: the whole matching pipeline at ~17K vertices (ours vs pyFM) and 50K x 50K point-map conversion.

Run by hand from the repository root (prints markdown tables to stdout, progress to stderr, and
writes them to ``bench/results/match_speed.md``)::

    python3 bench/match_speed.py                          # subdivided TOSCA wolf pair, k=100; NN 50K
    python3 bench/match_speed.py --pair synthetic --n 20000 --repeats 3
    python3 bench/match_speed.py --no-nn                  # or --no-match
    python3 bench/match_speed.py --pair synthetic --n 2000 --k 20 --eval-points 200 --no-nn  # quick

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
subsampled pair), and every cell is the median over rounds. ``pyFM / ours`` is the ratio of
those medians (target: >= 3). Errors: mean normalised geodesic error (heat method on x) and AUC
on the same ``--eval-points`` random vertices of y for all maps (distance rows computed once).
The 1-minute load average is recorded with every run: another job may share the CPUs.

(b) Point-map conversion (50K x 50K nearest neighbours, ours vs pyFM's ``knn_query``):
``bench/nn_speed.py``, run here too unless ``--no-nn`` (its options ``--nn-*`` are accepted).
"""

from __future__ import annotations

import argparse
import inspect
import statistics
import time
from typing import Any

import nn_speed
import numpy as np
from _common import Report, int_list, load1, load_note, log, markdown, require_data, versions
from _meshes import bench_mesh
from _pyfm import PYFM_FIT, run_pyfm

import torchfmap
from torchfmap.eval import auc
from torchfmap.kinds import KINDS
from torchfmap.pipeline import match

WOLVES = ("tosca_hires_wolf/wolf0.off", "tosca_hires_wolf/wolf1.off")


# -- (a) whole pipeline --------------------------------------------------------------------------
def wolf_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """Loop-subdivided TOSCA wolf0 / wolf1 (shared connectivity: identity ground truth)."""
    import trimesh

    paths = [require_data(name) for name in WOLVES]  # exits with a message if absent
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


def run_pyfm_once(vx, vy, f, args, refine: str | None, landmarks) -> dict[str, Any]:
    pf = run_pyfm(
        torchfmap.Mesh(vx, f),
        torchfmap.Mesh(vy, f),
        k=args.k,
        landmarks=landmarks,
        refine=(refine,) if refine else (),
        n_descr=args.n_descr,
        k_descr=args.k_descr,
        zoomout_samples=args.zoomout_samples,
    )
    log(f"  {pf.times[refine]:.1f} s: {short_phases(pf.phases)}")
    run = {"p2p": pf.p2p[refine], "time": pf.times[refine], "phases": pf.phases, "load": load1()}
    return run | {"n_descr": pf.n_descr, "eig": pf.k_process}


def run_rounds(vx, vy, f, args, landmarks) -> dict[tuple[str, str], list[dict]]:
    """``--repeats`` rounds of ours, pyFM for every refinement, in that order."""
    runs: dict[tuple[str, str], list[dict]] = {}
    for rep in range(args.repeats):
        for refine in (None, "zoomout", "zoomout-sub"):
            tag = refine or "none"
            log(f"round {rep + 1}/{args.repeats}: ours, refine={tag} (load {load1():.1f})")
            p2p, sec, phases = run_ours(vx, vy, f, args, refine, landmarks)
            eig = max(args.k, args.k_descr, 2 * args.k if refine else 0)
            run = {"p2p": p2p, "time": sec, "phases": phases, "load": load1(), "eig": eig}
            runs.setdefault(("ours", tag), []).append(run)
            log(f"  {sec:.1f} s: {short_phases(phases)}")
            log(f"round {rep + 1}/{args.repeats}: pyFM, refine={tag} (load {load1():.1f})")
            runs.setdefault(("pyFM", tag), []).append(run_pyfm_once(vx, vy, f, args, refine, landmarks))
    return runs


def result_rows(runs, errors: IdentityErrors, n: int, args) -> list[dict[str, Any]]:
    """Per method and refinement: median and min time, phases of the fastest run, errors of the last."""
    rows = []
    for (method, tag), rs in runs.items():
        err = errors(rs[-1]["p2p"])
        best = min(rs, key=lambda r: r["time"])
        row: dict[str, Any] = {
            "method": method,
            "refine": tag,
            "V": n,
            "k": args.k,
            "eigenpairs": rs[-1]["eig"],
        }
        row["descriptors"] = rs[-1].get("n_descr", args.n_descr + 2 * args.landmarks)
        row |= {"time [s] (median)": statistics.median(r["time"] for r in rs), "min": best["time"]}
        row["phases of the fastest run [s]"] = short_phases(best["phases"])
        row |= {"mean err": float(err.mean()), "AUC": auc(err)}
        row["load"] = "/".join(f"{r['load']:.1f}" for r in rs)
        rows.append(row)
    return rows


def ratio_rows(rows: list[dict]) -> list[dict[str, Any]]:
    """``pyFM / ours`` of the median times, per refinement (target >= 3)."""
    med = {(r["method"], r["refine"]): r["time [s] (median)"] for r in rows}
    out = []
    for tag in ("none", "zoomout", "zoomout-sub"):
        ratio = med[("pyFM", tag)] / med[("ours", tag)]
        out.append({"refine": tag, "ours [s]": med[("ours", tag)], "pyFM [s]": med[("pyFM", tag)]})
        out[-1] |= {"pyFM / ours": ratio, ">= 3x": "yes" if ratio >= 3 else "NO"}
    return out


def settings_note(args, n_eval: int) -> str:
    ours = {key: val for key, val in match_defaults().items() if key.startswith("w_")}
    ours["w_lap"] = ours["w_lap"] if ours["w_lap"] is not None else KINDS["laplacian"].w_lap
    lmk = args.landmarks
    return (
        f"ours: match weights {ours}, {args.n_descr} WKS from {args.k_descr} eigenpairs"
        f"{' + 2 heat descriptors per landmark' if lmk else ''}. pyFM: fit weights {PYFM_FIT}, "
        f"{args.n_descr} WKS from {args.k_descr} eigenpairs"
        f"{f' + {args.n_descr} landmark WKS per landmark' if lmk else ''}. "
        "Phases: ours = match().timings, pyFM = preprocess (eigenpairs + WKS), fit, p2p, zoomout "
        "(refinement + its p2p). Errors: mean normalised "
        f"geodesic error and AUC at the same {n_eval} random vertices of y (last round's map). "
        "load = 1-min load average after each round's run."
    )


def bench_match(args, out: Report) -> None:
    vx, vy, f, label = wolf_pair() if args.pair == "wolf" else synthetic_pair(args.n)
    n = len(vx)
    log(f"pair {label}: {n} vertices, {len(f)} faces")
    landmarks = None
    if args.landmarks:
        seeds = torchfmap.farthest_point_sampling(torchfmap.Mesh(vx, f), args.landmarks, metric="euclidean")
        landmarks = np.stack([seeds, seeds], axis=1)
    warm_up()
    runs = run_rounds(vx, vy, f, args, landmarks)
    log(f"errors on {args.eval_points} vertices")
    errors = IdentityErrors(vx, f, args.eval_points)
    rows = result_rows(runs, errors, n, args)
    out.table(
        f"## (a) Whole pipeline on {label}: {n:,} vertices, k={args.k}, "
        f"{args.landmarks or 'no'} landmarks, median of {args.repeats} round(s)",
        rows,
    )
    out.add(markdown(ratio_rows(rows)), settings_note(args, len(errors.rows)))


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
    nn_speed.add_arguments(parser)
    parser.add_argument("--no-match", action="store_true")
    parser.add_argument("--no-nn", action="store_true")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.nn_blocks = int_list(args.nn_blocks)
    t_start = time.perf_counter()
    out = Report("match_speed")
    out.add(f"# Matching speed ({versions('scipy', 'pyfmaps', 'scikit-learn')}; {load_note()} at start)")
    if not args.no_match:
        bench_match(args, out)
    if not args.no_nn:
        out.add(*nn_speed.bench_nn(args))
    out.add(f"{load_note()} at end; total {time.perf_counter() - t_start:.0f} s.")
    out.save()


if __name__ == "__main__":
    main()
