"""Scored pairs of a collection kept on disk as they finish (``torchfmap eval --out FILE``), so a
run stopped by Ctrl-C, a lost worker or a full disk resumes where it stopped.

The file is a checksummed ``.npz`` (:func:`torchfmap._util.files.save_arrays`: written to a temporary
file, verified, renamed), rewritten whole after each finished pair or chunk: it always holds
every pair finished before its last successful write, and never a half-written one. It records
the settings it was scored with (a JSON text); a run with other settings refuses to reuse or
overwrite it.
"""

from __future__ import annotations

import json
import os
import time
import warnings
from pathlib import Path

import numpy as np

from .._util.files import load_arrays, save_arrays
from ..errors import CorruptFileError, ParameterError
from .collection import PairResult
from .scores import MapReport

#: Seconds between two rewrites of the file while pairs come in (each rewrite writes every kept
#: pair: rewriting after each pair of a long run would cost quadratic time).
SAVE_INTERVAL = 5.0
#: Columns of the ``numbers`` array: the match time, the overlap IoU (NaN: none) and the report
#: (a file written before the report's last three fields has only the first seven columns).
_NUMBERS = ("seconds", "iou", "mean_error", "median_error", "auc", "coverage", "smoothness", "n_points",
            "n_total", "mean_error_se")  # fmt: skip


class SavedPairs:
    """The pairs scored so far under ``settings`` (a JSON-able dict), kept in ``path``.

    Opening reads the file when it exists (its pairs are then :attr:`results`); :meth:`add`
    appends finished pairs, :meth:`flush` rewrites the file atomically (also every
    :data:`SAVE_INTERVAL` seconds while pairs come). A failed write (full disk, no permission)
    warns once and the run goes on; the file keeps the pairs of its last write.

    Raises:
        ParameterError: a file of other settings, or a name without ``.npz``.
        CorruptFileError: a file that is not one of these (truncated, altered, foreign).
    """

    def __init__(self, path: str | os.PathLike, settings: dict) -> None:
        self.path = Path(path)
        if self.path.suffix != ".npz":
            raise ParameterError(
                f"--out {str(self.path)!r}: the scored pairs are kept in a .npz file. Fix: FILE.npz."
            )
        self.settings = json.dumps(settings, sort_keys=True, default=str)
        self.results: list[PairResult] = []
        self._warned, self._dirty, self._written = False, False, time.monotonic()
        if self.path.exists():
            self.results = self._read()

    def _read(self) -> list[PairResult]:
        arrays = load_arrays(self.path, what="scored-pairs file")
        try:
            stored = str(arrays["settings"])
            names, numbers = arrays["names"], arrays["numbers"]
            errors = [arrays[f"errors_{i}"] for i in range(len(names))]
        except KeyError as err:
            raise CorruptFileError(
                f"{self.path} is not a torchfmap scored-pairs file (no {err} array). Fix: another --out."
            ) from None
        if stored != self.settings:
            raise ParameterError(
                f"{self.path} holds pairs scored with other settings ({stored}; now {self.settings}). "
                "Fix: another --out file, or delete this one to score again."
            )
        results = []
        for (source, target), row, err in zip(names, numbers, errors, strict=True):
            values = dict(zip(_NUMBERS, row.tolist(), strict=False))
            counts = {k: int(values[k]) for k in ("n_points", "n_total") if k in values}
            report = MapReport(**{k: values[k] for k in _NUMBERS[2:] if k in values} | counts)
            iou = None if np.isnan(values["iou"]) else values["iou"]
            results.append(PairResult(str(source), str(target), report, err, values["seconds"], iou))
        return results

    @property
    def done(self) -> set[tuple[str, str]]:
        """``(source, target)`` of the pairs kept."""
        return {(r.source, r.target) for r in self.results}

    def add(self, results: list[PairResult]) -> None:
        """Keep ``results``; the file is rewritten when :data:`SAVE_INTERVAL` seconds have passed
        since its last write (:meth:`flush` writes now)."""
        self.results.extend(results)
        self._dirty = True
        if time.monotonic() - self._written >= SAVE_INTERVAL:
            self.flush()

    def flush(self) -> None:
        """Rewrite the file with every kept pair, atomically, if any came since the last write (a
        failed write warns once; the file then keeps the pairs of its last write)."""
        if not self._dirty:
            return
        arrays = {
            "settings": np.array(self.settings),
            "names": np.array([[r.source, r.target] for r in self.results], dtype=str).reshape(-1, 2),
            "numbers": np.array([self._numbers(r) for r in self.results], dtype=np.float64).reshape(
                -1, len(_NUMBERS)
            ),
            **{f"errors_{i}": np.asarray(r.errors, dtype=np.float64) for i, r in enumerate(self.results)},
        }  # fmt: skip
        try:
            save_arrays(self.path, arrays)
            self._dirty, self._written = False, time.monotonic()
        except OSError as err:
            if not self._warned:
                warnings.warn(
                    f"could not save the scored pairs to {self.path} ({err}); the run goes on and the "
                    "file keeps the pairs of its last write. Fix: free disk space (the next chunk "
                    "tries again).",
                    stacklevel=2,
                )
                self._warned = True

    @staticmethod
    def _numbers(r: PairResult) -> list[float]:
        iou = np.nan if r.iou is None else r.iou
        return [r.seconds, iou, *(getattr(r.report, k) for k in _NUMBERS[2:])]

    def in_order(self, pairs) -> list[PairResult]:
        """The kept results of ``pairs`` (``(source, target, ...)`` tuples), in their order."""
        by_name = {(r.source, r.target): r for r in self.results}
        return [by_name[(p[0], p[1])] for p in pairs if (p[0], p[1]) in by_name]
