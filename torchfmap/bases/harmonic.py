"""Harmonic basis: ``Δψ_i = 0`` away from the seeds, ``ψ_i(p_j) = δ_ij`` at the seeds, solved as
``L_II ψ_I = -L_IS`` (one factorisation)."""

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
    """``(V, k)`` harmonic interpolants of the indicators of ``seeds (k,)`` for stiffness ``L (V,
    V)``; ``symmetric``: whether ``L`` is (Cholesky), detected when None."""
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
    mesh: Mesh, seeds, *, scheme: LaplacianScheme = "cotan", operators: Operators | None = None
) -> Basis:
    """The harmonic basis of ``seeds (k,)`` (a seed on every component): a non-orthonormal
    :class:`Basis` of ``(V, k)`` values, provenance ``('harmonic', seed)``, from ``operators``
    ``(L, B)`` or the Laplacian of ``scheme``."""
    seeds = check_vertex_indices(seeds, mesh.n_vertices, "seeds")
    check_seeds_cover_components(mesh, seeds)
    L, B = operators if operators is not None else laplacian(mesh, scheme=scheme)
    psi = harmonic_functions(L, seeds)
    return Basis(psi, B, [Column("harmonic", int(s)) for s in seeds], stiffness=L)
