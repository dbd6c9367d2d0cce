"""The learned path on dense meshes: the network runs on a simplification of each mesh and its
features are carried to every vertex.

A feature network on a dense mesh needs ``k_net`` eigenpairs, WKS inputs, a gradient operator
and the activations of every layer at every vertex, while the functional map keeps only the
first ``k`` eigenfunctions of its features. Past :data:`DENSE_NETWORK_VERTICES`,
:func:`simplify` builds a :class:`Simplification` of :data:`COARSE_VERTICES` vertices for it
(no new dependency):

1. evenly spread samples (voxel thinning, then farthest points in space, chosen by position so
   that a vertex-permuted copy gets the same ones), the coarse vertices, each a vertex of the
   dense mesh (its position kept);
2. the geodesic Voronoi cells of the samples along the mesh's edges (one multi-source Dijkstra,
   ``O(E log V)``), so parts that touch in space (a hand on a hip) stay apart;
3. the dual triangulation: one coarse face per dense face whose corners lie in three different
   cells, with the dense face's orientation (duplicates dropped), as Voronoi remeshings (ACVD,
   the LRVD remeshing of FAUST_r) build theirs.

:meth:`Simplification.carry` brings per-vertex values of the coarse mesh to every dense vertex:
barycentric interpolation on the coarse face nearest the vertex among the faces around its own
cell's vertex (so carried features are continuous and never come from another part of the body).
"""

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

#: Vertices above which :class:`~torchfmap.nn.LearnedMatcher` (``coarse='auto'``) runs the
#: network on a :func:`simplify` of the mesh instead of the mesh itself: the network's inputs,
#: eigenfunctions, gradient operator and activations grow with ``V``, the simplification keeps
#: their share fixed (``python -m bench learned --case dense`` measures both routes).
DENSE_NETWORK_VERTICES = 400_000
#: Vertices of the simplification the network runs on (:func:`simplify`): fine enough that thin
#: parts (fingers, tails) keep their topology in the Voronoi dual, so the network sees a clean
#: surface, and a small fixed share of a dense mesh's cost.
COARSE_VERTICES = 20_000


@dataclass(frozen=True)
class Simplification:
    """A coarse mesh of a dense one and how to carry values back (:func:`simplify`).

    ``mesh``: the coarse :class:`~torchfmap.Mesh` (``S`` vertices); ``vertices (S,)``: the dense
    vertex each coarse vertex is (its position); ``cell (V,)``: the coarse vertex whose geodesic
    Voronoi cell holds each dense vertex; ``corners (V, 3)`` and ``weights (V, 3)``: the coarse
    vertices and barycentric weights (non-negative, summing to 1) that :meth:`carry` interpolates
    each dense vertex from.
    """

    mesh: Mesh
    vertices: np.ndarray
    cell: np.ndarray
    corners: np.ndarray
    weights: np.ndarray

    @property
    def n_dense(self) -> int:
        return len(self.cell)

    def carry(self, values):
        """``values (..., S, D)`` on the coarse vertices (a numpy array or a tensor, any leading
        dimensions) -> ``(..., V, D)`` on every dense vertex, in the input's type, dtype and
        device: ``sum_j weights[:, j] * values[..., corners[:, j], :]``.

        Raises:
            ParameterError: ``values`` does not have one row per coarse vertex.
        """
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
    """``(V,)`` the index into ``samples`` of the sample geodesically nearest each vertex along
    the mesh's edges (edge lengths); vertices of a component without a sample take the sample
    nearest in space."""
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
    """The coarse faces: ``cell`` of the corners of every dense face whose three corners lie in
    three different cells, in the face's corner order; one per set of three cells."""
    labels = cell[faces]
    a, b, c = labels.T
    labels = labels[(a != b) & (b != c) & (a != c)]
    _, first = np.unique(np.sort(labels, axis=1), axis=0, return_index=True)
    return labels[np.sort(first)]


def _barycentric(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """``(weights (N, 3), squared distance (N,))`` of each point to the point of its triangle
    ``(a, b, c)`` given by its projection's barycentric coordinates clipped to the triangle
    (negative ones set to 0, the rest renormalised)."""
    e0, e1, d = b - a, c - a, points - a
    d00 = np.einsum("ij,ij->i", e0, e0)
    d01 = np.einsum("ij,ij->i", e0, e1)
    d11 = np.einsum("ij,ij->i", e1, e1)
    d20 = np.einsum("ij,ij->i", d, e0)
    d21 = np.einsum("ij,ij->i", d, e1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 1e-300, den, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    bary = np.maximum(np.stack([1.0 - v - w, v, w], axis=1), 0.0)
    total = bary.sum(axis=1, keepdims=True)
    bary = np.where(total > 0, bary / np.where(total > 0, total, 1.0), 1.0 / 3.0)
    foot = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return bary, np.einsum("ij,ij->i", points - foot, points - foot)


def _interpolation(points: np.ndarray, coarse: Mesh, cell: np.ndarray):
    """``(corners (V, 3), weights (V, 3))``: for every dense point, the coarse face nearest it
    among the faces around its cell's coarse vertex and the barycentric weights there (a cell
    whose vertex has no face: that vertex alone)."""
    faces = coarse.faces
    n_c = coarse.n_vertices
    inc_v = faces.ravel()
    inc_f = np.repeat(np.arange(len(faces)), 3)
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
    corners = np.repeat(cell[:, None], 3, axis=1)
    weights = np.tile([1.0, 0.0, 0.0], (len(points), 1))
    corners[point[keep]] = faces[face[keep]]
    weights[point[keep]] = bary[keep]
    return corners, weights


def simplify(mesh: Mesh, n_vertices: int = COARSE_VERTICES) -> Simplification:
    """A :class:`Simplification` of ``mesh`` with about ``n_vertices`` vertices (the module
    docstring): ``O(V log V)`` work, deterministic. Coarse vertices that no coarse face uses
    are dropped (their dense vertices are then carried from the nearest coarse face around).

    Raises:
        ParameterError: ``n_vertices < 4``, or not fewer than the mesh's vertices.
    """
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
    """``coarse`` if it is a setting of :class:`~torchfmap.nn.LearnedMatcher`'s ``coarse``:
    ``'auto'``, None, or an int >= 4.

    Raises:
        ParameterError: anything else.
    """
    if coarse is None or (isinstance(coarse, str) and coarse == "auto"):
        return coarse
    if isinstance(coarse, (int, np.integer)) and not isinstance(coarse, bool) and coarse >= 4:
        return int(coarse)
    raise ParameterError(
        f"coarse must be 'auto', None (the network on every mesh itself) or the vertex count of "
        f"the simplification (an int >= 4), got {coarse!r}. Fix: e.g. coarse='auto'."
    )


def coarse_size(coarse, n_vertices: int) -> int | None:
    """The vertex count of the simplification the network runs on for a mesh of ``n_vertices``
    (None: the mesh itself): ``'auto'``, :data:`COARSE_VERTICES` above
    :data:`DENSE_NETWORK_VERTICES`; an int ``n``, ``n`` for meshes of more than ``n`` vertices;
    None, never."""
    coarse = check_coarse(coarse)
    if coarse == "auto":
        return COARSE_VERTICES if n_vertices > DENSE_NETWORK_VERTICES else None
    return coarse if coarse is not None and n_vertices > coarse else None
