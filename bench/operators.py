"""Benchmark: building Laplacians ``(L, B)`` and factorising ``L + B``, ours vs the reference libraries.

Run by hand from the repository root (prints two markdown tables to stdout, progress to stderr)::

    python bench/operators.py                      # 5K, 50K, 200K vertices + TOSCA wolf0
    python bench/operators.py --sizes 5000 --repeats 5 --memory

Operators (median of ``--repeats`` timed calls after one warm-up call, all in the same process):

- ours: ``torchfmap.laplacian(mesh, kind, mass)`` for cotan+voronoi, cotan+barycentric, robust
  and mean_value. Each call gets a fresh ``Mesh(V, F, validate=False)`` so no cached
  ``face_areas`` carry over between repeats; the input is the raw arrays, as for the others.
- potpourri3d: ``pp3d.cotan_laplacian(V, F)`` + ``pp3d.vertex_areas(V, F)`` (barycentric areas).
- robust_laplacian: ``robust_laplacian.mesh_laplacian(V, F)``.

``pp3d/ours`` is ``time(pp3d cotan+areas) / time(ours cotan+bary)``: the same two quantities.
``|ΔL| rel`` is ``max|L_ours - s L_pp3d| / max|L_pp3d|`` with ``s`` potpourri3d's sign convention
(detected from its diagonal: ``s = +1`` when it is PSD like ours); ``|ΔB| rel`` compares our
barycentric mass with ``pp3d.vertex_areas`` the same way.

Factorisations: ``torchfmap.factorize(L + B, spd=True, backend=b)`` (cotan+voronoi) for every
backend of ``torchfmap.available_backends()``; median of ``--repeats`` below ``--large``
vertices, one timed call (after the warm-up) at or above it; the residual is ``|A x - b| / |b|``
of one solve with a random ``b``. ``--memory`` adds the tracemalloc peak of one (untimed) ours
cotan+voronoi build; tracemalloc sees numpy/scipy allocations only, so it is not reported for the
C++ libraries.
"""

from __future__ import annotations

import argparse
import gc
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
import potpourri3d as pp3d
import robust_laplacian
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import log  # noqa: E402
from _meshes import bench_mesh, real_mesh_path  # noqa: E402

import torchfmap  # noqa: E402

REAL_MESH = "tosca_hires_wolf/wolf0.off"
OURS = {
    "ours cotan+voronoi [s]": ("cotan", "voronoi"),
    "ours cotan+bary": ("cotan", "barycentric"),
    "ours robust": ("robust", "voronoi"),
    "ours mean_value": ("mean_value", "voronoi"),
}


def timed(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> tuple[float, Any]:
    """Median wall time of ``repeats`` calls of ``fn`` after ``warmup`` calls, and the last result."""
    out = None
    for _ in range(warmup):
        out = fn()
    times = []
    for _ in range(repeats):
        del out
        gc.collect()
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def ours(v: np.ndarray, f: np.ndarray, kind: str, mass: str) -> torchfmap.Operators:
    """``torchfmap.laplacian`` from raw arrays (fresh, unvalidated Mesh: no cached quantities)."""
    return torchfmap.laplacian(torchfmap.Mesh(v, f, validate=False), kind=kind, mass=mass)


def pp3d_cotan(v: np.ndarray, f: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    return pp3d.cotan_laplacian(v, f), pp3d.vertex_areas(v, f)


def peak_mib(fn: Callable[[], Any]) -> float:
    """tracemalloc peak (MiB) of one call of ``fn`` (numpy/scipy allocations only)."""
    gc.collect()
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def bench_operators(name: str, mesh: torchfmap.Mesh, repeats: int, memory: bool) -> dict[str, Any]:
    v, f = mesh.vertices, mesh.faces
    row: dict[str, Any] = {"mesh": name, "V": mesh.n_vertices, "F": mesh.n_faces}
    results = {}
    for col, (kind, mass) in OURS.items():
        log(f"  {name}: {col}")
        row[col], results[col] = timed(lambda k=kind, m=mass: ours(v, f, k, m), repeats)
    log(f"  {name}: potpourri3d")
    row["pp3d cotan+areas"], (Lp, areas) = timed(lambda: pp3d_cotan(v, f), repeats)
    log(f"  {name}: robust_laplacian")
    row["robust_laplacian"], _ = timed(lambda: robust_laplacian.mesh_laplacian(v, f), repeats)
    row["pp3d/ours ratio"] = row["pp3d cotan+areas"] / row["ours cotan+bary"]
    sign = 1.0 if Lp.diagonal().sum() > 0 else -1.0
    L, B = results["ours cotan+bary"]
    row["|ΔL| rel"] = abs(L - sign * Lp).max() / abs(Lp).max()
    row["|ΔB| rel"] = np.abs(B.diagonal() - areas).max() / np.abs(areas).max()
    row["pp3d sign"] = "+" if sign > 0 else "-"
    if memory:
        row["ours peak MiB"] = peak_mib(lambda: ours(v, f, "cotan", "voronoi"))
    row["_A"] = (results["ours cotan+voronoi [s]"][0] + results["ours cotan+voronoi [s]"][1]).tocsc()
    return row


def bench_factorize(name: str, a: sp.csc_matrix, repeats: int, rng: np.random.Generator) -> list[dict]:
    rows = []
    b = rng.standard_normal(a.shape[0])
    for backend in torchfmap.available_backends():
        log(f"  {name}: factorize {backend} ({repeats} repeat(s))")
        t, fac = timed(lambda be=backend: torchfmap.factorize(a, spd=True, backend=be), repeats)
        t0 = time.perf_counter()
        x = fac.solve(b)
        t_solve = time.perf_counter() - t0
        res = np.linalg.norm(a @ x - b) / np.linalg.norm(b)
        rows.append(
            {
                "mesh": name,
                "V": a.shape[0],
                "nnz(A)": a.nnz,
                "backend": backend,
                "repeats": repeats,
                "factorize [s]": t,
                "solve [s]": t_solve,
                "rel. residual": res,
            }
        )
    return rows


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
        return fmt(x).replace("|", "\\|")  # a literal pipe would split the cell

    lines = ["| " + " | ".join(cell(c) for c in columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    lines += ["| " + " | ".join(cell(r[c]) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="5000,50000,200000", help="comma-separated vertex counts")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (median), after 1 warm-up")
    parser.add_argument("--large", type=int, default=100_000, help="factorise only once from this size")
    parser.add_argument("--no-real", action="store_true", help=f"skip the real mesh {REAL_MESH}")
    parser.add_argument("--memory", action="store_true", help="add tracemalloc peak of ours cotan+voronoi")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",") if s.strip()]

    meshes: list[tuple[str, Callable[[], torchfmap.Mesh]]] = [
        (f"bench{n // 1000}K" if n % 1000 == 0 else f"bench{n}", lambda n=n: bench_mesh(n, args.seed))
        for n in sizes
    ]
    real = real_mesh_path(REAL_MESH)
    if real is not None and not args.no_real:
        meshes.append((Path(REAL_MESH).stem, lambda: torchfmap.load_mesh(real)))
    elif not args.no_real:
        log(f"real mesh {REAL_MESH} not found; skipped")

    rng = np.random.default_rng(args.seed)
    op_rows, fac_rows = [], []
    for name, make in meshes:
        log(f"{name}: building mesh")
        mesh = make()
        row = bench_operators(name, mesh, args.repeats, args.memory)
        a = row.pop("_A")
        op_rows.append(row)
        fac_repeats = 1 if mesh.n_vertices >= args.large else args.repeats
        fac_rows += bench_factorize(name, a, fac_repeats, rng)
        del mesh, a

    op_cols = [
        "mesh",
        "V",
        "F",
        *OURS,
        "pp3d cotan+areas",
        "robust_laplacian",
        "pp3d/ours ratio",
        "|ΔL| rel",
        "|ΔB| rel",
        "pp3d sign",
    ] + (["ours peak MiB"] if args.memory else [])
    fac_cols = ["mesh", "V", "nnz(A)", "backend", "repeats", "factorize [s]", "solve [s]", "rel. residual"]
    print(
        f"## Building (L, B): median of {args.repeats} after 1 warm-up "
        f"({os.cpu_count()} CPUs; numpy {np.__version__}, scipy {version('scipy')}, potpourri3d "
        f"{version('potpourri3d')}, robust_laplacian {version('robust_laplacian')})\n"
    )
    print(markdown(op_rows, op_cols))
    print(
        "\npp3d/ours = pp3d cotan+areas / ours cotan+bary. |ΔL| rel = max|L_ours - s L_pp3d| / "
        "max|L_pp3d|, |ΔB| rel = max|B_bary - vertex_areas| / max(vertex_areas); s = pp3d sign.\n"
    )
    print("## Factorising A = L + B (cotan + voronoi), torchfmap.factorize(A, spd=True, backend=...)\n")
    print(markdown(fac_rows, fac_cols))


if __name__ == "__main__":
    main()
