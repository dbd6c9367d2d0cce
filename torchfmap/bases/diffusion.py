"""The diffusion basis: heat kernels (:func:`~torchfmap.operators.heat.heat_kernels`) at seeds and
relative times ``t`` (absolute ``t·|M|``: scale invariant)."""

from __future__ import annotations

from typing import Literal

import numpy as np

from .._util.checks import check_seeds_cover_components, check_times, check_vertex_indices
from ..mesh import Mesh
from ..operators.heat import Method, heat_kernels
from ..operators.laplacian import Operators, laplacian
from .basis import Basis, Column

#: Default relative times ``t`` (absolute ``t * |M|``), small to large.
DEFAULT_TIMES = (1e-3, 3e-3, 1e-2, 3e-2)


def diffusion_basis(
    mesh: Mesh,
    seeds,
    times=DEFAULT_TIMES,
    method: Method = "krylov",
    *,
    operators: Operators | None = None,
    kernel: Literal["delta", "indicator"] = "delta",
    tol: float = 1e-8,
    local: bool | Literal["auto"] = "auto",
    **kwargs,
) -> Basis:
    """Heat kernels at every seed and relative time ``t`` (absolute ``t·|M|``), not orthonormal: a
    :class:`Basis` of ``(V, T·S)`` values, time-major, provenance ``('diffusion', seed, t)``.
    ``method``, ``kernel``, ``tol``, ``local`` and ``kwargs`` go to
    :func:`~torchfmap.operators.heat.heat_kernels`.

    Raises:
        ParameterError: a time that is not finite and > 0, or what ``heat_kernels`` raises.
        SeedError: seeds out of range or missing a connected component.
    """
    ops = operators if operators is not None else laplacian(mesh)
    rel = check_times(times)
    order = np.argsort(rel, kind="stable")
    rel = rel[order]
    seeds = check_vertex_indices(seeds, mesh.n_vertices, "seeds")
    check_seeds_cover_components(mesh, seeds)
    K = heat_kernels(
        ops,
        seeds,
        rel * mesh.area,
        method,
        kernel=kernel,
        tol=tol,
        local=local,
        vertices=mesh.vertices,
        **kwargs,
    )
    values = K.transpose(1, 0, 2).reshape(mesh.n_vertices, -1)  # (V, T*S), time-major
    prov = [Column("diffusion", int(s), float(t)) for t in rel for s in seeds]
    return Basis(values, ops[1], prov, stiffness=ops[0])
