"""Harmonic basis: ``Δψ_i = 0`` away from the seeds, ``ψ_i(p_j) = δ_ij`` at the seeds.

With ``I`` the free (non-seed) vertices and ``S`` the seeds, the discrete problem is
``L_II ψ_I = -L_IS`` (one column per seed): **one** factorisation of ``L_II`` and one block
solve with ``k`` right-hand sides. ``L_II`` is symmetric positive definite for ``cotan`` and
``robust`` weights when every connected component holds a seed (Cholesky), and non-symmetric
for ``mean_value`` weights (sparse LU).

Properties (tested): ``ψ_i(p_j) = δ_ij`` exactly; ``Σ_i ψ_i = 1`` (rows of ``L`` sum to zero,
so the constant solves the summed problem); with non-negative weights (``robust``,
``mean_value``, or ``cotan`` on a Delaunay mesh) each ``ψ_i`` lies in ``[0, 1]`` and peaks at its
own seed (discrete maximum principle). Negative cotan weights can break the maximum principle
slightly (undulations, values a little outside ``[0, 1]``).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .._util.checks import check_seeds_cover_components, check_vertex_indices, is_symmetric
from ..errors import SeedError
from ..mesh import Mesh
from ..operators.laplacian import LaplacianScheme, Operators, laplacian
from ..operators.solvers import factorize
from .basis import Basis, Column


def harmonic_functions(L: sp.spmatrix, seeds, *, symmetric: bool | None = None) -> np.ndarray:
    """``(V, k)`` harmonic interpolants of the seed indicators for stiffness ``L``.

    Args:
        L: ``(V, V)`` stiffness (rows summing to zero).
        seeds: ``(k,)`` distinct vertex indices.
        symmetric: whether ``L`` is symmetric (Cholesky); detected when None.
    """
    L = sp.csr_matrix(L)
    n = L.shape[0]
    seeds = check_vertex_indices(seeds, n, "seeds")
    free = np.ones(n, dtype=bool)
    free[seeds] = False
    interior = np.flatnonzero(free)
    psi = np.zeros((n, len(seeds)))
    psi[seeds, np.arange(len(seeds))] = 1.0
    if len(interior) == 0:
        return psi
    if symmetric is None:
        symmetric = is_symmetric(L)
    L_ii = L[interior][:, interior]
    rhs = -L[interior][:, seeds].toarray()
    fac = factorize(L_ii, spd=symmetric)
    psi[interior] = fac.solve(rhs)
    if not np.isfinite(psi).all():
        raise SeedError(
            "the harmonic system is singular: some part of the mesh is not connected to any seed. "
            "Fix: put a seed on every connected component."
        )
    return psi


def harmonic_basis(
    mesh: Mesh,
    seeds,
    *,
    scheme: LaplacianScheme = "cotan",
    operators: Operators | None = None,
) -> Basis:
    """The harmonic basis of ``seeds`` as a (non-orthonormal) :class:`Basis`.

    Args:
        mesh: the surface (every connected component needs at least one seed).
        seeds: ``(k,)`` distinct vertex indices.
        scheme: the Laplacian's scheme (``'cotan'``, ``'robust'``, ``'mean_value'``,
            :func:`~torchfmap.laplacian`) when ``operators`` is not given.
        operators: precomputed ``(L, B)``; ``L`` may be non-symmetric.

    Returns:
        ``Basis`` with ``(V, k)`` values and provenance ``('harmonic', seed)``.
    """
    seeds = check_vertex_indices(seeds, mesh.n_vertices, "seeds")
    check_seeds_cover_components(mesh, seeds)
    L, B = operators if operators is not None else laplacian(mesh, scheme=scheme)
    psi = harmonic_functions(L, seeds)
    return Basis(psi, B, [Column("harmonic", int(s)) for s in seeds], stiffness=L)
