"""The default weights of the functional-map solve and ZoomOut's default step: plain numbers.

:func:`~torchfmap.fmap.solve_fmap` and :class:`torchfmap.nn.RegularizedFMSolver` default to
them. A weight or point-map rule that depends on the kind of basis belongs to the kind (in
:mod:`torchfmap.kinds`, above this layer), and :func:`torchfmap.match` passes it to the solver.
Nothing here knows a basis kind.
"""

from __future__ import annotations

#: The basis size ``k`` of every match, classical or learned, and of the command line, when none is
#: given (ZoomOut grows it to ``2k`` by default).
DEFAULT_K = 50
#: Laplacian-commutativity weight of eigenfunctions and of bases with no heat kernels (the mask
#: is normalised to mean 1), chosen by ``python -m bench accuracy --case weight_sweep``; the default of
#: :func:`~torchfmap.fmap.solve_fmap`.
W_LAP_SMOOTH = 0.1
#: Laplacian-commutativity weight of bases holding heat kernels, whose projected Laplacians have
#: very large top eigenvalues, which dominate the mask's mean.
W_LAP_KERNELS = 1.0
#: Orientation-preservation weight when both meshes are given (tells left from right). Each
#: operator pair is scaled to unit norm (``fmap.solver``), so at 1 the 16 orientation pairs
#: together weigh like several times the descriptor term: on humans, whose limbs WKS cannot
#: tell apart, weaker settings mix up left and right (``python -m bench accuracy --case faust``).
W_ORIENT = 1.0
#: Descriptor-commutativity weight of :func:`torchfmap.match` (multiplication operators,
#: Nogneng & Ovsjanikov 2017): it asks ``C`` to carry each descriptor's product structure,
#: which the descriptor term alone does not constrain (``python -m bench accuracy --case faust``).
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


def zoomout_step(k: int) -> int:
    """Default ZoomOut step for a start of ``k`` eigenfunctions."""
    return max(1, k // ZOOMOUT_STEP_DIVISOR)


#: Above this many vertex pairs ``V_x V_y`` (two meshes of 10K vertices), point maps and every
#: ZoomOut leave the exhaustive nearest-neighbour search: iterations run on
#: :data:`SURFACE_SAMPLES` samples per shape and the map of every vertex is searched near where
#: its samples went (:func:`~torchfmap.fmap.nearest.local_nearest`); at or below it, every
#: vertex is compared with every vertex (``python -m bench speed --case dense``).
LOCAL_SEARCH_PAIRS = 10_000**2
#: Samples per shape of the sampled ZoomOut and the local search
#: (:func:`~torchfmap.fmap.nearest.surface_sampling`): their least-squares fits hold ``k_final``
#: columns many times over.
SURFACE_SAMPLES = 3000
#: Above ``SURFACE_SAMPLES`` times this many vertices, one sample per this many: the local
#: search compares each vertex with the vertices of a few cells around its image, so its cost
#: grows with ``V² / S`` (``V`` at a fixed cell size), the samples' own search with ``S²``.
VERTICES_PER_SAMPLE = 100
