"""One home for the default weights and rules of the functional-map solve, shared by
:func:`~torchfmap.fmap.solve_fmap`, :func:`~torchfmap.fmap.fmap_to_p2p`,
:func:`torchfmap.match` and :class:`torchfmap.nn.RegularizedFMSolver`.

A default that depends on the basis is read off the basis' provenance (:func:`basis_kind`),
so the same call gives the same map whichever entry point makes it.
"""

from __future__ import annotations

from ..bases.basis import Basis

#: Laplacian-commutativity weight per basis kind (the mask is normalised to mean 1), chosen
#: by ``python bench/weight_sweep.py``. Projected Laplacians of small-t heat kernels have very
#: large top eigenvalues, which dominate the mask's mean, so bases with diffusion columns need
#: a larger weight than eigenbases.
W_LAP = {"laplacian": 0.1, "harmonic": 0.1, "diffusion": 1.0, "stack": 1.0, "custom": 0.1}
#: Orientation-preservation weight when both meshes are given (tells left from right).
W_ORIENT = 1e-2
#: Pointwise landmark-preservation weight when landmarks are given.
W_LMK = 1.0


def basis_kind(basis: Basis) -> str:
    """``'laplacian'``, ``'harmonic'`` or ``'custom'`` when every kept column is of that kind,
    ``'diffusion'`` when every column is a heat kernel, ``'stack'`` for diffusion mixed with
    other kinds."""
    kinds = {c.kind for c in basis.columns}
    if len(kinds) == 1:
        return kinds.pop()
    return "stack" if "diffusion" in kinds else "custom"


def default_w_lap(basis_x: Basis, basis_y: Basis) -> float:
    """:data:`W_LAP` of the pair's kind (the larger one if the two kinds differ)."""
    return max(W_LAP.get(basis_kind(b), W_LAP["custom"]) for b in (basis_x, basis_y))


def default_p2p_mode(basis_x: Basis, basis_y: Basis) -> str:
    """``'orthogonal'`` (nearest neighbours of ``Φ_y`` in ``Φ_x Cᵀ``) when both bases are
    eigenbases, where maps of near-isometries are near-orthogonal; ``'pullback'`` otherwise."""
    eigen = all(basis_kind(b) == "laplacian" for b in (basis_x, basis_y))
    return "orthogonal" if eigen else "pullback"
