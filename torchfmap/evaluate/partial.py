"""Evaluation of partial-to-full matching: partial collections (:func:`discover_partial_pairs`) and the
overlap score (:func:`overlap_iou`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..errors import ParameterError
from ..io import find_file, mesh_files, read_arrays, read_index_table, shape_name
from .scores import Correspondence

__all__ = ["PARTIAL_LAYOUT", "PARTIAL_LAYOUTS", "discover_partial_pairs", "overlap_iou", "part_radius"]


#: The true region of a part on its whole: within this many of the part's mean edge lengths of an image.
REGION_RADIUS = 0.75
#: The partial collections :func:`discover_partial_pairs` reads, by name: how each is laid out.
PARTIAL_LAYOUTS = {
    "torchfmap": "full/ (wholes), partial/ (parts named <whole>_...), corres/<part>.map",
    "shapes+maps": "shapes/ (wholes and parts), maps/<part>_<whole>.map",
    "SHREC'16": "null/<whole>.off, cuts/ or holes/<cuts|holes>_<whole>_shape_<i>.off with a .baryc_gt beside "
    "each (or those folders' off/ and corres/<part>.vts)",
}
#: Sub-folders of the ``torchfmap`` layout: wholes, parts, their maps to the wholes.
PARTIAL_LAYOUT = ("full", "partial", "corres")
#: The part folders of the SHREC'16 layout.
SHREC16_PARTS = ("cuts", "holes")


def discover_partial_pairs(folder: str | os.PathLike, map_base: int = 0):
    """Yields ``(whole, part, path_whole, path_part, gt)`` of a collection in one of :data:`PARTIAL_LAYOUTS`,
    ``gt`` a :class:`~torchfmap.evaluate.ground_truth.Correspondence` (whole, part vertices); a ``.map`` has
    per part vertex its ``map_base``-based whole vertex (``-1``, or 0 if 1-based: none).

    Raises:
        ParameterError: a folder in no layout, a missing map or ground truth, a part naming no whole, or a map
            that does not fit the meshes."""
    folder = Path(folder)
    if map_base not in (0, 1):
        raise ParameterError(f"map_base is 0 or 1, got {map_base!r}.")
    if all((folder / d).is_dir() for d in PARTIAL_LAYOUT):
        yield from _torchfmap_layout(folder, map_base)
    elif (folder / "shapes").is_dir() and (folder / "maps").is_dir():
        yield from _shapes_maps_layout(folder, map_base)
    elif (folder / "null").is_dir() and any((folder / d).is_dir() for d in SHREC16_PARTS):
        yield from _shrec16_layout(folder)
    else:
        layouts = "; ".join(f"{name}: {how}" for name, how in PARTIAL_LAYOUTS.items())
        raise ParameterError(
            f"{folder} is not a partial collection in a layout torchfmap reads. Fix: lay it out as one of "
            f"them ({layouts})."
        )


def _part_map(map_file: Path, map_base: int, part_path: Path, whole_path: Path) -> Correspondence:
    """A ``.map`` file's ground truth, checked against both meshes' vertex counts."""
    gt_map = read_index_table(map_file, 1, "partial map")[:, 0] - map_base
    n_part, n_whole = len(read_arrays(part_path)[0]), len(read_arrays(whole_path)[0])
    if len(gt_map) != n_part or gt_map.max() >= n_whole or gt_map.min() < -1:
        raise ParameterError(
            f"{map_file.name} has {len(gt_map)} lines for {n_part} part vertices, indices "
            f"{gt_map.min()}..{gt_map.max()} ({map_base}-based) for {n_whole} whole vertices. Fix: one "
            "line per part vertex, its whole vertex (-1: unknown), or the right --map-base."
        )
    known = np.flatnonzero(gt_map >= 0)
    return Correspondence(gt_map[known], known)


def _torchfmap_layout(folder: Path, map_base: int):
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
        yield whole, part, wholes[whole], path, _part_map(map_file, map_base, path, wholes[whole])


def _shapes_maps_layout(folder: Path, map_base: int):
    shapes = {shape_name(p): p for p in mesh_files(folder / "shapes")}
    maps = sorted(p for p in (folder / "maps").iterdir() if p.name.endswith((".map", ".map.gz")))
    if not maps:
        raise ParameterError(f"no maps/<part>_<whole>.map in {folder}. Fix: add the parts' maps.")
    for map_file in maps:
        stem = map_file.name.removesuffix(".gz").removesuffix(".map")
        splits = [(stem[:i], stem[i + 1 :]) for i, c in enumerate(stem) if c == "_"]
        named = [(part, whole) for part, whole in splits if part in shapes and whole in shapes]
        if len(named) != 1:
            raise ParameterError(
                f"{map_file.name} names {'no' if not named else 'more than one'} <part>_<whole> pair of "
                f"shapes in {folder / 'shapes'}. Fix: name it <part>_<whole>.map after two shapes there."
            )
        part, whole = named[0]
        gt = _part_map(map_file, map_base, shapes[part], shapes[whole])
        yield whole, part, shapes[whole], shapes[part], gt


def _shrec16_layout(folder: Path):
    converted = (folder / "null" / "off").is_dir()
    null = folder / "null" / ("off" if converted else "")
    wholes = {shape_name(p): p for p in mesh_files(null)}
    for kind in SHREC16_PARTS:
        parts = folder / kind / ("off" if converted else "")
        if not parts.is_dir():
            continue
        for path in mesh_files(parts):
            part = shape_name(path)
            whole = next(
                (w for w in sorted(wholes, key=len, reverse=True) if part.startswith(f"{kind}_{w}_")), None
            )
            if whole is None:
                raise ParameterError(
                    f"part {part} names no whole in {null}. Fix: name it {kind}_<whole>_shape_<i>."
                )
            truth = (
                folder / kind / "corres" / f"{part}.vts" if converted else path.with_name(f"{part}.baryc_gt")
            )
            if not truth.is_file():
                raise ParameterError(f"no ground truth {truth}. Fix: add it.")
            whole_v, whole_f = read_arrays(wholes[whole])
            n_part = len(read_arrays(path)[0])
            if converted:
                idx = read_index_table(truth, 1, "SHREC'16 ground truth")[:, 0] - 1
                rows = np.arange(len(idx))
            else:
                idx, rows = _barycentric_vertices(truth, whole_f)
            if len(idx) and (rows.max() >= n_part or idx.min() < 0 or idx.max() >= len(whole_v)):
                raise ParameterError(
                    f"{truth.name}: rows or indices beyond {part} ({n_part} vertices) or {whole} "
                    f"({len(whole_v)} vertices). Fix: the ground truth of this part and whole."
                )
            yield whole, part, wholes[whole], path, Correspondence(idx, rows)


def _barycentric_vertices(path: Path, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A ``.baryc_gt`` file as ``(whole vertices, part rows)``: each row's heaviest corner."""
    try:
        table = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as err:
        raise ParameterError(
            f"{path.name} is not a table of numbers ({err}). Fix: the .baryc_gt file."
        ) from err
    if table.shape[1] != 4:
        raise ParameterError(
            f"{path.name} has {table.shape[1]} columns. Fix: a .baryc_gt file (triangle, three weights)."
        )
    tri = table[:, 0].astype(np.int64) - 1
    rows = np.flatnonzero((tri >= 0) & (tri < len(faces)))
    corner = np.argmax(table[rows, 1:], axis=1)
    return faces[tri[rows], corner].astype(np.int64), rows


def overlap_iou(overlap: np.ndarray, true_vertices, mass, *, points=None, radius: float = 0.0) -> float:
    """Area-weighted IoU of the estimated part ``overlap > 0.5`` ``(V_x,)`` and the true part: the whole's
    vertices (``points`` ``(V_x, 3)``) within ``radius`` (e.g. :func:`part_radius`; 0: the images alone) of
    ``true_vertices``. ``mass``: the whole's lumped mass, ``(V_x, V_x)`` or ``(V_x,)``.

    Raises:
        ParameterError: ``radius > 0`` without ``points``."""
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
    """The radius of :func:`overlap_iou`'s region: :data:`REGION_RADIUS` times the mean edge length."""
    v, f = np.asarray(part_vertices, dtype=np.float64), np.asarray(part_faces, dtype=np.int64)
    edges = np.linalg.norm(v[f] - v[np.roll(f, 1, axis=1)], axis=2).ravel()
    return float(REGION_RADIUS * edges.mean()) if len(edges) else 0.0
