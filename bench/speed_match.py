"""Suite ``speed``, whole jobs: the matching pipeline against pyFM, point-map conversion (nearest
neighbours) against pyFM / scikit-learn, evaluating a collection (prepared shapes, workers), the
landmark default's time, and threads.

Every time is wall-clock in this process against a baseline run in the same process; the
1-minute load average is recorded beside, since another job may share the CPUs.
"""

from __future__ import annotations

import ctypes
import gc
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

import torchfmap
from torchfmap.evaluate.collection import evaluate_pairs, pool_threads
from torchfmap.evaluate.scores import auc, discover_pairs
from torchfmap.fmap import nearest_neighbor

from .common import (
    MiB,
    Report,
    Settings,
    Skip,
    bench_mesh,
    load1,
    log,
    require_data,
    reset_peak_rss,
    status_mib,
    timed,
    traced_peak_mib,
)
from .pairs import PYFM_FIT, Pair, pyfm_missing, run_pyfm


def twisted(mesh, degrees: float) -> np.ndarray:
    """Vertices of ``mesh`` twisted about x by ``degrees`` over its length (near-isometric)."""
    v = mesh.vertices
    a = np.deg2rad(degrees) * ((v[:, 0] - v[:, 0].min()) / np.ptp(v[:, 0]) - 0.5)
    c, s = np.cos(a), np.sin(a)
    return np.stack([v[:, 0], c * v[:, 1] - s * v[:, 2], s * v[:, 1] + c * v[:, 2]], axis=1)


def match_speed(cfg: Settings, report: Report) -> None:
    """The whole matching pipeline (no refinement, ZoomOut, subsampled ZoomOut) against pyFM's,
    same k and descriptors, on a 17K-vertex pair with identity ground truth."""
    if cfg.pair == "wolf":  # Loop-subdivided TOSCA wolf0 / wolf1 (shared connectivity)
        import trimesh

        a, b = (torchfmap.load_mesh(require_data(f"tosca_hires_wolf/{n}.off")) for n in ("wolf0", "wolf1"))
        vx, f = trimesh.remesh.subdivide_loop(a.vertices, a.faces, iterations=1)
        vy, fb = trimesh.remesh.subdivide_loop(b.vertices, b.faces, iterations=1)
        if not np.array_equal(f, fb):
            raise Skip("the wolves' subdivisions differ in connectivity: no identity ground truth")
        label = "wolf0/wolf1 Loop x1"
    else:
        m = bench_mesh(cfg.n)
        vx, vy, f, label = m.vertices, twisted(m, 40.0), m.faces, f"bench_mesh({cfg.n}) / twisted copy"
    vx, vy, f = np.asarray(vx), np.asarray(vy), np.asarray(f, dtype=np.int64)
    defaults = {"n_descriptors": 20, "k_descriptors": 100}
    nd, kd = cfg.n_descriptors or defaults["n_descriptors"], cfg.k_descriptors or defaults["k_descriptors"]
    lmk = None
    if cfg.landmarks:
        seeds = torchfmap.farthest_point_sampling(torchfmap.Mesh(vx, f), cfg.landmarks, metric="euclidean")
        lmk = np.stack([seeds, seeds], axis=1)
    use_pyfm = cfg.pyfm and not pyfm_missing()
    report.add(pyfm_missing() if cfg.pyfm else "")
    m = bench_mesh(1500)  # warm-up of both pipelines
    torchfmap.match(
        m, m.copy(m.vertices * np.array([1.0, 1.05, 0.95])), basis="laplacian", k=20, refine="zoomout"
    )
    runs: dict[tuple[str, str], list[dict]] = {}
    for _ in range(cfg.repeats):
        for refine in ("none", "zoomout", "zoomout-sub"):
            t0 = time.perf_counter()
            x, y = (
                torchfmap.Mesh(vx.copy(), f.copy()),
                torchfmap.Mesh(vy.copy(), f.copy()),
            )  # construction timed
            res = torchfmap.match(
                x,
                y,
                landmarks=lmk,
                basis="laplacian",
                k=cfg.k,
                refine=None if refine == "none" else "zoomout",
                n_descriptors=nd,
                k_descriptors=kd,
                zoomout_samples=cfg.zoomout_samples if refine == "zoomout-sub" else None,
            )
            runs.setdefault(("ours", refine), []).append(
                {"p2p": res.p2p_yx, "time": time.perf_counter() - t0, "phases": res.timings, "load": load1()}
            )
            if use_pyfm:
                extra = () if refine == "none" else (refine,)
                pf = run_pyfm(
                    torchfmap.Mesh(vx, f),
                    torchfmap.Mesh(vy, f),
                    k=cfg.k,
                    landmarks=lmk,
                    refine=extra,
                    n_descr=nd,
                    k_descr=kd,
                    zoomout_samples=cfg.zoomout_samples,
                )
                key = None if refine == "none" else refine
                runs.setdefault(("pyFM", refine), []).append(
                    {"p2p": pf.p2p[key], "time": pf.times[key], "phases": pf.phases, "load": load1()}
                )
    mesh_x = torchfmap.Mesh(vx, f)  # errors at the same random vertices of y for every map
    pts = np.sort(np.random.default_rng(0).choice(len(vx), min(cfg.eval_points, len(vx)), replace=False))
    dist = torchfmap.GeodesicSolver(mesh_x).distances(pts)
    rows = []
    for (method, refine), rs in runs.items():
        pred = np.asarray(rs[-1]["p2p"])[pts]
        err = np.maximum(dist[np.arange(len(pts)), pred], 0.0)
        err[pred == pts] = 0.0
        err /= np.sqrt(mesh_x.area)
        best = min(rs, key=lambda r: r["time"])
        med = statistics.median(r["time"] for r in rs)
        rows.append(
            {
                "method": method,
                "refine": refine,
                "V": len(vx),
                "k": cfg.k,
                "time [s] (median)": med,
                "phases of the fastest [s]": ", ".join(f"{k} {v:.1f}" for k, v in best["phases"].items()),
                "mean err": float(err.mean()),
                "AUC": auc(err),
                "load": "/".join(f"{r['load']:.1f}" for r in rs),
            }
        )
    for r in rows:
        base = [x for x in rows if x["method"] == "pyFM" and x["refine"] == r["refine"]]
        if base:
            r["pyFM / ours"] = (
                base[0]["time [s] (median)"] / r["time [s] (median)"] if r["method"] == "ours" else 1.0
            )
    report.table(
        f"Whole pipeline on {label}: {len(vx):,} vertices, k={cfg.k}, {cfg.landmarks or 'no'} landmarks",
        rows,
        note=f"Both: {nd} WKS descriptors from {kd} eigenpairs; ZoomOut k -> 2k in steps of k // "
        f"10; zoomout-sub on "
        f"{cfg.zoomout_samples} FPS samples per shape. pyFM fit weights {PYFM_FIT}. Errors: mean "
        f"normalised geodesic "
        f"error and AUC at the same {len(pts)} random vertices (last round's map). Target: pyFM / ours >= 3.",
    )


def _timed_rss(fn):
    """Wall time of one call and its peak resident memory above the start (MiB; nan off Linux):
    freed heap given back first (``malloc_trim``), ``VmHWM`` reset, so every buffer counts."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    start = status_mib("VmRSS") if reset_peak_rss() else float("nan")
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, status_mib("VmHWM") - start, out


def nn_speed(cfg: Settings, report: Report) -> None:
    """Point-map conversion: brute-force nearest neighbours at 50K x 50K, ours (bounded memory)
    against pyFM's knn_query (scikit-learn)."""
    rng = np.random.default_rng(cfg.seed)
    n, d = cfg.n, cfg.dim
    reference = rng.standard_normal((n, d))
    perm = rng.permutation(n)
    query = reference[perm] + 1e-3 * rng.standard_normal((n, d))  # the answer is known
    methods = [
        (
            f"ours block_bytes={mb} MiB",
            lambda mb=mb: nearest_neighbor(query, reference, search="brute", block_bytes=mb * MiB),
        )
        for mb in cfg.blocks_mib
    ]
    if cfg.pyfm and not pyfm_missing():
        from pyFM.spectral.nearest_neighbor import knn_query

        methods.append(
            ("pyFM knn_query brute (sklearn)", lambda: knn_query(reference, query, method="brute"))
        )
    else:
        report.add(pyfm_missing())
    rows = []
    for name, fn in methods:
        sec, rss, idx = _timed_rss(fn)
        rows.append(
            {
                "method": name,
                "M x N x D": f"{n:,} x {n:,} x {d}",
                "time [s]": sec,
                "tracemalloc peak [MiB]": traced_peak_mib(fn)[0],
                "peak RSS [MiB]": rss,
                "RSS / naive": rss * MiB / (n * n * 8),
                "correct": float(np.mean(idx == perm)),
                "load": load1(),
            }
        )
    for r in rows:
        r[f"t / {rows[-1]['method']}"] = r["time [s]"] / rows[-1]["time [s]"]
    report.table(
        f"Nearest neighbour of {n:,} queries among {n:,} points, {d} dimensions",
        rows,
        note=f"Naive (M, N) float64 distance matrix: {n * n * 8 / 2**30:.1f} GiB, not allocated. "
        f"tracemalloc: numpy "
        "allocations of a second call; peak RSS: VmHWM (reset before the call) above the resident "
        "size at its start.",
    )


def eval_speed(cfg: Settings, report: Report) -> None:
    """Evaluating a collection: each pair on its own against shapes prepared once, one process
    against a pool of workers (bit-identical results with the same threads)."""
    collections = []
    if cfg.dev:
        try:
            collections.append(("tosca5k_dev test pairs", require_data("tosca5k_dev")))
        except Skip as why:
            log(f"skipped: {why}")
    tmp = tempfile.TemporaryDirectory()
    if cfg.synthetic:
        base = bench_mesh(cfg.synthetic_v)
        for i in range(cfg.synthetic):
            bent = twisted(base, 60.0 * i / max(cfg.synthetic - 1, 1))
            torchfmap.save_mesh(torchfmap.Mesh(bent, base.faces), Path(tmp.name) / f"shape{i:03d}.off")
        collections.append((f"synthetic, {cfg.synthetic} x {cfg.synthetic_v} V", Path(tmp.name)))
    rows = []
    with tmp:
        for label, folder in collections:
            pairs = list(discover_pairs(folder))
            n_base = min(cfg.baseline_pairs, len(pairs))
            t0 = time.perf_counter()
            for pair in pairs[:n_base]:
                evaluate_pairs([pair])  # both meshes prepared again for every pair
            base = (time.perf_counter() - t0) / max(n_base, 1) * len(pairs)
            threads = pool_threads(cfg.workers)
            runs = {}
            for name, kw in (
                ("prepared, 1 process", {}),
                (f"1 process, {threads} thread(s)", {"threads": threads}),
                (
                    f"{cfg.workers} workers x {threads} thread(s)",
                    {"workers": cfg.workers, "threads": threads},
                ),
            ):
                t0 = time.perf_counter()
                runs[name] = (evaluate_pairs(pairs, **kw), time.perf_counter() - t0)
            same = [
                np.array_equal(a.errors, b.errors)
                for a, b in zip(*(r[0] for r in list(runs.values())[1:]), strict=True)
            ]
            rows.append(
                {
                    "collection": label,
                    "pairs": len(pairs),
                    "method": "per pair (extrapolated)",
                    "time [s]": base,
                    "speed-up": 1.0,
                }
            )
            for name, (res, t) in runs.items():
                rows.append(
                    {
                        "collection": label,
                        "pairs": len(pairs),
                        "method": name,
                        "time [s]": t,
                        "speed-up": base / t,
                        "mean error": float(np.mean([r.errors.mean() for r in res])),
                        "load": load1(),
                    }
                )
            rows[-1]["pool == 1 process (same threads)"] = "yes" if all(same) else "NO"
    report.table(
        "Wall time of the whole collection",
        rows,
        note=f"per pair: each pair evaluated on its own on the first {cfg.baseline_pairs} pairs, "
        f"extrapolated (linear "
        "by construction). speed-up: against it. Same match settings everywhere (eval's defaults).",
    )


def landmark_timing(cfg: Settings, report: Report) -> None:
    """Time of match's landmark default (it chooses the basis) over eigenbasis ZoomOut, from the meshes."""
    rows = []
    for spec in cfg.pairs:
        pair = Pair(spec)
        lm = pair.landmarks(cfg.L)
        run = lambda basis, p=pair, lm=lm: torchfmap.match(  # noqa: E731
            p.x, p.y, landmarks=lm, k=cfg.k, refine="zoomout", basis=basis
        )  # noqa: E731
        run(None)  # warm-up
        times: dict[str, list[float]] = {"default": [], "laplacian": []}
        for _ in range(cfg.repeats):
            for name in times:
                t, _, res = timed(lambda name=name: run(None if name == "default" else name))  # noqa: B023
                times[name].append(t)
                if name == "default":
                    chosen = res.kind
        med = {n: statistics.median(t) for n, t in times.items()}
        rows.append(
            {
                "pair": spec,
                "method": "default",
                "chosen": chosen,
                "time [s]": med["default"],
                "t / eigenbasis ZoomOut": med["default"] / med["laplacian"],
            }
        )
        rows.append(
            {
                "pair": spec,
                "method": "laplacian ZoomOut",
                "time [s]": med["laplacian"],
                "t / eigenbasis ZoomOut": 1.0,
            }
        )
    report.table(f"Median of {cfg.repeats}, {cfg.L} landmarks, k = {cfg.k}, preparation included", rows)


def threads(cfg: Settings, report: Report) -> None:
    """No workload slower with all BLAS/torch threads than with one."""
    import torch
    from threadpoolctl import threadpool_info, threadpool_limits

    try:
        pair = Pair(cfg.pair)
    except Skip:
        pair = Pair("demo")
    x, y, lmk = pair.x, pair.y, pair.landmarks(7)
    seeds = torchfmap.farthest_point_sampling(x, 50, metric="euclidean")
    work = {
        "diffusion_basis 50 x 2": lambda: torchfmap.diffusion_basis(x, seeds, [1e-3, 1e-2], tol=1e-6),
        "laplacian_eigenbasis k=100": lambda: torchfmap.laplacian_eigenbasis(x, 100),
        "match default (L=7), refined": lambda: torchfmap.match(x, y, landmarks=lmk, k=60, refine="zoomout"),
        "match laplacian, ZoomOut": lambda: torchfmap.match(x, y, basis="laplacian", k=60, refine="zoomout"),
    }
    blas = sorted({f"{i['internal_api']} ({i['num_threads']} threads)" for i in threadpool_info()})
    default = torch.get_num_threads()
    rows = []
    for name, fn in work.items():
        times: dict[str, list[float]] = {"one": [], "all": []}
        for label in ("one", "all", "one", "all"):  # alternating: drift in load hits both
            if label == "one":
                with threadpool_limits(limits=1):
                    torch.set_num_threads(1)
                    times[label].append(timed(fn, cfg.repeats)[0])
                torch.set_num_threads(default)
            else:
                times[label].append(timed(fn, cfg.repeats)[0])
        one, every = min(times["one"]), min(times["all"])
        rows.append({"workload": name, "method": "1 thread", "time [s]": one, "t / 1 thread": 1.0})
        rows.append(
            {
                "workload": name,
                "method": "all threads",
                "time [s]": every,
                "t / 1 thread": every / one,
                "load": load1(),
            }
        )
    report.table(
        f"{pair.name} (V={x.n_vertices}); {', '.join(blas)}; torch {default} threads; best of two rounds",
        rows,
    )


CASES = {
    "match_speed": match_speed,
    "nn_speed": nn_speed,
    "eval_speed": eval_speed,
    "landmark_timing": landmark_timing,
    "threads": threads,
}
