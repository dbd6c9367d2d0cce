"""The diffusion kind: heat kernels ``K_t(p_i, ·)`` at seeds, at one or more relative times."""

from __future__ import annotations

from dataclasses import dataclass

from ..bases.prepared import seed_kernels
from ..fmap.defaults import W_LAP_KERNELS
from .base import SeededKind, relative_times


@dataclass(frozen=True, kw_only=True)
class DiffusionKind(SeededKind):
    """One heat kernel per seed and relative time (time-major columns), from the shape's kernel
    cache (:func:`~torchfmap.bases.prepared.seed_kernels`)."""

    def columns_per_seed(self, times) -> int:
        return len(relative_times(times, 1))  # checked here: an empty list is refused, not divided by

    def functions(self, shape, seeds, times=None):
        return seed_kernels(shape, seeds, relative_times(times, len(seeds)))


DIFFUSION = DiffusionKind(
    name="diffusion",
    summary="heat kernels at corresponding seeds (landmarks + farthest points)",
    # Projected Laplacians of small-t heat kernels have very large top eigenvalues, which
    # dominate the mask's mean: bases with diffusion columns need a larger weight than eigenbases
    # (python -m bench accuracy --case weight_sweep).
    w_lap=W_LAP_KERNELS,
    column_families=frozenset({"diffusion"}),
)
