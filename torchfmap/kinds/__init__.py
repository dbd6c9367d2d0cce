"""The basis kinds, their registry :data:`KINDS` and their refiners. A new kind is one module here
and one line in the tuple below (or :func:`register_kind`)."""

from __future__ import annotations

from .base import BasisKind, SeededKind, relative_times, seed_time
from .diffusion import DIFFUSION
from .eigen_diffusion import EIGEN_DIFFUSION
from .harmonic import HARMONIC
from .hybrid import HYBRID
from .laplacian import LAPLACIAN
from .refiners import ICP, REFINE_METHODS, FixedSizeIterations, SeedMoves, ZoomOut, check_refine
from .registry import KINDS, get_kind, kind_of, learned_kind, register_kind
from .stack import STACK

for _kind in (LAPLACIAN, HYBRID, DIFFUSION, HARMONIC, STACK, EIGEN_DIFFUSION):
    register_kind(_kind)
del _kind

__all__ = [
    "ICP", "KINDS", "REFINE_METHODS", "BasisKind", "FixedSizeIterations", "SeedMoves", "SeededKind",
    "ZoomOut", "check_refine", "get_kind", "kind_of", "learned_kind", "register_kind", "relative_times",
    "seed_time",
]  # fmt: skip
