"""PyTorch layers over the same functional-map code as the classical path.

Functions (:mod:`torchfmap.nn.functional`) do the work; modules hold settings and buffers.
Shapes: ``(B, V, K)`` basis values, ``(B, V)`` lumped mass, ``(B, V, D)`` features,
``(B, K_y, K_x)`` maps ``C_xy``.
"""

from . import functional
from .data import (
    PairDataset,
    PrecomputeCache,
    ShapeBatch,
    ShapeDataset,
    class_pairs,
    collate_pairs,
    collate_shapes,
    precompute_shape,
)
from .functional import BasisBatch, GradientBatch
from .modules import (
    BasisModule,
    FeatureNet,
    RegularizedFMSolver,
    SoftPointMap,
    SpectralDiffusion,
    UnsupervisedFMLoss,
    basis_arrays,
)
from .networks import DiffusionNet, FeatureNetwork, SpatialGradientFeatures

__all__ = [
    "BasisBatch",
    "BasisModule",
    "DiffusionNet",
    "FeatureNet",
    "FeatureNetwork",
    "GradientBatch",
    "PairDataset",
    "PrecomputeCache",
    "RegularizedFMSolver",
    "ShapeBatch",
    "ShapeDataset",
    "SoftPointMap",
    "SpatialGradientFeatures",
    "SpectralDiffusion",
    "UnsupervisedFMLoss",
    "basis_arrays",
    "class_pairs",
    "collate_pairs",
    "collate_shapes",
    "functional",
    "precompute_shape",
]
