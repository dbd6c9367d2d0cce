"""The harmonic kind: ``Δψ_i = 0`` away from the seeds, ``ψ_i(p_j) = δ_ij`` at them."""

from __future__ import annotations

from dataclasses import dataclass

from ..bases.harmonic import harmonic_basis
from ..fmap.defaults import W_LAP_SMOOTH
from .base import SeededKind


@dataclass(frozen=True, kw_only=True)
class HarmonicKind(SeededKind):
    """One harmonic function per seed (they depend on the whole seed set: always rebuilt)."""

    def columns_per_seed(self, times) -> int:
        return 1

    def functions(self, shape, seeds, times=None):
        return harmonic_basis(shape.mesh, seeds, operators=shape.operators)


HARMONIC = HarmonicKind(
    name="harmonic",
    summary="harmonic functions interpolating corresponding seeds",
    w_lap=W_LAP_SMOOTH,
    column_families=frozenset({"harmonic"}),
)
