"""The registry of basis kinds: name -> kind object.

It lives with the bases because which kind made a basis, and which weights solve in it, are
facts about the basis that the functional-map layer reads (:mod:`torchfmap.fmap.defaults`).
The kinds themselves (how each builds its bases, solves and refines its maps) live above the
solver in :mod:`torchfmap.kinds`, which registers each built-in kind here on import; a kind
from outside the package is registered with :func:`register_kind`.
"""

from __future__ import annotations

from ..errors import ParameterError
from .basis import Basis

#: Every basis kind by name (a kind object of :mod:`torchfmap.kinds`), in the order the command
#: line lists them.
KINDS: dict = {}
#: Names of bases of no registered kind (``fmap.defaults.basis_kind``), never a kind's name.
RESERVED_NAMES = ("custom", "diffusion_mix")


def register_kind(kind):
    """Add ``kind`` (a :class:`torchfmap.kinds.BasisKind`) to :data:`KINDS` under its ``name``;
    returns it. Registering a name again replaces the kind.

    Raises:
        ParameterError: an object without a string ``name``, or a name reserved for bases of no
            kind (:data:`RESERVED_NAMES`).
    """
    name = getattr(kind, "name", None)
    if not isinstance(name, str) or not name:
        raise ParameterError(f"a basis kind needs a non-empty string name, got {name!r}.")
    if name in RESERVED_NAMES:
        raise ParameterError(
            f"{name!r} names bases of no registered kind (torchfmap.fmap.defaults.W_LAP_OTHER). "
            "Fix: give the kind another name."
        )
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
    kept columns' kinds, e.g. ``'stack'`` for heat kernels and harmonic functions), or None for
    other mixes."""
    return next((name for name, kind in KINDS.items() if kind.recognises(basis)), None)
