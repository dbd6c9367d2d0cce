"""Partial shapes (:class:`Cut`) cut from whole ones, vertex positions and order kept, with exact ground
truth: :func:`cut_plane`, :func:`cut_holes`, :func:`overlapping_cuts`; see :func:`torchfmap.remesh.remesh`."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .._util.checks import check_count
from ..errors import MeshError, ParameterError
from ..mesh import Mesh
from ..operators.geodesic import geodesic_distances

#: Bisection steps of the plane offset that reaches the asked area ratio.
CUT_STEPS = 60
#: Draws of :func:`overlapping_cuts` before it gives up.
OVERLAP_DRAWS = 50

__all__ = ["Cut", "cut_holes", "cut_plane", "overlapping_cuts"]


class Cut(NamedTuple):
    """A part ``mesh`` of a whole mesh and ``vertices`` ``(V_part,)``, the ground-truth map part -> whole."""

    mesh: Mesh
    vertices: np.ndarray

    @property
    def n_vertices(self) -> int:
        return self.mesh.n_vertices


def _check_ratio(area_ratio: float) -> float:
    if not (np.isfinite(area_ratio) and 0.05 <= area_ratio < 1.0):
        raise ParameterError(f"area_ratio must be in [0.05, 1), got {area_ratio!r}. Fix: e.g. 0.6.")
    return float(area_ratio)


def _kept_part(mesh: Mesh, drop_faces: np.ndarray) -> Cut:
    part, ids = mesh.without_faces(np.flatnonzero(drop_faces)).referenced()
    piece, kept = part.largest_component()
    return Cut(Mesh(piece.vertices, piece.faces, name=f"{mesh.name or 'shape'}-part"), ids[kept])


def cut_plane(mesh: Mesh, area_ratio: float, normal=None, *, seed: int = 0) -> Cut:
    """The largest piece of ``mesh`` on the negative side of a plane of ``normal`` ``(3,)`` (default
    random, from ``seed``; offset by :data:`CUT_STEPS` bisection steps) keeping about ``area_ratio`` of its
    area (less when the plane cuts a limb off). Raises :class:`ParameterError` for ``area_ratio`` outside
    ``[0.05, 1)`` or a zero ``normal``, :class:`MeshError` if the cut leaves no faces."""
    area_ratio = _check_ratio(area_ratio)
    if normal is None:
        normal = np.random.default_rng(seed).normal(size=3)
    normal = np.asarray(normal, dtype=np.float64).reshape(3)
    if not np.isfinite(normal).all() or np.linalg.norm(normal) == 0:
        raise ParameterError(f"normal must be a non-zero 3-vector, got {normal}.")
    heights = mesh.vertices[mesh.faces].mean(axis=1) @ (normal / np.linalg.norm(normal))
    areas = mesh.face_areas
    lo, hi = float(heights.min()), float(heights.max())
    for _ in range(CUT_STEPS):  # area below the plane grows with its offset
        mid = 0.5 * (lo + hi)
        if areas[heights < mid].sum() < area_ratio * areas.sum():
            lo = mid
        else:
            hi = mid
    drop = heights >= hi
    if drop.all():
        raise MeshError("the plane cut leaves no faces. Fix: a larger area_ratio.")
    return _kept_part(mesh, drop)


def cut_holes(mesh: Mesh, area_ratio: float, n_holes: int = 3, *, seed: int = 0) -> Cut:
    """The largest piece of ``mesh`` after ``n_holes`` (>= 1) geodesic balls about random centres (``seed``)
    remove about ``1 - area_ratio`` of its area (in [0.05, 1), else :class:`ParameterError`)."""
    area_ratio = _check_ratio(area_ratio)
    n_holes = check_count(n_holes, 1, mesh.n_vertices, "n_holes")
    centres = np.random.default_rng(seed).choice(mesh.n_vertices, n_holes, replace=False)
    dist = geodesic_distances(mesh, centres).min(axis=0)  # (V,): to the nearest centre
    face_dist = dist[mesh.faces].max(axis=1)
    order = np.argsort(face_dist)
    removed = np.cumsum(mesh.face_areas[order]) <= (1 - area_ratio) * mesh.area
    drop = np.zeros(mesh.n_faces, dtype=bool)
    drop[order[removed]] = True
    return _kept_part(mesh, drop)


def overlapping_cuts(
    mesh: Mesh, *, seed: int = 0, shares: tuple[float, float] = (0.3, 0.7), area_ratios=(0.45, 0.85)
) -> tuple[Cut, Cut]:
    """Two plane cuts of ``mesh`` (normals ``n`` and ``-n`` tilted, area ratios drawn in ``area_ratios``
    from ``seed``) whose overlap is within ``shares`` of each part's area, at most :data:`OVERLAP_DRAWS`
    draws (else, or for ``shares`` not ``0 <= lo < hi <= 1``, :class:`ParameterError`). Part-a vertex
    ``i`` and part-b vertex ``j`` correspond iff ``a.vertices[i] == b.vertices[j]``."""
    lo, hi = shares
    if not 0 <= lo < hi <= 1:
        raise ParameterError(f"shares must be 0 <= lo < hi <= 1, got {shares!r}.")
    rng = np.random.default_rng(seed)
    area = np.zeros(mesh.n_vertices)
    np.add.at(area, mesh.faces, np.repeat(mesh.face_areas[:, None] / 3, 3, axis=1))
    for _ in range(OVERLAP_DRAWS):
        normal = rng.normal(size=3)
        other = -normal / np.linalg.norm(normal) + 0.8 * rng.normal(size=3)
        ra, rb = rng.uniform(*area_ratios, size=2)
        a, b = cut_plane(mesh, ra, normal=normal), cut_plane(mesh, rb, normal=other)
        common = area[np.intersect1d(a.vertices, b.vertices)].sum()
        if all(lo <= common / area[c.vertices].sum() <= hi for c in (a, b)):
            return a, b
    raise ParameterError(
        f"no two plane cuts of {mesh.name or 'the mesh'} overlapping by {lo:g}-{hi:g} of each in "
        f"{OVERLAP_DRAWS} draws (seed {seed}). Fix: wider shares or area_ratios, or another seed."
    )
