"""The stack kind: heat kernels (small to large time), then harmonic functions, at the same seeds
(the paper's order, Sect. 4)."""

from __future__ import annotations

from dataclasses import dataclass

from ..bases.stack import concatenate
from ..fmap.defaults import W_LAP_KERNELS
from .base import SeededKind
from .diffusion import DIFFUSION
from .harmonic import HARMONIC


@dataclass(frozen=True, kw_only=True)
class StackKind(SeededKind):
    """Diffusion columns (every relative time) then one harmonic function per seed."""

    def columns_per_seed(self, times) -> int:
        return DIFFUSION.columns_per_seed(times) + HARMONIC.columns_per_seed(times)

    def functions(self, shape, seeds, times=None):
        return concatenate([DIFFUSION.functions(shape, seeds, times), HARMONIC.functions(shape, seeds)])


STACK = StackKind(
    name="stack",
    summary="heat kernels then harmonic functions at corresponding seeds",
    w_lap=W_LAP_KERNELS,
    column_families=frozenset({"diffusion", "harmonic"}),
)
