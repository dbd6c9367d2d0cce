"""Error and warning types raised by torchfmap.

Every error message names the problem *and* the fix, e.g.
``MeshError: 3 faces index vertices outside [0, 100): faces [4, 7, 9]. Fix: ...``.
All errors derive from :class:`TorchFmapError` and from :class:`ValueError`, so
``except ValueError`` keeps working for callers that do not know our types.
"""

from __future__ import annotations


class TorchFmapError(ValueError):
    """Base class of all torchfmap input errors."""


class MeshError(TorchFmapError):
    """The mesh is unusable as given (empty, non-finite, bad faces, non-manifold, ...)."""


class SeedError(TorchFmapError):
    """Seeds / landmarks are invalid (duplicates, out of range, missing on a component)."""


class ParameterError(TorchFmapError):
    """A numerical parameter is outside its valid range (t <= 0, k too large, ...)."""


class ConvergenceError(TorchFmapError, RuntimeError):
    """An iterative solver stopped before reaching its tolerance (never returned silently)."""


class NotPositiveDefiniteError(ParameterError):
    """A Cholesky backend was asked for, but the matrix is not symmetric positive definite."""


class CorruptFileError(TorchFmapError):
    """A saved file is truncated, altered or unreadable."""


class MeshWarning(UserWarning):
    """A mesh property worth knowing about that does not stop the computation (e.g. holes)."""


def _preview(indices, limit: int = 8) -> str:
    """Render the first few offending indices, e.g. ``[3, 17, 42, ...] (12 in all)``."""
    items = [int(i) for i in list(indices)[:limit]]
    n = len(indices)
    text = ", ".join(str(i) for i in items)
    return f"[{text}{', ...' if n > limit else ''}]" + (f" ({n} in all)" if n > limit else "")
