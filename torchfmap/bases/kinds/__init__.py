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
from .hybrid import HYBRID
from .laplacian import LAPLACIAN
from .stack import STACK

#: Every basis kind by name, in the order the command line lists them.
KINDS: dict[str, BasisKind] = {
    kind.name: kind for kind in (LAPLACIAN, HYBRID, DIFFUSION, HARMONIC, STACK, EIGEN_DIFFUSION)
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


def learned_kind(name: str | BasisKind) -> BasisKind:
    """:func:`get_kind` for the torch layers: the kind, if :mod:`torchfmap.nn` solves in it.

    Raises:
        ParameterError: an unknown kind, or one the learned path does not solve in.
    """
    kind = get_kind(name)
    if not kind.learned:
        usable = ", ".join(n for n, k in KINDS.items() if k.learned)
        raise ParameterError(
            f"the {kind.name} basis is solved block-wise by torchfmap.match only; the learned path "
            f"(torchfmap.nn, torchfmap train) does not solve in it. Fix: one of {usable}."
        )
    return kind


def kind_of(basis: Basis) -> str | None:
    """The first registered kind that recognises ``basis`` (:meth:`BasisKind.recognises`: by
    default its kept columns' kinds, e.g. ``'stack'`` for heat kernels and harmonic functions),
    or None for other mixes."""
    return next((name for name, kind in KINDS.items() if kind.recognises(basis)), None)


__all__ = [
    "KINDS",
    "BasisKind",
    "SeededKind",
    "get_kind",
    "kind_of",
    "learned_kind",
    "relative_times",
    "seed_time",
]
