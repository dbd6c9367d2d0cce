"""Suite ``speed``, the building blocks: Laplacians and factorisations against the reference
libraries, eigensolvers, the harmonic and diffusion bases against an eigenbasis, heat-kernel
accuracy and local support.

Meshes are ``bench_mesh(n)`` (irregular, closed, genus 0; ``bench/common.py``); ``(L, B)`` is
``torchfmap.laplacian(mesh)`` (cotan + lumped voronoi mass); seeds are Euclidean farthest
points, so that seed selection is in no basis timing. Cells are medians of ``repeats`` calls
(one call at or above ``large`` vertices, or when the first took longer than ``max_repeat_s``),
all in one process, after one warm-up of every timed operation on a small mesh.
"""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as ssla

import torchfmap
from torchfmap.bases import concatenate, orthonormalize
from torchfmap.operators import eigen
from torchfmap.operators.heat import heat_kernels

from .common import (
    Failed,
    Report,
    Settings,
    Skip,
    attempt,
    bench_mesh,
    data_path,
    fmt,
    load1,
    log,
    mesh_name,
    require_data,
    reset_peak_rss,
    run_timed,
    status_mib,
    timed,
    traced_peak_mib,
)

HEAT_TOL = 1e-6
EIGSH_RATIO_K = 100


def setup(n: int, seed: int, n_seeds: int):
    """``(mesh, L, B, seeds)`` of ``bench_mesh(n, seed)`` with ``n_seeds`` Euclidean FPS seeds."""
    mesh = bench_mesh(n, seed)
    L, B = torchfmap.laplacian(mesh)
    return mesh, L, B, torchfmap.farthest_point_sampling(mesh, n_seeds, metric="euclidean")


def eigsh(L, B, k: int):
    """The baseline eigenbasis: ``scipy.sparse.linalg.eigsh`` in shift-invert mode (SuperLU)."""
    return ssla.eigsh(L, k=k, M=B, sigma=-1e-8, which="LM")


def diffusion(mesh, seeds, ops, times, local: bool | str = False):
    """``diffusion_basis`` with krylov, tol ``HEAT_TOL``."""
    return torchfmap.diffusion_basis(mesh, seeds, times, "krylov", operators=ops, tol=HEAT_TOL, local=local)


def rel_diff(K: np.ndarray, K_ref: np.ndarray) -> float:
    """Max over columns of ``max|K - K_ref| / max|K_ref|`` for ``(V, C)`` arrays."""
    return float((np.abs(K - K_ref).max(axis=0) / np.abs(K_ref).max(axis=0)).max())


def column_errors(K: np.ndarray, K_ref: np.ndarray) -> np.ndarray:
    """``max|K - K_ref| / max|K_ref|`` for every (time, seed) column of ``(T, V, S)`` arrays."""
    return np.abs(K - K_ref).max(axis=1) / np.abs(K_ref).max(axis=1)


def warm_up(cfg: Settings) -> None:
    """One call of every timed operation on a small mesh (imports, ARPACK, CHOLMOD set-up)."""
    log(f"warm-up on bench_mesh({cfg.warmup_size})")
    mesh, L, B, seeds = setup(cfg.warmup_size, cfg.seed, cfg.n_seeds)
    torchfmap.farthest_point_sampling(mesh, 5, metric="geodesic")
    h = torchfmap.harmonic_basis(mesh, seeds, operators=(L, B))
    times = np.array([1e-5, 1e-4]) * mesh.area
    for method in ("krylov", "rational", "backward_euler", "spectral"):
        heat_kernels((L, B), seeds[:5], times, method=method, tol=HEAT_TOL)
    dg = diffusion(mesh, seeds, (L, B), cfg.times, local=False)
    diffusion(mesh, seeds, (L, B), cfg.times, local="auto")
    for m in ("mgs", "cholqr"):
        orthonormalize(concatenate([dg, h]), m)
    eigsh(L, B, min(50, cfg.warmup_size - 2))


# -- operators ------------------------------------------------------------------------------------
def operators(cfg: Settings, report: Report) -> None:
    """Building (L, B) and factorising L + B: ours against potpourri3d and robust_laplacian."""
    import potpourri3d as pp3d
    import robust_laplacian

    ours = {
        "ours cotan+voronoi": ("cotan", "voronoi"),
        "ours cotan+bary": ("cotan", "barycentric"),
        "ours robust": ("robust", "voronoi"),
        "ours mean_value": ("mean_value", "voronoi"),
    }
    meshes = [(mesh_name(n), lambda n=n: bench_mesh(n, cfg.seed)) for n in cfg.sizes]
    real = data_path(cfg.real_mesh) if cfg.real_mesh else None
    if real is not None:
        meshes.append((real.stem, lambda: torchfmap.load_mesh(real)))
    rng = np.random.default_rng(cfg.seed)
    op_rows, fac_rows = [], []
    for name, make in meshes:
        mesh = make()
        v, f = mesh.vertices, mesh.faces
        reps = 1 if mesh.n_vertices >= cfg.large else cfg.repeats
        built = {}
        for label, (scheme, mass) in ours.items():  # a fresh, unvalidated Mesh: no cached quantities
            build = lambda s=scheme, m=mass: torchfmap.laplacian(torchfmap.Mesh(v, f, validate=False), s, m)  # noqa: B023, E731
            t, _, built[label] = timed(build, reps, warmup=1)
            op_rows.append({"mesh": name, "V": mesh.n_vertices, "method": label, "time [s]": t})
        t_pp, _, (Lp, areas) = timed(
            lambda: (pp3d.cotan_laplacian(v, f), pp3d.vertex_areas(v, f)),  # noqa: B023
            reps,
            warmup=1,  # noqa: B023
        )
        t_rl, _, _ = timed(lambda: robust_laplacian.mesh_laplacian(v, f), reps, warmup=1)  # noqa: B023
        base = [r for r in op_rows if r["mesh"] == name and r["method"] == "ours cotan+bary"][0]["time [s]"]
        sign = 1.0 if Lp.diagonal().sum() > 0 else -1.0  # potpourri3d's sign convention
        L, B = built["ours cotan+bary"]
        op_rows.append(
            {
                "mesh": name,
                "V": mesh.n_vertices,
                "method": "potpourri3d cotan+areas",
                "time [s]": t_pp,
                "|ΔL| rel": abs(L - sign * Lp).max() / abs(Lp).max(),
                "|ΔB| rel": np.abs(B.diagonal() - areas).max() / np.abs(areas).max(),
            }
        )
        op_rows.append({"mesh": name, "V": mesh.n_vertices, "method": "robust_laplacian", "time [s]": t_rl})
        for r in op_rows:
            if r["mesh"] == name:
                r["t / ours cotan+bary"] = r["time [s]"] / base
        if cfg.memory:
            op_rows[-6]["peak MiB"] = traced_peak_mib(lambda: torchfmap.laplacian(mesh))[0]  # noqa: B023
        a = (built["ours cotan+voronoi"][0] + built["ours cotan+voronoi"][1]).tocsc()
        b = rng.standard_normal(a.shape[0])
        for backend in torchfmap.available_backends():
            log(f"  {name}: factorize {backend}")
            t, _, fac = timed(lambda be=backend: torchfmap.factorize(a, spd=True, backend=be), reps, warmup=1)  # noqa: B023
            t_solve, _, x = timed(lambda fac=fac: fac.solve(b))  # noqa: B023
            fac_rows.append(
                {
                    "mesh": name,
                    "V": a.shape[0],
                    "nnz(A)": a.nnz,
                    "method": backend,
                    "factorize [s]": t,
                    "solve [s]": t_solve,
                    "rel. residual": np.linalg.norm(a @ x - b) / np.linalg.norm(b),
                }
            )
    report.table(
        "Building (L, B)",
        op_rows,
        note="|ΔL| rel = max|L_ours - s L_pp3d| / max|L_pp3d| (s: potpourri3d's sign), |ΔB| rel: "
        "our barycentric "
        "mass against pp3d.vertex_areas; both against ours cotan+bary, the same quantities.",
    )
    report.table(
        "Factorising A = L + B (cotan + voronoi): torchfmap.factorize(A, spd=True, backend=...)", fac_rows
    )


def eigenpairs(cfg: Settings, report: Report) -> None:
    """Laplacian eigenpairs: block Lanczos against ARPACK on the same factorisation."""
    from threadpoolctl import threadpool_limits

    rows = []
    with threadpool_limits(cfg.threads) if cfg.threads else contextlib.nullcontext():
        for n in cfg.sizes:
            L, B = torchfmap.laplacian(bench_mesh(n))
            for k in cfg.ks:
                times: dict[str, list[float]] = {"arpack": [], "block": []}
                out = {}
                for _ in range(cfg.repeats):  # alternating
                    for solver in times:
                        t, _, out[solver] = timed(
                            lambda s=solver, k=k, L=L, B=B: eigen.eigenpairs(L, B, k, solver=s)
                        )
                        times[solver].append(t)
                (la, pa), (lb, pb) = out["arpack"], out["block"]
                pos = la > 1e-8 * la[-1]
                gaps = np.diff(la) / la[-1]
                simple = [i for i in range(1, len(la) - 1) if gaps[i - 1] > 1e-6 and gaps[i] > 1e-6]
                overlap = np.abs(np.einsum("vi,vi->i", pa[:, simple], B @ pb[:, simple]))
                med = {s: float(np.median(t)) for s, t in times.items()}
                for solver in times:
                    rows.append(
                        {
                            "V": n,
                            "k": k,
                            "method": solver,
                            "time [s]": med[solver],
                            "t / ARPACK": med[solver] / med["arpack"],
                            "auto picks": eigen.auto_solver(n, k),
                            "max rel. Δλ": float(np.max(np.abs(la[pos] - lb[pos]) / la[pos])),
                            "min |overlap|": float(overlap.min()) if simple else float("nan"),
                            "load": load1(),
                        }
                    )
    report.table(
        "Median of alternating runs, each with its factorisation",
        rows,
        note="Both stop at residual <= ARPACK_TOL |θ|. Overlap: |φ_arpackᵀ B φ_block| over "
        "eigenvalues separated "
        f"from their neighbours by 1e-6 relative. Threads: {cfg.threads or 'default'}.",
    )


def bases(cfg: Settings, report: Report) -> None:
    """Speed of the harmonic and diffusion bases against a Laplacian eigenbasis (eigsh)."""
    warm_up(cfg)
    rows, ratios = [], []
    for n in cfg.sizes:
        reps, mrs, name = (1 if n >= cfg.large else cfg.repeats), cfg.max_repeat_s, mesh_name(n)
        mesh = bench_mesh(n, cfg.seed)
        row: dict[str, Any] = {"mesh": name, "V": n}
        row["(L, B) [s]"], _, (L, B) = timed(lambda: torchfmap.laplacian(mesh), reps, max_repeat_s=mrs)  # noqa: B023
        fps = lambda m: lambda: torchfmap.farthest_point_sampling(mesh, cfg.n_seeds, metric=m)  # noqa: E731, B023
        row["seeds eucl. [s]"], _, seeds = timed(fps("euclidean"), reps, max_repeat_s=mrs)
        t1 = timed(lambda: torchfmap.farthest_point_sampling(mesh, 1, metric="geodesic"))[0]  # noqa: B023
        t6 = timed(lambda: torchfmap.farthest_point_sampling(mesh, 6, metric="geodesic"))[0]  # noqa: B023
        est = t1 + (t6 - t1) * (cfg.n_seeds - 1) / 5
        row["seeds geod. [s]"] = (
            f"skipped (est. {est:.0f} s)"
            if est > cfg.geodesic_limit_s
            else timed(fps("geodesic"), reps, max_repeat_s=10)[0]
        )
        eig_t: dict[int, Any] = {}
        prev = None
        for k in sorted(cfg.eigsh_k):
            if prev is not None and prev[1] * (k / prev[0]) ** 2 > cfg.eigsh_budget:
                row[f"eigsh k={k} [s]"] = eig_t[k] = f"skipped (est. {prev[1] * (k / prev[0]) ** 2:.0f} s)"
                continue
            log(f"{name}: eigsh k={k}")
            row[f"eigsh k={k} [s]"] = eig_t[k] = run_timed(
                f"eigsh {k}",
                lambda k=k: eigsh(L, B, k),  # noqa: B023
                reps,
                mrs,  # noqa: B023
            )[0]
            prev = (k, eig_t[k]) if isinstance(eig_t[k], float) else prev
        row["harmonic [s]"], harm = run_timed(
            "harmonic",
            lambda: torchfmap.harmonic_basis(mesh, seeds, operators=(L, B)),  # noqa: B023
            reps,
            mrs,  # noqa: B023
        )  # noqa: B023
        diffs = {}
        for local in (False, "auto"):
            fn = lambda local=local: diffusion(mesh, seeds, (L, B), cfg.times, local)  # noqa: E731, B023
            row[f"diffusion local={local} [s]"], diffs[local] = run_timed(f"diffusion {local}", fn, reps, mrs)
        dg, da = diffs[False], diffs["auto"]
        row["max rel. diff auto vs global"] = (
            rel_diff(da.values, dg.values) if dg is not None and da is not None else "n/a"
        )
        stack = concatenate([dg, harm]) if dg is not None and harm is not None else None
        for m in ("mgs", "cholqr"):
            t, ortho = (
                run_timed(m, lambda m=m: orthonormalize(stack, m), reps, mrs) if stack else ("n/a", None)  # noqa: B023
            )  # noqa: B023
            Q = None if ortho is None else ortho.values
            row[f"{m} [s] (kept)"] = t if Q is None else f"{fmt(t)} ({Q.shape[1]})"
            row[f"{m} |QᵀBQ-I|"] = (
                "n/a" if Q is None else float(np.abs(Q.T @ (B @ Q) - np.eye(Q.shape[1])).max())
            )
        rows.append(row)
        e100 = eig_t.get(EIGSH_RATIO_K)
        ratio: dict[str, Any] = {"mesh": name, "V": n}
        for label, col in (
            ("harmonic", "harmonic [s]"),
            ("diffusion global", "diffusion local=False [s]"),
            ("diffusion auto", "diffusion local=auto [s]"),
        ):
            ok = isinstance(e100, float) and isinstance(row[col], float)
            ratio[f"eigsh{EIGSH_RATIO_K} / {label}"] = e100 / row[col] if ok else "n/a"
        if cfg.memory:
            for label, fn in (
                ("harmonic", lambda: torchfmap.harmonic_basis(mesh, seeds, operators=(L, B))),  # noqa: B023
                ("diffusion global", lambda: diffusion(mesh, seeds, (L, B), cfg.times, False)),  # noqa: B023
                (f"eigsh{EIGSH_RATIO_K}", lambda: eigsh(L, B, EIGSH_RATIO_K)),  # noqa: B023
            ):  # noqa: B023
                ratio[f"peak MiB {label}"] = attempt(label, lambda fn=fn: traced_peak_mib(fn)[0])
        ratios.append(ratio)
    report.table(
        f"Wall time per mesh size ({cfg.n_seeds} seeds, relative times {cfg.times}, tol {HEAT_TOL:g})",
        rows,
        note="eigsh: scipy.sparse.linalg.eigsh(L, k, M=B, sigma=-1e-8, which='LM'); 'skipped (est.)': "
        f"t(k_prev)·(k/k_prev)² > {cfg.eigsh_budget:g} s. Orthonormalisation of "
        f"concatenate([diffusion global, "
        "harmonic]); kept columns in brackets.",
    )
    report.table("Ratios (same run) and tracemalloc peaks (numpy allocations only)", ratios)


def heat_accuracy(cfg: Settings, report: Report) -> None:
    """Accuracy and time of every heat-kernel method against a reference checked against expm."""
    mesh, L, B, seeds = setup(cfg.dense_size, cfg.seed, 10)
    d = B.diagonal()
    times = np.array([1e-5, 1e-4, *cfg.times])
    t_rat, _, K = timed(
        lambda: heat_kernels((L, B), seeds, times * mesh.area, method="rational", tol=cfg.ref_tol)
    )

    def dense_eigh(L, B, seeds, abs_times):
        s = 1.0 / np.sqrt(B.diagonal())  # exact kernels from the dense eigh of D^-1/2 L D^-1/2
        lam, U = np.linalg.eigh(s[:, None] * L.toarray() * s[None, :])
        Us = U[seeds].T * s[seeds]
        return np.stack([s[:, None] * (U @ (np.exp(-t * lam)[:, None] * Us)) for t in abs_times])

    K_eigh = dense_eigh(L, B, seeds, times * mesh.area)
    A = L.toarray() / d[:, None]
    check, passed = [], True
    for ti, t in enumerate(times):
        t_dense, _, K_dense = timed(lambda t=t: sla.expm(-t * mesh.area * A)[:, seeds] / d[seeds])
        err = column_errors(K[ti][None], K_dense[None])[0].max()
        passed &= bool(err < cfg.dense_limit)
        check.append(
            {
                "t (rel.)": f"{t:g}",
                "method": f"rational tol={cfg.ref_tol:g}",
                "max col. rel. err": err,
                f"< {cfg.dense_limit:g}": "yes" if err < cfg.dense_limit else "**NO**",
                "dense eigh: max col. rel. err": column_errors(K_eigh[ti][None], K_dense[None])[0].max(),
                "expm [s]": t_dense,
                "rational, all t [s]": t_rat if ti == 0 else "",
            }
        )
    report.table(
        f"Dense check on {mesh_name(cfg.dense_size)} (10 seeds) against expm(-t B⁻¹L)[:, seeds] / "
        f"B[seeds, seeds]",
        check,
    )
    warm_up(cfg)
    mesh, L, B, seeds = setup(cfg.size, cfg.seed, cfg.n_seeds)
    abs_times = np.array(cfg.times) * mesh.area
    if passed:
        label = f"rational tol {cfg.ref_tol:g}"
        fn = lambda: heat_kernels((L, B), seeds, abs_times, method="rational", tol=cfg.ref_tol)  # noqa: E731
        t_ref, _, K_ref = timed(fn, cfg.repeats, max_repeat_s=cfg.max_repeat_s)
    else:
        label = "dense eigh"
        t_ref, _, K_ref = timed(lambda: dense_eigh(L, B, seeds, abs_times))
    rows: list[dict] = [{"method": f"{label} (reference)", "time [s]": t_ref, "t / t_ref": 1.0}]
    methods = [
        ("krylov", 1e-6, {}),
        ("krylov", 1e-8, {}),
        ("rational", 1e-6, {}),
        ("backward_euler", None, {}),
        ("spectral", None, {"n_eigen": 200}),
        ("krylov", 1e-6, {"local": "auto", "vertices": mesh.vertices}),
    ]
    for method, tol, extra in methods:
        fn = lambda m=method, tol=tol, e=extra: heat_kernels(  # noqa: E731
            (L, B), seeds, abs_times, method=m, tol=tol or HEAT_TOL, **e
        )  # noqa: E731
        t, Kt = run_timed(method, fn, cfg.repeats, cfg.max_repeat_s)
        row = {
            "method": method
            + (" local='auto'" if extra.get("local") else "")
            + (f" {extra}" if "n_eigen" in extra else ""),
            "tol": "n/a" if tol is None else f"{tol:g}",
            "time [s]": t,
            "t / t_ref": t / t_ref if not isinstance(t, Failed) else "n/a",
        }
        if Kt is not None:
            err = column_errors(Kt, K_ref)
            row |= {
                "max col. rel. err": float(err.max()),
                "median col. rel. err": float(np.median(err)),
                "max err ≤ tol": "n/a" if tol is None else ("yes" if err.max() <= tol else "**NO**"),
            }
        rows.append(row)
    report.table(
        f"Accuracy on {mesh_name(cfg.size)}: {cfg.n_seeds} seeds x {len(cfg.times)} times, against {label}",
        rows,
        note="Column error = max_v |K - K_ref| / max_v |K_ref| for one (seed, time); krylov's tol "
        "is a relative "
        "B-norm convergence test, not this max-norm error. t / t_ref: ratio to the reference's "
        "time, same run.",
    )


def heat_support(cfg: Settings, report: Report) -> None:
    """Diffusion bases at small times: global against local (local='auto') kernels."""
    warm_up(cfg)
    rows = []
    for n in cfg.sizes:
        mesh, L, B, seeds = setup(n, cfg.seed, cfg.n_seeds)
        reps, out = (1 if n >= cfg.large else cfg.repeats), {}
        for local in (False, "auto"):
            fn = lambda local=local: diffusion(mesh, seeds, (L, B), cfg.small_times, local)  # noqa: E731, B023
            t, out[local] = run_timed(f"local={local}", fn, reps, cfg.max_repeat_s)
            rows.append({"mesh": mesh_name(n), "V": n, "method": f"local={local}", "time [s]": t})
        g, a = out[False], out["auto"]
        if g is not None and a is not None:
            rows[-1] |= {
                "t / global": rows[-1]["time [s]"] / rows[-2]["time [s]"],
                "max rel. diff": rel_diff(a.values, g.values),
                "local support (mean % of V)": 100.0 * float((a.values != 0).mean()),
            }
    report.table(
        f"Small times {cfg.small_times} (relative), krylov tol {HEAT_TOL:g}, {cfg.n_seeds} seeds",
        rows,
        note="local support: mean over columns of the fraction of vertices where the local kernel "
        "is non-zero.",
    )


# -- dense meshes -----------------------------------------------------------------------------
def dense_mesh(cfg: Settings, level: int):
    """``cfg.mesh`` Loop-subdivided ``level`` times (trimesh), cached as ``<cache>/<stem>_s<level>.ply``
    when ``cfg.cache`` names a folder."""
    from torchfmap.io import load_mesh

    cache = Path(cfg.cache) / f"{Path(cfg.mesh).stem}_s{level}.ply" if cfg.cache else None
    if cache is not None and cache.exists():
        return load_mesh(cache)
    try:
        import trimesh
        from trimesh.remesh import subdivide_loop
    except ImportError as err:
        raise Skip("trimesh is needed to subdivide the dense meshes") from err
    base = torchfmap.load_mesh(require_data(cfg.mesh))
    v, f = base.vertices, base.faces
    for _ in range(level):
        v, f = subdivide_loop(v, f)
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        trimesh.Trimesh(v, f, process=False).export(cache)
        return load_mesh(cache)
    return torchfmap.Mesh(v, f)


def peak_timed(fn: Callable[[], Any]) -> tuple[Any, Any, Any]:
    """``(seconds, peak RSS above the start in MiB, result)`` of one call of ``fn``: the
    process' high-water mark (``VmHWM``, reset before the call), so memory inside C libraries
    (factors, ARPACK) counts too; ``Failed`` cells if it raises, nan MiB where the mark cannot
    be reset."""
    gc.collect()
    start = status_mib("VmRSS")
    reset = reset_peak_rss()
    res = attempt("dense", lambda: timed(fn))
    if isinstance(res, Failed):
        return res, res, None
    peak = status_mib("VmHWM") - start if reset else float("nan")
    return res[0], peak, res[2]


def dense_bases(cfg: Settings, report: Report) -> None:
    """Dense meshes: the diffusion basis against scipy eigsh k=100 and our eigenpairs, time and
    peak memory, in one process."""
    warm_up(cfg)
    rows = []
    for level in cfg.levels:
        mesh = dense_mesh(cfg, level)
        n = mesh.n_vertices
        log(f"{mesh.name or cfg.mesh} s{level}: {n} vertices")
        t_ops, _, (L, B) = timed(lambda: torchfmap.laplacian(mesh))  # noqa: B023
        seeds = torchfmap.farthest_point_sampling(mesh, cfg.n_seeds, metric="euclidean")
        base = {"mesh": f"{Path(cfg.mesh).stem} s{level}", "V": n, "(L, B) [s]": t_ops}
        runs: list[tuple[str, Callable[[], Any]]] = [
            (f"scipy eigsh k={cfg.k}", lambda: eigsh(L, B, cfg.k)),  # noqa: B023
            (f"eigenpairs k={cfg.k}", lambda: eigen.eigenpairs(L, B, cfg.k)),  # noqa: B023
        ]
        for tol in cfg.tols:
            runs.append(
                (f"diffusion {cfg.n_seeds}x{len(cfg.times)} tol={tol:g}", lambda tol=tol: torchfmap.diffusion_basis(mesh, seeds, cfg.times, "krylov", operators=(L, B), tol=tol, local=False))  # noqa: B023, E501
            )  # fmt: skip
        results: dict[str, Any] = {}
        for label, fn in runs:
            log(f"  {label}")
            t, peak, out = peak_timed(fn)
            results[label] = out
            rows.append(base | {"method": label, "time [s]": t, "peak RSS above start [MiB]": peak})
        t_eigsh = rows[-len(runs)]["time [s]"]
        for row in rows[-len(runs) :]:
            ok = isinstance(t_eigsh, float) and isinstance(row["time [s]"], float)
            row["eigsh / this"] = t_eigsh / row["time [s]"] if ok else "n/a"
            row["load"] = load1()
        for tol in cfg.tols if cfg.orthonormalize else ():
            basis = results.get(f"diffusion {cfg.n_seeds}x{len(cfg.times)} tol={tol:g}")
            if basis is not None:
                t, peak, ortho = peak_timed(lambda b=basis: orthonormalize(b))
                label = f"  + orthonormalize (mgs) of tol={tol:g}: kept {'n/a' if ortho is None else ortho.k}"
                rows.append(base | {"method": label, "time [s]": t, "peak RSS above start [MiB]": peak})
                rows[-1]["load"] = load1()
        results.clear()
        report.rows_csv(rows)
    report.table(
        f"One process, one call each ({cfg.n_seeds} Euclidean farthest-point seeds, relative times "
        f"{cfg.times}, krylov, local=False)",
        rows,
        note="eigsh: scipy.sparse.linalg.eigsh(L, k, M=B, sigma=-1e-8, which='LM') (SuperLU "
        "shift-invert, the baseline); eigenpairs: torchfmap.operators.eigenpairs (block Lanczos on a "
        "sparse Cholesky). eigsh / this: the baseline's time over the row's, same mesh, same run. "
        "Peak RSS: VmHWM (reset before each call) minus VmRSS at its start, so factorisations and "
        "work buffers inside C libraries count; the result itself is included. load: 1-minute load "
        "average after the call (2 cores, shared).",
    )


def dense_shot(cfg: Settings, report: Report) -> None:
    """SHOT on dense meshes: every vertex as its support (exact) against the voxel quadrature
    (``descriptors.SHOT_SUPPORT`` points) on one FAUST_r human midpoint-subdivided, time and agreement,
    in one process; the exact SHOT of the mesh before subdivision is the meshing's own effect."""
    import trimesh

    from torchfmap.descriptors import SHOT_SUPPORT, shot

    base = torchfmap.load_mesh(require_data(cfg.mesh))
    radius, n0 = cfg.radius * np.sqrt(base.area), base.n_vertices
    support = cfg.support or SHOT_SUPPORT
    coarse = shot(base, radius)

    def agree(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.mean(np.einsum("ij,ij->i", a, b)))

    rows, v, f = [], base.vertices, base.faces
    for level in range(1, max(cfg.levels) + 1):
        v, f = trimesh.remesh.subdivide(v, f)  # the old vertices first
        if level not in cfg.levels:
            continue
        mesh = torchfmap.Mesh(np.asarray(v), np.asarray(f, dtype=np.int64))
        log(f"{Path(cfg.mesh).stem} s{level}: {mesh.n_vertices} vertices")
        t_exact, _, exact = timed(lambda m=mesh: shot(m, radius, support=10**12))
        t_sampled, _, sampled = timed(lambda m=mesh: shot(m, radius, support=support))
        common = {"mesh": f"{Path(cfg.mesh).stem} s{level}", "V": mesh.n_vertices, "load": load1()}
        rows.append(common | {"method": "exact (every vertex)", "time [s]": t_exact, "exact / this": 1.0,
                              "agreement with exact": 1.0})  # fmt: skip
        rows.append(common | {"method": f"support {support}", "time [s]": t_sampled,
                              "exact / this": t_exact / t_sampled,
                              "agreement with exact": agree(sampled, exact)})  # fmt: skip
        meshing = agree(coarse, exact[:n0])
        rows.append(common | {"method": f"exact on the {n0}-vertex mesh (meshing)", "time [s]": "",
                              "exact / this": "", "agreement with exact": meshing})  # fmt: skip
    report.rows_csv(rows)
    report.table(
        f"SHOT at {cfg.radius:g} sqrt(area) on {cfg.mesh} subdivided: time and agreement",
        rows,
        note="agreement: the mean over vertices of the cosine between a row's signatures and the exact "
        "ones of the same mesh (unit rows; on the original vertices for the meshing row). exact / this: "
        "the exact SHOT's time over the row's, same mesh, same process.",
    )


CASES = {
    "operators": operators,
    "eigenpairs": eigenpairs,
    "bases": bases,
    "heat_accuracy": heat_accuracy,
    "heat_support": heat_support,
    "dense_bases": dense_bases,
    "dense_shot": dense_shot,
}
