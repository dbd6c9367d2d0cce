"""PyTorch layers over the same functional-map code as the classical path.

Functions (:mod:`torchfmap.nn.functional`) do the work; modules hold settings and buffers.
Shapes: ``(B, V, K)`` basis values, ``(B, V)`` lumped mass, ``(B, V, D)`` features,
``(B, K_y, K_x)`` maps ``C_xy``.
"""

from . import functional
from .data import PairDataset, PrecomputeCache, ShapeDataset, collate_pairs, collate_shapes, precompute_shape
from .functional import BasisBatch
from .modules import (
    BasisModule,
    FeatureNet,
    RegularizedFMSolver,
    SoftPointMap,
    SpectralDiffusion,
    UnsupervisedFMLoss,
    basis_arrays,
)

__all__ = [
    "BasisBatch",
    "BasisModule",
    "FeatureNet",
    "PairDataset",
    "PrecomputeCache",
    "RegularizedFMSolver",
    "ShapeDataset",
    "SoftPointMap",
    "SpectralDiffusion",
    "UnsupervisedFMLoss",
    "basis_arrays",
    "collate_pairs",
    "collate_shapes",
    "functional",
    "precompute_shape",
]
