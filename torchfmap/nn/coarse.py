"""Dense meshes on the learned path: the network runs on a :func:`simplify` of the mesh (samples, their
geodesic Voronoi cells, the dual triangulation); :meth:`Simplification.carry` interpolates back."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from ..errors import MeshWarning, ParameterError
from ..fmap.nearest import spread_samples
from ..mesh import Mesh

#: Vertices above which :class:`~torchfmap.nn.LearnedMatcher` (``coarse='auto'``) runs the network on a
#: :func:`simplify` of the mesh.
DENSE_NETWORK_VERTICES = 400_000
#: Vertices of the simplification the network runs on (:func:`simplify`).
COARSE_VERTICES = 20_000


@dataclass(frozen=True)
class Simplification:
    """A coarse ``mesh`` (``S`` vertices) of a dense one: ``vertices (S,)`` the dense vertex of each coarse
    one, ``cell (V,)`` the coarse vertex whose cell holds each dense vertex, and the ``corners (V, 3)`` and
    barycentric ``weights (V, 3)`` :meth:`carry` interpolates from."""

    mesh: Mesh
    vertices: np.ndarray
    cell: np.ndarray
    corners: np.ndarray
    weights: np.ndarray

    @property
    def n_dense(self) -> int:
        return len(self.cell)

    def carry(self, values):
        """``values (..., S, D)`` (array or tensor) -> ``(..., V, D)`` on the dense vertices, same type.
        Raises :class:`ParameterError`: ``values`` does not have one row per coarse vertex."""
        if values.ndim < 2 or values.shape[-2] != self.mesh.n_vertices:
            raise ParameterError(
                f"carry takes (..., S, D) values on the {self.mesh.n_vertices} coarse vertices, got "
                f"shape {tuple(values.shape)}. Fix: the network's features of this simplification."
            )
        if isinstance(values, torch.Tensor):
            corners = torch.as_tensor(self.corners, device=values.device)
            weights = torch.as_tensor(self.weights, dtype=values.dtype, device=values.device)
            out = values[..., corners[:, 0], :] * weights[:, 0:1]
            for j in (1, 2):
                out = out + values[..., corners[:, j], :] * weights[:, j : j + 1]
            return out
        values = np.asarray(values)
        weights = self.weights.astype(values.dtype, copy=False)
        return sum(values[..., self.corners[:, j], :] * weights[:, j : j + 1] for j in range(3))


def _voronoi_cells(mesh: Mesh, samples: np.ndarray) -> np.ndarray:
    """``(V,)`` index of the sample geodesically nearest each vertex (else nearest in space)."""
    e = mesh.edges
    length = np.linalg.norm(mesh.vertices[e[:, 0]] - mesh.vertices[e[:, 1]], axis=1)
    length = np.maximum(length, 1e-300)  # a zero weight would be read as no edge
    n = mesh.n_vertices
    graph = sp.coo_matrix((length, (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    _, _, sources = dijkstra(graph, directed=False, indices=samples, min_only=True, return_predecessors=True)
    lookup = np.full(n, -1, dtype=np.int64)
    lookup[samples] = np.arange(len(samples))
    cell = np.where(sources >= 0, lookup[np.maximum(sources, 0)], -1)
    lost = np.flatnonzero(cell < 0)
    if len(lost):
        cell[lost] = cKDTree(mesh.vertices[samples]).query(mesh.vertices[lost])[1]
    return cell


def _dual_faces(faces: np.ndarray, cell: np.ndarray) -> np.ndarray:
    """The coarse faces: the cells of each dense face's corners where all three differ, one face per set."""
    labels = cell[faces]
    a, b, c = labels.T
    labels = labels[(a != b) & (b != c) & (a != c)]
    _, first = np.unique(np.sort(labels, axis=1), axis=0, return_index=True)
    return labels[np.sort(first)]


def _barycentric(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """``(weights (N, 3), squared distance (N,))`` of points to triangles ``(a, b, c)``, clipped to them."""
    e0, e1, d = b - a, c - a, points - a
    pairs = ((e0, e0), (e0, e1), (e1, e1), (d, e0), (d, e1))
    d00, d01, d11, d20, d21 = (np.einsum("ij,ij->i", p, q) for p, q in pairs)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 1e-300, den, 1.0)
    v, w = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    bary = np.maximum(np.stack([1.0 - v - w, v, w], axis=1), 0.0)
    total = bary.sum(axis=1, keepdims=True)
    bary = np.where(total > 0, bary / np.where(total > 0, total, 1.0), 1.0 / 3.0)
    foot = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return bary, np.einsum("ij,ij->i", points - foot, points - foot)


def _interpolation(points: np.ndarray, coarse: Mesh, cell: np.ndarray):
    """``(corners (V, 3), weights (V, 3))``: per point, the nearest coarse face around its cell's vertex."""
    faces, n_c = coarse.faces, coarse.n_vertices
    inc_v, inc_f = faces.ravel(), np.repeat(np.arange(len(faces)), 3)
    order = np.argsort(inc_v, kind="stable")
    start = np.searchsorted(inc_v[order], np.arange(n_c + 1))
    degree = np.diff(start)[cell]
    point = np.repeat(np.arange(len(points)), degree)  # one row per (point, candidate face)
    first = np.cumsum(degree) - degree
    offset = np.arange(len(point)) - np.repeat(first, degree) + np.repeat(start[cell], degree)
    face = inc_f[order[offset]]
    tri = coarse.vertices[faces[face]]
    bary, dist = _barycentric(points[point], tri[:, 0], tri[:, 1], tri[:, 2])
    best = np.lexsort((dist, point))  # per point, nearest face first
    keep = best[np.r_[True, point[best][1:] != point[best][:-1]]] if len(best) else best
    corners, weights = np.repeat(cell[:, None], 3, axis=1), np.tile([1.0, 0.0, 0.0], (len(points), 1))
    corners[point[keep]] = faces[face[keep]]
    weights[point[keep]] = bary[keep]
    return corners, weights


def simplify(mesh: Mesh, n_vertices: int = COARSE_VERTICES) -> Simplification:
    """A deterministic :class:`Simplification` of ``mesh`` with about ``n_vertices`` vertices. Raises
    :class:`ParameterError`: ``n_vertices < 4``, not fewer than the mesh's vertices, or too few cells meet."""
    if not isinstance(mesh, Mesh):
        raise ParameterError(f"simplify takes a Mesh, got {type(mesh).__name__}.")
    n_vertices = int(n_vertices)
    if not 4 <= n_vertices < mesh.n_vertices:
        raise ParameterError(
            f"a simplification of {n_vertices} vertices of a mesh of {mesh.n_vertices}: it needs "
            f"4 <= n_vertices < {mesh.n_vertices}. Fix: run the network on the mesh itself (coarse=None)."
        )
    mass = np.zeros(mesh.n_vertices)
    np.add.at(mass, mesh.faces.ravel(), np.repeat(mesh.face_areas / 3.0, 3))
    samples = spread_samples(mesh.vertices, mass, n_vertices)
    cell = _voronoi_cells(mesh, samples)
    faces = _dual_faces(mesh.faces, cell)
    used = np.zeros(len(samples), dtype=bool)
    used[faces.ravel()] = True
    renumber = np.cumsum(used) - 1
    samples, faces = samples[used], renumber[faces]
    if len(samples) < 4:
        raise ParameterError(
            f"the simplification of {mesh.name or 'the mesh'} has {len(samples)} vertices in faces: "
            f"too few cells meet. Fix: a larger n_vertices, or coarse=None."
        )
    with warnings.catch_warnings():  # a dual's few flipped faces or non-manifold edges: handled here
        warnings.simplefilter("ignore", MeshWarning)
        coarse = Mesh(
            mesh.vertices[samples], faces, name=f"{mesh.name or 'mesh'} simplified", allow_components=True,
            allow_nonmanifold=True,
        )  # fmt: skip
    orphan = ~used[cell]  # cells whose vertex is in no face: the nearest used vertex's
    cell = np.where(orphan, -1, renumber[cell])
    if orphan.any():
        cell[orphan] = cKDTree(coarse.vertices).query(mesh.vertices[orphan])[1]
    corners, weights = _interpolation(mesh.vertices, coarse, cell)
    return Simplification(coarse, samples, cell, corners, weights)


def check_coarse(coarse) -> str | int | None:
    """``coarse`` if it is ``'auto'``, None or an int >= 4, else :class:`ParameterError`."""
    if coarse is None or (isinstance(coarse, str) and coarse == "auto"):
        return coarse
    if isinstance(coarse, (int, np.integer)) and not isinstance(coarse, bool) and coarse >= 4:
        return int(coarse)
    raise ParameterError(
        f"coarse must be 'auto', None (the network on every mesh itself) or the vertex count of "
        f"the simplification (an int >= 4), got {coarse!r}. Fix: e.g. coarse='auto'."
    )


def coarse_size(coarse, n_vertices: int) -> int | None:
    """The simplification's vertex count for a mesh of ``n_vertices`` (None: the mesh itself): ``'auto'``,
    :data:`COARSE_VERTICES` above :data:`DENSE_NETWORK_VERTICES`; ``n``, ``n`` above ``n``."""
    coarse = check_coarse(coarse)
    if coarse == "auto":
        return COARSE_VERTICES if n_vertices > DENSE_NETWORK_VERTICES else None
    return coarse if coarse is not None and n_vertices > coarse else None
