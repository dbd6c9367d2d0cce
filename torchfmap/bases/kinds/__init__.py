"""The registry of basis kinds: name -> kind object (see :mod:`.base` for what a kind holds).

A new kind is one module in this folder and one line in :data:`KINDS`.
"""

from __future__ import annotations

from ...errors import ParameterError
from ..basis import Basis
from .base import BasisKind, SeededKind, relative_times, seed_time
from .diffusion import DIFFUSION
from .eigen_diffusion import EIGEN_DIFFUSION
from .harmonic import HARMONIC
from .laplacian import LAPLACIAN
from .stack import STACK

#: Every basis kind by name, in the order the command line lists them.
KINDS: dict[str, BasisKind] = {
    kind.name: kind for kind in (LAPLACIAN, DIFFUSION, HARMONIC, STACK, EIGEN_DIFFUSION)
}


def get_kind(name: str | BasisKind) -> BasisKind:
    """The kind called ``name`` (a kind object is returned as it is).

    Raises:
        ParameterError: an unknown name.
    """
    if isinstance(name, BasisKind):
        return name
    try:
        return KINDS[name]
    except (KeyError, TypeError):
        raise ParameterError(f"unknown basis kind {name!r}. Fix: one of {', '.join(KINDS)}.") from None


def kind_of(basis: Basis) -> str | None:
    """The registered kind whose column kinds are exactly those of ``basis``'s kept columns
    (e.g. ``'stack'`` for heat kernels and harmonic functions), or None for other mixes."""
    present = frozenset(c.kind for c in basis.columns)
    return next((name for name, kind in KINDS.items() if kind.column_kinds == present), None)


__all__ = ["KINDS", "BasisKind", "SeededKind", "get_kind", "kind_of", "relative_times", "seed_time"]
