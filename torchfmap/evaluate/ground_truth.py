"""Ground truth of a pair as a :class:`Correspondence` ``(idx_x, idx_y)``, from the identity, a 0-based map or
two ``.vts`` files."""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import ParameterError
from ..io import find_file, read_vts
from ..mesh import Mesh


class Correspondence(NamedTuple):
    """Ground truth: ``idx_x[r]`` on the source matches ``idx_y[r]`` on the target; ``(P,)`` ints each."""

    idx_x: np.ndarray
    idx_y: np.ndarray


def gt_identity(n: int) -> Correspondence:
    """The identity correspondence on ``n`` vertices."""
    idx = np.arange(n, dtype=np.int64)
    return Correspondence(idx, idx.copy())


def gt_from_map(gt_yx: np.ndarray) -> Correspondence:
    """From a full 0-based map ``gt_yx`` (target vertex ``v`` -> its source vertex)."""
    gt_yx = np.asarray(gt_yx, dtype=np.int64)
    return Correspondence(gt_yx, np.arange(len(gt_yx), dtype=np.int64))


def gt_from_vts(vts_x: np.ndarray, vts_y: np.ndarray) -> Correspondence:
    """From two 0-based ``.vts`` index arrays whose rows correspond.

    Raises:
        ParameterError: paths instead of arrays (read them with :func:`~torchfmap.io.read_vts`), or row counts
            that differ."""
    if any(isinstance(v, (str, os.PathLike)) for v in (vts_x, vts_y)):
        raise ParameterError(
            "gt_from_vts takes the 0-based index arrays of two .vts files, not their paths. Fix: "
            "gt_from_vts(read_vts(path_x), read_vts(path_y)) (torchfmap.io.read_vts)."
        )
    if len(vts_x) != len(vts_y):
        raise ParameterError(f".vts files have {len(vts_x)} and {len(vts_y)} rows; rows must correspond.")
    return Correspondence(np.asarray(vts_x, dtype=np.int64), np.asarray(vts_y, dtype=np.int64))


def vts_ground_truth(corres: str | os.PathLike, name_x: str, name_y: str) -> Correspondence:
    """The ground truth of ``name_x`` and ``name_y`` from a ``corres/`` folder of ``<name>.vts`` (or
    ``.vts.gz``) files.

    Raises:
        ParameterError: a missing file, or as :func:`gt_from_vts`."""
    corres = Path(corres)
    found = {n: find_file(corres, f"{n}.vts") for n in (name_x, name_y)}
    absent = [str(corres / f"{n}.vts") for n, p in found.items() if p is None]
    if absent:
        raise ParameterError(f"no ground truth {absent}. Fix: add the .vts (or .vts.gz) files.")
    return gt_from_vts(read_vts(found[name_x]), read_vts(found[name_y]))


def as_correspondence(gt, n_x: int | None = None) -> Correspondence:
    """``gt`` checked, as int64 arrays; with ``n_x``, its source vertices checked against ``[0, n_x)``.

    Raises:
        ParameterError: anything but a :class:`Correspondence`, arrays of different lengths, or source
            vertices outside ``[0, n_x)``."""
    if not isinstance(gt, Correspondence):
        raise ParameterError(
            f"gt must be a Correspondence(idx_x, idx_y), got {type(gt).__name__}. Fix: build it with "
            "Correspondence(idx_x=..., idx_y=...), gt_from_vts, gt_from_map or gt_identity."
        )
    idx_x, idx_y = (np.asarray(a, dtype=np.int64) for a in gt)
    if len(idx_y) != len(idx_x):
        raise ParameterError("ground-truth index arrays differ in length.")
    if n_x is not None and idx_x.size and (idx_x.max() >= n_x or idx_x.min() < 0):
        raise ParameterError("ground truth refers to source vertices outside mesh_x.")
    return Correspondence(idx_x, idx_y)


def landmarks_from_gt(mesh_x: Mesh, gt: Correspondence, n: int) -> np.ndarray:
    """``(n, 2)`` landmark pairs ``(x vertex, y vertex)``: ground-truth rows spread by Euclidean farthest
    points on ``x``.

    Raises:
        ParameterError: ``n`` outside ``[1, P]``."""
    idx_x, idx_y = as_correspondence(gt)
    if not 1 <= n <= len(idx_x):
        raise ParameterError(
            f"the number of landmarks must be in [1, {len(idx_x)}] (the ground-truth rows), got {n}. "
            "Fix: ask for fewer landmarks (CLI: --gt-landmarks)."
        )
    pts = mesh_x.vertices[idx_x]
    chosen = [int(np.argmax(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))]
    dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    while len(chosen) < n:
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[nxt], axis=1))
    rows = np.asarray(chosen)
    return np.stack([idx_x[rows], idx_y[rows]], axis=1)
