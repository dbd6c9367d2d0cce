"""One home for the default weights and rules of the functional-map solve, shared by
:func:`~torchfmap.fmap.solve_fmap`, :func:`~torchfmap.fmap.fmap_to_p2p`,
:func:`torchfmap.match`, the refinements and :class:`torchfmap.nn.RegularizedFMSolver`.

A default that depends on the basis is read off the basis' kind in the registry
(:data:`torchfmap.bases.KINDS`, recognised from the columns' provenance by
:func:`~torchfmap.bases.kind_of`; the kinds themselves live in :mod:`torchfmap.kinds`), so
the same call gives the same map whichever entry point makes it.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping

from ..bases.basis import Basis
from ..bases.registry import KINDS, kind_of

#: Laplacian-commutativity weight of eigenfunctions and of bases with no heat kernels (the mask
#: is normalised to mean 1), chosen by ``python bench/weight_sweep.py``.
W_LAP_SMOOTH = 0.1
#: Laplacian-commutativity weight of bases holding heat kernels, whose projected Laplacians have
#: very large top eigenvalues, which dominate the mask's mean.
W_LAP_KERNELS = 1.0
#: Laplacian-commutativity weight of bases of no registered kind: ``'diffusion_mix'`` for mixes
#: holding heat kernels, ``'custom'`` for the rest.
W_LAP_OTHER = {"diffusion_mix": W_LAP_KERNELS, "custom": W_LAP_SMOOTH}  # registry.RESERVED_NAMES
#: Orientation-preservation weight when both meshes are given (tells left from right), for
#: bases of no registered kind and the kinds' default; a kind's own is its ``w_orient``. Each
#: operator pair is scaled to unit norm (``fmap.solver``), so at 1 the 16 orientation pairs
#: together weigh like several times the descriptor term: on humans, whose limbs WKS cannot
#: tell apart, weaker settings mix up left and right (``python3 bench/faust.py``).
W_ORIENT = 1.0


class _KindWeights(Mapping):
    """:data:`W_LAP`: each registered kind's ``w_lap`` (read when asked, so a kind registered
    later is seen), then :data:`W_LAP_OTHER`."""

    def __getitem__(self, name: str) -> float:
        return KINDS[name].w_lap if name in KINDS else W_LAP_OTHER[name]

    def __iter__(self) -> Iterator[str]:
        return iter([*KINDS, *W_LAP_OTHER])

    def __len__(self) -> int:
        return len(KINDS) + len(W_LAP_OTHER)

    def __repr__(self) -> str:
        return repr(dict(self))


#: Laplacian-commutativity weight per basis kind name (and of :data:`W_LAP_OTHER`).
W_LAP: Mapping[str, float] = _KindWeights()
#: Descriptor-commutativity weight of :func:`torchfmap.match` (multiplication operators,
#: Nogneng & Ovsjanikov 2017): it asks ``C`` to carry each descriptor's product structure,
#: which the descriptor term alone does not constrain (``python3 bench/faust.py``).
#: :func:`~torchfmap.fmap.solve_fmap` and the torch layers default to 0 (the layers have no such
#: term).
W_DCOMM = 0.3
#: Pointwise landmark-preservation weight when landmarks are given.
W_LMK = 1.0
#: Weight of the proximity-to-identity prior for feature-aware bases built at corresponding
#: seeds (relative to the descriptor term; ``inf``: ``C = I`` exactly, no descriptors needed).
W_PRIOR = float("inf")
#: ZoomOut adds ``max(1, k // ZOOMOUT_STEP_DIVISOR)`` eigenfunctions per iteration by default.
ZOOMOUT_STEP_DIVISOR = 10


def basis_kind(basis: Basis) -> str:
    """The registered kind of ``basis`` (:func:`~torchfmap.bases.kind_of`), else
    ``'diffusion_mix'`` if it holds heat kernels, else ``'custom'``."""
    kind = kind_of(basis)
    if kind is not None:
        return kind
    return "diffusion_mix" if any(c.family == "diffusion" for c in basis.columns) else "custom"


def default_w_lap(basis_x: Basis, basis_y: Basis) -> float:
    """The ``w_lap`` of the pair's kind (:data:`W_LAP`; the larger one if the kinds differ)."""
    names = [basis_kind(b) for b in (basis_x, basis_y)]
    return max(W_LAP[n] for n in names)


def default_w_orient(basis_x: Basis, basis_y: Basis) -> float:
    """The ``w_orient`` of the pair's kind (the smaller one if the kinds differ; :data:`W_ORIENT`
    for bases of no registered kind)."""
    names = [basis_kind(b) for b in (basis_x, basis_y)]
    return min(KINDS[n].w_orient if n in KINDS else W_ORIENT for n in names)


def default_p2p_mode(basis_x: Basis, basis_y: Basis) -> str:
    """The ``p2p_mode`` of the bases' kind when both are of one registered kind
    (``'orthogonal'``, nearest neighbours of ``Φ_y`` in ``Φ_x Cᵀ``, for eigenbases, where maps
    of near-isometries are near-orthogonal); ``'pullback'`` otherwise."""
    names = {basis_kind(b) for b in (basis_x, basis_y)}
    name = names.pop() if len(names) == 1 else None
    return KINDS[name].p2p_mode if name in KINDS else "pullback"


def zoomout_step(k: int) -> int:
    """Default ZoomOut step for a start of ``k`` eigenfunctions."""
    return max(1, k // ZOOMOUT_STEP_DIVISOR)
