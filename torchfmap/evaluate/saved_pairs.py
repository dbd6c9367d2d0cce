"""Scored pairs kept on disk as they finish (``torchfmap eval --out FILE``) so a stopped run resumes: a
checksummed ``.npz`` rewritten atomically, with the settings it was scored with."""

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

#: Seconds between two rewrites of the file while pairs come in (each rewrite writes every pair).
SAVE_INTERVAL = 5.0
#: Columns of the ``numbers`` array: match time, overlap IoU (NaN: none), the report (older files: 7).
_NUMBERS = ("seconds", "iou", "mean_error", "median_error", "auc", "coverage", "smoothness", "n_points",
            "n_total", "mean_error_se")  # fmt: skip


class SavedPairs:
    """The pairs scored under ``settings`` (a JSON-able dict), kept in ``path`` (read into :attr:`results` if
    it exists). :meth:`add` appends, :meth:`flush` rewrites; a failed write warns once.

    Raises:
        ParameterError: a file of other settings, or a name without ``.npz``.
        CorruptFileError: a file that is not one of these."""

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
        """Keep ``results``; rewrite the file if :data:`SAVE_INTERVAL` seconds passed since the last write."""
        self.results.extend(results)
        self._dirty = True
        if time.monotonic() - self._written >= SAVE_INTERVAL:
            self.flush()

    def flush(self) -> None:
        """Rewrite the file atomically with every kept pair, if any came since the last write."""
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
