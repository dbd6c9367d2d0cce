"""The diffusion kind: heat kernels ``K_t(p_i, ·)`` at seeds, at one or more relative times."""

from __future__ import annotations

from dataclasses import dataclass

from ..bases.prepared import seed_kernels
from ..fmap.defaults import W_LAP_KERNELS
from .base import SeededKind, relative_times


@dataclass(frozen=True, kw_only=True)
class DiffusionKind(SeededKind):
    """One heat kernel per seed and relative time (time-major), from the shape's kernel cache."""

    def columns_per_seed(self, times) -> int:
        return len(relative_times(times, 1))  # checked: an empty list is refused

    def functions(self, shape, seeds, times=None):
        return seed_kernels(shape, seeds, relative_times(times, len(seeds)))


DIFFUSION = DiffusionKind(
    name="diffusion",
    summary="heat kernels at corresponding seeds (landmarks + farthest points)",
    w_lap=W_LAP_KERNELS,
    column_families=frozenset({"diffusion"}),
)
