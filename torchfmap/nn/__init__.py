"""PyTorch layers over the classical path's functional-map code: functions (:mod:`torchfmap.nn.functional`)
do the work, modules hold settings and buffers. Shapes: ``(B, V, K)`` basis values, ``(B, V)`` lumped mass,
``(B, V, D)`` features, ``(B, K_y, K_x)`` maps ``C_xy``, padding in :class:`BasisBatch`.
``check: bool | None = None`` switches data checks (None: CPU inputs only)."""

from . import functional
from .checkpoints import load_checkpoint, read_checkpoint, read_recipe, save_checkpoint
from .config import Budget, CosineBudget, TrainConfig, build_model, build_solver
from .data import (
    PairDataset,
    PrecomputeCache,
    ShapeBatch,
    ShapeDataset,
    class_pairs,
    collate_pairs,
    collate_shapes,
)
from .devices import resolve_device
from .functional import BasisBatch, FmapPair, GradientBatch, SoftMaps, TangentGradient
from .inference import LearnedMatcher
from .inputs import coordinates_on, network_inputs, shape_arrays, shape_item
from .item_inference import adapt, evaluate, predict_p2p
from .modules import (
    BasisModule,
    RegularizedFMSolver,
    SoftPointMap,
    SpectralDiffusion,
    UnsupervisedFMLoss,
    basis_arrays,
)
from .networks import DiffusionNet, FeatureNetwork, SpatialGradientFeatures, check_network, features
from .parts import PartLoss, PartPairs, part_score
from .shipped import shipped_models
from .train import TrainState, unsupervised_score
from .trainer import Trainer

__all__ = [
    "BasisBatch", "BasisModule", "Budget", "CosineBudget", "LearnedMatcher", "TrainConfig", "TrainState",
    "Trainer", "adapt", "build_model", "build_solver", "evaluate", "load_checkpoint", "predict_p2p",
    "read_checkpoint", "read_recipe", "save_checkpoint", "shipped_models", "resolve_device",
    "unsupervised_score", "DiffusionNet", "FeatureNetwork", "FmapPair", "GradientBatch", "PairDataset",
    "PrecomputeCache", "RegularizedFMSolver", "ShapeBatch", "ShapeDataset", "SoftMaps", "SoftPointMap",
    "SpatialGradientFeatures", "SpectralDiffusion", "TangentGradient", "UnsupervisedFMLoss",
    "basis_arrays", "check_network", "class_pairs", "collate_pairs", "collate_shapes", "coordinates_on",
    "features", "functional", "network_inputs", "part_score", "PartLoss", "PartPairs", "shape_arrays",
    "shape_item",
]  # fmt: skip
