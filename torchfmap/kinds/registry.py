"""The registry of basis kinds: name -> kind object (:class:`~torchfmap.kinds.BasisKind`).

:mod:`torchfmap.kinds` registers each built-in kind on import; a kind from outside the package
is registered with :func:`register_kind`. Everything that asks about a kind (``match``, the
command line's ``--basis`` choices, the datasets, the learned layers) reads it here; the
functional-map layer below (:mod:`torchfmap.fmap`) knows no kind and takes plain weights.
"""

from __future__ import annotations

from ..bases.basis import Basis
from ..errors import ParameterError
from .base import BasisKind

#: Every basis kind by name, in the order the command line lists them.
KINDS: dict = {}


def register_kind(kind: BasisKind):
    """Add ``kind`` (a :class:`torchfmap.kinds.BasisKind`) to :data:`KINDS` under its ``name``;
    returns it. Registering a name again replaces the kind.

    Raises:
        ParameterError: an object without a non-empty string ``name``.
    """
    name = getattr(kind, "name", None)
    if not isinstance(name, str) or not name:
        raise ParameterError(f"a basis kind needs a non-empty string name, got {name!r}.")
    KINDS[name] = kind
    return kind


def get_kind(name):
    """The kind called ``name`` (a kind object is returned as it is).

    Raises:
        ParameterError: an unknown name.
    """
    if not isinstance(name, str) and hasattr(name, "pair_bases"):
        return name
    try:
        return KINDS[name]
    except (KeyError, TypeError):
        raise ParameterError(f"unknown basis kind {name!r}. Fix: one of {', '.join(KINDS)}.") from None


def learned_kind(name):
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
    """The first registered kind that recognises ``basis`` (``kind.recognises``: by default its
    kept columns' families, e.g. ``'stack'`` for heat kernels and harmonic functions), or None
    for other mixes."""
    return next((name for name, kind in KINDS.items() if kind.recognises(basis)), None)
