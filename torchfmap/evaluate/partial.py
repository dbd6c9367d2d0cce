"""Evaluation of partial-to-full matching: the partial collections ``torchfmap eval --partial``
reads (:func:`discover_partial_pairs`) and the overlap score (:func:`overlap_iou`). Errors are
those of :mod:`torchfmap.evaluate.scores`: geodesic on the whole, over the part's vertices with
ground truth (:func:`~torchfmap.evaluate.scores.geodesic_errors` of the pairs'
:class:`~torchfmap.evaluate.ground_truth.Correspondence`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..errors import ParameterError
from ..io import find_file, mesh_files, read_arrays, read_index_table, shape_name
from .scores import Correspondence

__all__ = ["PARTIAL_LAYOUT", "discover_partial_pairs", "overlap_iou", "part_radius"]


#: The true region of a part on its whole (:func:`part_radius`): within this many of the part's
#: mean edge lengths of a ground-truth image.
REGION_RADIUS = 0.75
#: Sub-folders of a partial collection (:func:`discover_partial_pairs`): the whole shapes, the
#: parts, and the parts' maps to their wholes.
PARTIAL_LAYOUT = ("full", "partial", "corres")


def discover_partial_pairs(folder: str | os.PathLike, map_base: int = 0):
    """Pairs of a partial collection: yields ``(whole, part, path_whole, path_part, gt)``.

    Layout: ``FOLDER/full/`` the whole shapes, ``FOLDER/partial/`` the parts, each named after its
    whole (``<whole>_<anything>``; any name when there is one whole), ``FOLDER/corres/<part>.map``
    one line per part vertex: its vertex on the whole (``map_base`` 0 or 1; ``-1``, or 0 when
    1-based, marks a vertex without ground truth). ``tools/cut_shapes.py`` writes this layout.

    Raises:
        ParameterError: a missing sub-folder or map, a part naming no whole, a map whose length
            is not the part's vertex count or whose indices leave the whole.
    """
    folder = Path(folder)
    missing = [d for d in PARTIAL_LAYOUT if not (folder / d).is_dir()]
    if missing:
        raise ParameterError(
            f"{folder} is not a partial collection: no {', '.join(missing)}/. Fix: the layout full/ (whole "
            "shapes), partial/ (parts), corres/<part>.map (python3 tools/cut_shapes.py makes one)."
        )
    if map_base not in (0, 1):
        raise ParameterError(f"map_base is 0 or 1, got {map_base!r}.")
    wholes = {shape_name(p): p for p in mesh_files(folder / "full")}
    for path in mesh_files(folder / "partial"):
        part = shape_name(path)
        owners = [w for w in wholes if part.startswith(w + "_") or part.startswith(w + "-")]
        if not owners and len(wholes) != 1:
            raise ParameterError(f"part {part} names no whole in {folder / 'full'}. Fix: name it <whole>_...")
        whole = max(owners, key=len) if owners else next(iter(wholes))
        map_file = find_file(folder / "corres", f"{part}.map")
        if map_file is None:
            raise ParameterError(f"no ground truth {folder / 'corres' / (part + '.map')}. Fix: add it.")
        gt_map = read_index_table(map_file, 1, "partial map")[:, 0] - map_base
        n_part, n_whole = len(read_arrays(path)[0]), len(read_arrays(wholes[whole])[0])
        if len(gt_map) != n_part or gt_map.max() >= n_whole or gt_map.min() < -1:
            raise ParameterError(
                f"{map_file.name} has {len(gt_map)} lines for {n_part} part vertices, indices "
                f"{gt_map.min()}..{gt_map.max()} ({map_base}-based) for {n_whole} whole vertices. Fix: one "
                "line per part vertex, its whole vertex (-1: unknown), or the right --map-base."
            )
        known = np.flatnonzero(gt_map >= 0)
        yield whole, part, wholes[whole], path, Correspondence(gt_map[known], known)


def overlap_iou(overlap: np.ndarray, true_vertices, mass, *, points=None, radius: float = 0.0) -> float:
    """Area-weighted intersection over union of the estimated part ``overlap > 0.5`` (``(V_x,)``,
    :attr:`~torchfmap.MatchResult.overlap`) and the true part on the whole; ``mass`` the whole's
    lumped mass, a ``(V_x, V_x)`` diagonal matrix or its ``(V_x,)`` diagonal (any scale).

    The true part is a region, not a vertex sample: every vertex of the whole within ``radius``
    of one of ``true_vertices`` (the ground-truth images of the part's vertices), ``points``
    ``(V_x, 3)`` the whole's vertices. A part meshed more coarsely than its whole has images a
    few of the whole's edges apart; with ``radius`` about the part's edge length (as
    :func:`part_radius` gives) the region between them counts too. ``radius=0``: the images
    alone (a part cut from the whole's own vertices).

    Raises:
        ParameterError: ``radius > 0`` without ``points``.
    """
    area = np.asarray(mass.diagonal() if np.ndim(mass) == 2 else mass, dtype=np.float64)
    est = np.asarray(overlap) > 0.5
    true = np.zeros(len(area), dtype=bool)
    images = np.unique(np.asarray(true_vertices, dtype=np.int64))
    true[images] = True
    if radius > 0:
        if points is None:
            raise ParameterError("overlap_iou with a radius needs the whole's points (V_x, 3).")
        points = np.asarray(points, dtype=np.float64)
        near = cKDTree(points[images]).query(points, k=1, distance_upper_bound=radius)[0]
        true |= np.isfinite(near)
    union = area[est | true].sum()
    return float(area[est & true].sum() / union) if union > 0 else 1.0


def part_radius(part_vertices: np.ndarray, part_faces: np.ndarray) -> float:
    """The radius of the true region of :func:`overlap_iou` for a part: :data:`REGION_RADIUS`
    times its mean edge length, in the part's units (the whole's, as partial matching
    requires). An equilateral triangle's points lie within ``1 / sqrt(3)`` of its edge of one of
    its corners; the margin covers triangles of uneven shape."""
    v, f = np.asarray(part_vertices, dtype=np.float64), np.asarray(part_faces, dtype=np.int64)
    edges = np.linalg.norm(v[f] - v[np.roll(f, 1, axis=1)], axis=2).ravel()
    return float(REGION_RADIUS * edges.mean()) if len(edges) else 0.0
