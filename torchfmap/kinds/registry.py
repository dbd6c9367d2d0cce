"""The registry of basis kinds: name -> kind object (:class:`~torchfmap.kinds.BasisKind`);
:mod:`torchfmap.kinds` registers the built-in ones on import."""

from __future__ import annotations

from ..bases.basis import Basis
from ..errors import ParameterError
from .base import BasisKind

#: Every basis kind by name, in the order the command line lists them.
KINDS: dict = {}


def register_kind(kind: BasisKind):
    """Add ``kind`` to :data:`KINDS` under its ``name`` (replacing any) and return it; ParameterError
    without a non-empty string ``name``."""
    name = getattr(kind, "name", None)
    if not isinstance(name, str) or not name:
        raise ParameterError(f"a basis kind needs a non-empty string name, got {name!r}.")
    KINDS[name] = kind
    return kind


def get_kind(name):
    """The kind called ``name`` (a kind object as it is); ParameterError for an unknown name."""
    if not isinstance(name, str) and hasattr(name, "pair_bases"):
        return name
    try:
        return KINDS[name]
    except (KeyError, TypeError):
        raise ParameterError(f"unknown basis kind {name!r}. Fix: one of {', '.join(KINDS)}.") from None


def learned_kind(name):
    """:func:`get_kind`, refusing (ParameterError) a kind the torch layers do not solve in."""
    kind = get_kind(name)
    if not kind.learned:
        usable = ", ".join(n for n, k in KINDS.items() if k.learned)
        raise ParameterError(
            f"the {kind.name} basis is solved block-wise by torchfmap.match only; the learned path "
            f"(torchfmap.nn, torchfmap train) does not solve in it. Fix: one of {usable}."
        )
    return kind


def kind_of(basis: Basis) -> str | None:
    """The name of the first registered kind that recognises ``basis`` (``kind.recognises``), or None."""
    return next((name for name, kind in KINDS.items() if kind.recognises(basis)), None)
