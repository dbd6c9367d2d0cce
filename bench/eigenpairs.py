"""Benchmark: Laplacian eigenpairs, block Lanczos against ARPACK on the same factorisation.

Run by hand from the repository root (table to stdout and ``bench/results/eigenpairs.md``)::

    python3 bench/eigenpairs.py                                   # 5K, 20K, 200K; k = 100, 200
    python3 bench/eigenpairs.py --sizes 5000,20000 --ks 100 --repeats 3
    python3 bench/eigenpairs.py --sizes 3000 --ks 50 --threads 1  # quick

Meshes: ``bench_mesh(V)`` (``bench/_meshes.py``). For each ``(V, k)``: ``eigenpairs(L, B, k,
solver='arpack')`` (``scipy.sparse.linalg.eigsh`` in shift-invert mode with our sparse Cholesky
as its inverse) and ``solver='block'`` (block Lanczos, :func:`torchfmap.operators.eigen.
block_lanczos`, with its own Cholesky of ``L + s B``), alternating, ``--repeats`` rounds,
medians; each time includes its factorisation. Both stop at the same test, residual
``<= ARPACK_TOL · |θ|``. Agreement: the largest relative eigenvalue difference (``λ > 0``) and
the smallest ``|φ_arpackᵀ B φ_block|`` diagonal entry over eigenvalues separated from their
neighbours by 1e-6 relative (degenerate eigenspaces have no unique vectors). ``auto`` is the
solver ``solver='auto'`` picks. Thread counts: default, or ``--threads N`` for BLAS and torch.
"""

from __future__ import annotations

import argparse
import contextlib

import numpy as np
from _common import Report, int_list, load1, load_note, log, timed, versions
from _meshes import bench_mesh
from threadpoolctl import threadpool_limits

from torchfmap.operators import eigen as eig_module
from torchfmap.operators import laplacian


def agreement(arpack, block, B) -> tuple[float, float]:
    (la, pa), (lb, pb) = arpack, block
    pos = la > 1e-8 * la[-1]
    rel = float(np.max(np.abs(la[pos] - lb[pos]) / la[pos]))
    gaps = np.diff(la) / la[-1]
    simple = [i for i in range(1, len(la) - 1) if gaps[i - 1] > 1e-6 and gaps[i] > 1e-6]
    overlap = np.abs(np.einsum("vi,vi->i", pa[:, simple], B @ pb[:, simple]))
    return rel, float(overlap.min()) if simple else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="5000,20000,200000")
    parser.add_argument("--ks", default="100,200")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--threads", type=int, default=0, help="BLAS threads (0: default)")
    args = parser.parse_args()
    limit = threadpool_limits(args.threads) if args.threads else contextlib.nullcontext()
    report = Report("eigenpairs")
    report.add(f"# Eigenpairs: block Lanczos vs ARPACK ({versions('scipy')}; {load_note()})")
    rows = []
    with limit:
        for n in int_list(args.sizes):
            mesh = bench_mesh(n)
            L, B = laplacian(mesh)
            for k in int_list(args.ks):
                log(f"V={mesh.n_vertices}, k={k}")
                times, out = {}, {}
                for r in range(args.repeats):
                    for solver in ("arpack", "block"):
                        run = lambda s=solver, L=L, B=B, k=k: eig_module.eigenpairs(L, B, k, solver=s)  # noqa: E731
                        t, _, out[solver] = timed(run)
                        times.setdefault(solver, []).append(t)
                        log(f"  round {r + 1}: {solver} {t:.2f} s")
                med = {s: float(np.median(t)) for s, t in times.items()}
                rel, overlap = agreement(out["arpack"], out["block"], B)
                auto = eig_module.auto_solver(n, k)
                rows.append(
                    {
                        "V": mesh.n_vertices,
                        "k": k,
                        "ARPACK [s]": med["arpack"],
                        "block [s]": med["block"],
                        "ARPACK / block": med["arpack"] / med["block"],
                        "max rel. Δλ": rel,
                        "min |overlap|": overlap,
                        "auto": auto,
                        "load1": load1(),
                    }
                )
    report.table(
        f"Median of {args.repeats} alternating runs, each with its factorisation",
        rows,
        note=f"{load_note()} at end. Threads: {'default' if not args.threads else args.threads}.",
    )
    report.save()


if __name__ == "__main__":
    main()
