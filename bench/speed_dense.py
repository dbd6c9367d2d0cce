"""Suite ``speed``, dense meshes: matching with ZoomOut from ~70K to ~1.1M vertices, the
exhaustive search against the local one (``fmap.nearest``), time, peak memory and error.

The pairs are the shared TOSCA hi-res wolf0 / wolf1 Loop-subdivided 2-4 times (shared
connectivity, so vertex i matches vertex i). Every time is wall-clock against a baseline run in
the same process: both shapes' Laplacians and the eigenpairs the match needs.
"""

from __future__ import annotations

import time

import numpy as np

import torchfmap
import torchfmap.kinds.refiners as refiners

from .common import Report, Settings, Skip, load1, log, require_data, reset_peak_rss, status_mib


def wolf_pair(levels: int) -> tuple[torchfmap.Mesh, torchfmap.Mesh]:
    """wolf0 / wolf1 Loop-subdivided ``levels`` times (identity ground truth)."""
    import trimesh

    meshes = [torchfmap.load_mesh(require_data(f"tosca_hires_wolf/{n}.off")) for n in ("wolf0", "wolf1")]
    out = [trimesh.remesh.subdivide_loop(m.vertices, m.faces, iterations=levels) for m in meshes]
    if not np.array_equal(out[0][1], out[1][1]):
        raise Skip("the wolves' subdivisions differ in connectivity: no identity ground truth")
    return tuple(torchfmap.Mesh(np.asarray(v), np.asarray(f, dtype=np.int64)) for v, f in out)


def identity_errors(mesh_x: torchfmap.Mesh, maps: list, points: np.ndarray, chunk: int = 25) -> np.ndarray:
    """Normalised geodesic errors ``(len(maps), len(points))`` of each ``p2p_yx`` in ``maps`` at
    the vertices ``points`` under the identity ground truth, each distance row solved once,
    ``chunk`` at a time (memory ``chunk x V``)."""
    solver = torchfmap.GeodesicSolver(mesh_x)
    err = np.empty((len(maps), len(points)))
    for lo in range(0, len(points), chunk):
        rows = points[lo : lo + chunk]
        d = solver.distances(rows)
        for i, p2p in enumerate(maps):
            err[i, lo : lo + chunk] = np.maximum(d[np.arange(len(rows)), p2p[rows]], 0.0)
    for i, p2p in enumerate(maps):
        err[i, p2p[points] == points] = 0.0
    return err / np.sqrt(mesh_x.area)


def dense(cfg: Settings, report: Report) -> None:
    """Match with ZoomOut on dense pairs: the exhaustive nearest-neighbour search (where it runs
    in reasonable time) against the local search around surface samples, with time as a ratio
    of both shapes' Laplacians and eigenpairs, peak memory and mean geodesic error."""
    rows = []
    for levels in cfg.levels:
        x, y = wolf_pair(levels)
        points = np.sort(np.random.default_rng(0).choice(y.n_vertices, cfg.eval_points, replace=False))
        paths = ["local", "exhaustive"] if x.n_vertices <= cfg.exhaustive_max else ["local"]
        for path in paths:
            limit = refiners.LOCAL_SEARCH_PAIRS
            if path == "exhaustive":  # the module constant past which the local search is used
                refiners.LOCAL_SEARCH_PAIRS = float("inf")
            try:
                reset_peak_rss()
                start = status_mib("VmRSS")
                t0 = time.perf_counter()
                shapes = tuple(torchfmap.prepare_shape(m, 2 * cfg.k) for m in (x, y))
                t_base = time.perf_counter() - t0
                log(f"{x.n_vertices:,} vertices: Laplacians + {2 * cfg.k} eigenpairs {t_base:.1f} s")
                t0 = time.perf_counter()
                res = torchfmap.match(x, y, k=cfg.k, refine="zoomout", shapes=shapes)
                t_match = time.perf_counter() - t0
                peak = status_mib("VmHWM") - start
            finally:
                refiners.LOCAL_SEARCH_PAIRS = limit
            raw, refined = identity_errors(x, [res.p2p_yx_initial, res.p2p_yx], points)
            rows.append(
                {
                    "V": x.n_vertices,
                    "search": path,
                    "Laplacians + eigenpairs [s]": t_base,
                    "match + ZoomOut [s]": t_match,
                    "match / (Laplacians + eigenpairs)": t_match / t_base,
                    "phases [s]": ", ".join(f"{k} {v:.1f}" for k, v in res.timings.items()),
                    "peak memory [GiB]": peak / 1024,
                    "raw error x100": 100 * raw.mean(),
                    "ZoomOut error x100": 100 * refined.mean(),
                    "load": load1(),
                }
            )
            log(str(rows[-1]))
            report.rows_csv(rows)
    for r in rows:
        base = [b for b in rows if b["V"] == r["V"] and b["search"] == "exhaustive"]
        if base:
            r["error / exhaustive"] = r["ZoomOut error x100"] / base[0]["ZoomOut error x100"]
            r["time / exhaustive"] = r["match + ZoomOut [s]"] / base[0]["match + ZoomOut [s]"]
    report.table(
        f"match(x, y, k={cfg.k}, refine='zoomout') on wolf0 / wolf1 Loop-subdivided {cfg.levels} times",
        rows,
        note=f"Baseline in the same process: both shapes' Laplacians and {2 * cfg.k} eigenpairs (what the "
        f"match needs, ZoomOut grows k to 2k). Peak memory: VmHWM above the start. Errors: mean "
        f"normalised geodesic error at the same {cfg.eval_points} random vertices, identity ground "
        f"truth. The exhaustive search runs up to {cfg.exhaustive_max:,} vertices.",
    )


CASES = {"dense": dense}
