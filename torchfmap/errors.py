"""Error and warning types raised by torchfmap. Every error message names the problem and the fix; all
errors derive from :class:`TorchFmapError`, a :class:`ValueError`."""

from __future__ import annotations

import functools


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


class MemoryEstimateError(ParameterError, MemoryError):
    """Refused before it starts: its estimated memory exceeds what is available; a :class:`MemoryError`."""


class NotPositiveDefiniteError(ParameterError):
    """A Cholesky backend was asked for, but the matrix is not symmetric positive definite."""


class CorruptFileError(TorchFmapError):
    """A saved file is truncated, altered or unreadable."""


class FileWriteError(OSError, TorchFmapError):
    """A file could not be written; also an :class:`OSError`, of its class (:func:`file_write_error`)."""


class FileReadError(OSError, TorchFmapError):
    """A file could not be read; also an :class:`OSError`, of its class (:func:`file_read_error`)."""


@functools.cache
def _joined_class(kind: type, base: type) -> type:
    """``kind`` joined with the OSError subclass ``base`` (one class per pair)."""
    if base is OSError or issubclass(base, kind):
        return kind if base is OSError else base
    return type(base.__name__, (kind, base), {"__module__": __name__})


def _joined(kind: type, err: OSError, message: str):
    cls = _joined_class(kind, type(err))
    return cls(err.errno, message) if err.errno is not None else cls(message)


def file_read_error(err: OSError, path, what: str = "file") -> FileReadError:
    """A :class:`FileReadError` (also an instance of ``type(err)``, same errno) naming ``path``."""
    reason = err.strerror or str(err)
    message = f"cannot read the {what} {str(path)!r} ({reason}). Fix: check the path and its permissions."
    return _joined(FileReadError, err, message)


def file_write_error(err: OSError, message: str) -> FileWriteError:
    """A :class:`FileWriteError` that is also an instance of ``type(err)``, with its errno."""
    return _joined(FileWriteError, err, message)


class EvaluationInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`torchfmap.evaluate.collection.evaluate_pairs`: ``finished`` holds the
    :class:`~torchfmap.evaluate.collection.PairResult` of every pair scored before, in pair order."""

    def __init__(self, finished: list, total: int) -> None:
        super().__init__(f"interrupted after {len(finished)} of {total} pairs")
        self.finished, self.total = finished, total


class WorkerLost(TorchFmapError, RuntimeError):
    """A worker of :func:`torchfmap.evaluate.collection.evaluate_pairs` died mid-run: ``finished`` holds
    the :class:`~torchfmap.evaluate.collection.PairResult` of every pair scored before, in pair order."""

    def __init__(self, finished: list, total: int, cause: str) -> None:
        super().__init__(
            f"a worker process died ({cause}) after {len(finished)} of {total} pairs. Fix: check the "
            "machine's memory (fewer --workers, or --threads); with eval --out FILE the same command "
            "resumes from the finished pairs."
        )
        self.finished, self.total = finished, total


class MapWarning(UserWarning):
    """A computed map that is valid but suspicious (e.g. collapsed onto a few vertices)."""


class MeshWarning(UserWarning):
    """A mesh property worth knowing about that does not stop the computation (e.g. holes)."""


class CostWarning(UserWarning):
    """A computation that will run but takes far longer or more memory than the usual settings."""


def _preview(indices, limit: int = 8) -> str:
    """Render the first few offending indices, e.g. ``[3, 17, 42, ...] (12 in all)``."""
    n = len(indices)
    text = ", ".join(str(int(i)) for i in list(indices)[:limit])
    return f"[{text}{', ...' if n > limit else ''}]" + (f" ({n} in all)" if n > limit else "")
