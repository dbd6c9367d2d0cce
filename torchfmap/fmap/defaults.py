"""Default weights of the functional-map solve, ZoomOut's default step and search thresholds:
plain numbers (a kind's own settings live in :mod:`torchfmap.kinds`)."""

from __future__ import annotations

#: The basis size ``k`` of every match and of the command line when none is given.
DEFAULT_K = 50
#: Laplacian-commutativity weight of bases with no heat kernels (the mask has mean 1).
W_LAP_SMOOTH = 0.1
#: Laplacian-commutativity weight of bases holding heat kernels (huge top eigenvalues dominate the mask).
W_LAP_KERNELS = 1.0
#: Orientation-preservation weight when both meshes are given (tells left from right).
W_ORIENT = 1.0
#: Descriptor-commutativity weight of :func:`torchfmap.match` (:func:`~torchfmap.fmap.solve_fmap`: 0).
W_DCOMM = 0.3
#: Pointwise landmark-preservation weight when landmarks are given.
W_LMK = 1.0
#: Weight of the proximity-to-identity prior for feature-aware bases built at corresponding
#: seeds (relative to the descriptor term; ``inf``: ``C = I`` exactly, no descriptors needed).
W_PRIOR = float("inf")
#: ZoomOut adds ``max(1, k // ZOOMOUT_STEP_DIVISOR)`` eigenfunctions per iteration by default.
ZOOMOUT_STEP_DIVISOR = 10


def zoomout_step(k: int) -> int:
    """Default ZoomOut step for a start of ``k`` eigenfunctions."""
    return max(1, k // ZOOMOUT_STEP_DIVISOR)


#: Above this many vertex pairs ``V_x V_y``, point maps and ZoomOut search locally around
#: :data:`SURFACE_SAMPLES` samples per shape (:func:`~torchfmap.fmap.nearest.local_nearest`).
LOCAL_SEARCH_PAIRS = 10_000**2
#: Samples per shape of the sampled ZoomOut and the local search.
SURFACE_SAMPLES = 3000
#: Above ``SURFACE_SAMPLES`` times this many vertices, one sample per this many vertices.
VERTICES_PER_SAMPLE = 100
