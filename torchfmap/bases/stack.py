"""Stacks of feature-aware functions, orthonormalised in the paper's order (Sect. 4): diffusion
(small to large time), harmonic, then Laplacian eigenfunctions."""

from __future__ import annotations

from typing import Literal

import numpy as np

from ..errors import ParameterError
from ..mesh import Mesh
from ..operators.laplacian import Operators, laplacian
from .basis import Basis
from .diffusion import DEFAULT_TIMES, Method, diffusion_basis
from .harmonic import harmonic_basis
from .laplacian import laplacian_eigenbasis
from .orthonormalize import orthonormalize


def concatenate(bases: list[Basis]) -> Basis:
    """Bases on the same mesh side by side (provenance kept); one basis is returned as it is."""
    if not bases:
        raise ParameterError("nothing to concatenate. Fix: pass at least one basis.")
    if len(bases) == 1:
        return bases[0]
    n = bases[0].n_vertices
    if any(b.n_vertices != n for b in bases):
        raise ParameterError("bases live on meshes of different sizes. Fix: build them on the same mesh.")
    values = np.concatenate([b.values for b in bases], axis=1)
    prov = [c for b in bases for c in b.columns]
    stiffness = next((b.stiffness for b in bases if b.stiffness is not None), None)
    return Basis(values, bases[0].mass, prov, stiffness=stiffness)


def basis_stack(
    mesh: Mesh,
    seeds,
    *,
    times=DEFAULT_TIMES,
    harmonic: bool = True,
    n_eigen: int = 0,
    operators: Operators | None = None,
    method: Method = "krylov",
    orthonormalization: Literal["mgs", "cholqr"] | None = "mgs",
    tol: float | None = None,
    heat_tol: float = 1e-8,
    local: bool | Literal["auto"] = "auto",
) -> Basis:
    """B-orthonormal stack of diffusion (``times``, relative; empty: none), harmonic (at ``seeds
    (k,)``) and ``n_eigen`` Laplacian functions, in that order; ``orthonormalization``: ``'mgs'``,
    ``'cholqr'`` (drop tolerance ``tol``) or None for the raw stack. ``basis.dropped`` lists the
    dependent columns."""
    ops = operators if operators is not None else laplacian(mesh)
    parts: list[Basis] = []
    if len(np.atleast_1d(times)):
        parts.append(diffusion_basis(mesh, seeds, times, method, operators=ops, tol=heat_tol, local=local))
    if harmonic:
        parts.append(harmonic_basis(mesh, seeds, operators=ops))
    if n_eigen:
        parts.append(laplacian_eigenbasis(mesh, n_eigen, operators=ops))
    if not parts:
        raise ParameterError("empty stack. Fix: give times, harmonic=True or n_eigen > 0.")
    stacked = concatenate(parts)
    if orthonormalization is None:
        return stacked
    return orthonormalize(stacked, scheme=orthonormalization, tol=tol)
