"""Benchmark: building Laplacians ``(L, B)`` and factorising ``L + B``, ours vs the reference libraries.

Run by hand from the repository root (prints two markdown tables to stdout, progress to stderr,
and writes them to ``bench/results/operators.md``)::

    python3 bench/operators.py                     # 5K, 50K, 200K vertices + TOSCA wolf0
    python3 bench/operators.py --sizes 5000 --repeats 5 --memory
    python3 bench/operators.py --sizes 2000 --repeats 1 --no-real   # quick check

Operators (median of ``--repeats`` timed calls after one warm-up call, all in the same process):

- ours: ``torchfmap.laplacian(mesh, scheme, mass)`` for cotan+voronoi, cotan+barycentric, robust
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
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import potpourri3d as pp3d
import robust_laplacian
import scipy.sparse as sp
from _common import Report, data_path, int_list, load_note, log, timed, traced_peak_mib, versions
from _meshes import bench_mesh, mesh_name

import torchfmap

REAL_MESH = "tosca_hires_wolf/wolf0.off"
OURS = {
    "ours cotan+voronoi [s]": ("cotan", "voronoi"),
    "ours cotan+bary": ("cotan", "barycentric"),
    "ours robust": ("robust", "voronoi"),
    "ours mean_value": ("mean_value", "voronoi"),
}


def ours(v: np.ndarray, f: np.ndarray, scheme: str, mass: str) -> torchfmap.Operators:
    """``torchfmap.laplacian`` from raw arrays (fresh, unvalidated Mesh: no cached quantities)."""
    return torchfmap.laplacian(torchfmap.Mesh(v, f, validate=False), scheme=scheme, mass=mass)


def pp3d_cotan(v: np.ndarray, f: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    return pp3d.cotan_laplacian(v, f), pp3d.vertex_areas(v, f)


def bench_operators(name: str, mesh: torchfmap.Mesh, repeats: int, memory: bool) -> dict[str, Any]:
    v, f = mesh.vertices, mesh.faces
    row: dict[str, Any] = {"mesh": name, "V": mesh.n_vertices, "F": mesh.n_faces}
    results = {}
    for col, (scheme, mass) in OURS.items():
        log(f"  {name}: {col}")
        row[col], _, results[col] = timed(lambda s=scheme, m=mass: ours(v, f, s, m), repeats, warmup=1)
    log(f"  {name}: potpourri3d")
    row["pp3d cotan+areas"], _, (Lp, areas) = timed(lambda: pp3d_cotan(v, f), repeats, warmup=1)
    log(f"  {name}: robust_laplacian")
    row["robust_laplacian"], _, _ = timed(lambda: robust_laplacian.mesh_laplacian(v, f), repeats, warmup=1)
    row["pp3d/ours ratio"] = row["pp3d cotan+areas"] / row["ours cotan+bary"]
    sign = 1.0 if Lp.diagonal().sum() > 0 else -1.0
    L, B = results["ours cotan+bary"]
    row["|ΔL| rel"] = abs(L - sign * Lp).max() / abs(Lp).max()
    row["|ΔB| rel"] = np.abs(B.diagonal() - areas).max() / np.abs(areas).max()
    row["pp3d sign"] = "+" if sign > 0 else "-"
    if memory:
        row["ours peak MiB"] = traced_peak_mib(lambda: ours(v, f, "cotan", "voronoi"))[0]
    row["_A"] = (results["ours cotan+voronoi [s]"][0] + results["ours cotan+voronoi [s]"][1]).tocsc()
    return row


def bench_factorize(name: str, a: sp.csc_matrix, repeats: int, rng: np.random.Generator) -> list[dict]:
    rows = []
    b = rng.standard_normal(a.shape[0])
    for backend in torchfmap.available_backends():
        log(f"  {name}: factorize {backend} ({repeats} repeat(s))")
        t, _, fac = timed(lambda be=backend: torchfmap.factorize(a, spd=True, backend=be), repeats, warmup=1)
        t_solve, _, x = timed(lambda fac=fac: fac.solve(b))
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


def meshes(args) -> list[tuple[str, Callable[[], torchfmap.Mesh]]]:
    """``(name, builder)`` of every ``--sizes`` bench mesh and, unless ``--no-real``, the real mesh."""
    out: list[tuple[str, Callable[[], torchfmap.Mesh]]] = [
        (mesh_name(n), lambda n=n: bench_mesh(n, args.seed)) for n in int_list(args.sizes)
    ]
    real = None if args.no_real else data_path(REAL_MESH)
    if real is not None:
        out.append((Path(REAL_MESH).stem, lambda: torchfmap.load_mesh(real)))
    elif not args.no_real:
        log(f"real mesh {REAL_MESH} not found; skipped")
    return out


def report(args, op_rows: list[dict], fac_rows: list[dict]) -> None:
    op_cols = ["mesh", "V", "F", *OURS, "pp3d cotan+areas", "robust_laplacian", "pp3d/ours ratio"]
    op_cols += ["|ΔL| rel", "|ΔB| rel", "pp3d sign"] + (["ours peak MiB"] if args.memory else [])
    fac_cols = ["mesh", "V", "nnz(A)", "backend", "repeats", "factorize [s]", "solve [s]", "rel. residual"]
    out = Report("operators")
    out.table(
        f"## Building (L, B): median of {args.repeats} after 1 warm-up "
        f"({versions('scipy', 'potpourri3d', 'robust_laplacian')}; {load_note()} at end)",
        op_rows,
        op_cols,
        note="pp3d/ours = pp3d cotan+areas / ours cotan+bary. |ΔL| rel = max|L_ours - s L_pp3d| / "
        "max|L_pp3d|, |ΔB| rel = max|B_bary - vertex_areas| / max(vertex_areas); s = pp3d sign.",
    )
    out.table(
        "## Factorising A = L + B (cotan + voronoi), torchfmap.factorize(A, spd=True, backend=...)",
        fac_rows,
        fac_cols,
    )
    out.save()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="5000,50000,200000", help="comma-separated vertex counts")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (median), after 1 warm-up")
    parser.add_argument("--large", type=int, default=100_000, help="factorise only once from this size")
    parser.add_argument("--no-real", action="store_true", help=f"skip the real mesh {REAL_MESH}")
    parser.add_argument("--memory", action="store_true", help="add tracemalloc peak of ours cotan+voronoi")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    op_rows, fac_rows = [], []
    for name, make in meshes(args):
        log(f"{name}: building mesh")
        mesh = make()
        row = bench_operators(name, mesh, args.repeats, args.memory)
        a = row.pop("_A")
        op_rows.append(row)
        fac_repeats = 1 if mesh.n_vertices >= args.large else args.repeats
        fac_rows += bench_factorize(name, a, fac_repeats, rng)
        del mesh, a
    report(args, op_rows, fac_rows)


if __name__ == "__main__":
    main()
