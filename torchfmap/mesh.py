"""Triangle meshes: :class:`Mesh` (vertex order never changed); :func:`validate_mesh`,
:class:`MeshReport` and :func:`orient_faces` live in :mod:`torchfmap.mesh_checks` (importable from here)."""

from __future__ import annotations

import dataclasses
import warnings
from functools import cached_property

import numpy as np
import trimesh

from .errors import MeshError, MeshWarning, _preview
from .mesh_checks import (
    MeshReport,
    _as_arrays,
    _edge_components,
    _edge_face_incidence,
    _face_areas,
    duplicate_faces,
    orient_faces,
    validate_mesh,
    weld_vertices,
)

__all__ = ["Mesh", "MeshReport", "orient_faces", "validate_mesh", "weld_vertices"]


class Mesh:
    """A triangle mesh: ``vertices (V, 3)`` float64, ``faces (F, 3)`` 0-based int64; vertex order is never
    changed. ``validate``: run :func:`validate_mesh` with the ``allow_*`` flags (duplicated faces are
    dropped and faces oriented, with a :class:`~torchfmap.errors.MeshWarning`). Lazy attributes:
    ``face_areas (F,)``, ``area``, normals, ``edges (E, 2)``, boundary, components, ``report``."""

    def __init__(
        self,
        vertices,
        faces,
        *,
        validate: bool = True,
        allow_components: bool = False,
        allow_unreferenced: bool = False,
        allow_nonmanifold: bool | str = False,
        name: str | None = None,
    ) -> None:
        v, f = _as_arrays(vertices, faces)
        self.vertices: np.ndarray = np.ascontiguousarray(v)
        self.faces: np.ndarray = np.ascontiguousarray(f)
        self.name = name
        self._flags = dict(
            allow_components=allow_components,
            allow_unreferenced=allow_unreferenced,
            allow_nonmanifold=allow_nonmanifold,
        )
        self._report: MeshReport | None = None
        if validate:
            twins = duplicate_faces(self.faces) if len(self.vertices) and len(self.faces) else []
            if len(twins):  # counted twice by the cotangent weights and the mass otherwise
                self.faces = np.ascontiguousarray(np.delete(self.faces, twins, axis=0))
                warnings.warn(
                    f"{name or 'mesh'}: dropped {len(twins)} duplicated faces (the same three vertices "
                    f"as an earlier face): faces {_preview(twins)}; vertex order is unchanged. Fix: "
                    "remove them from the file to silence this.",
                    MeshWarning,
                    stacklevel=2,
                )
            report = validate_mesh(self.vertices, self.faces, **self._flags)
            if report.n_nonmanifold_edges and allow_nonmanifold == "warn":
                warnings.warn(
                    f"{name or 'mesh'}: {report.n_nonmanifold_edges} non-manifold edges (shared by more "
                    "than two faces); read as they are, and its operators are the intrinsic tufted "
                    "Laplacian (prepare_shape), which is right on them. Fix: repair the mesh to "
                    "silence this.",
                    MeshWarning,
                    stacklevel=2,
                )
            if report.n_coincident_vertices:
                warnings.warn(
                    f"{name or 'mesh'}: {report.n_coincident_vertices} vertices share their position "
                    "with another vertex: the surface is cut along seams there, and its operators see "
                    "a boundary where the shape has none. Fix: weld them, torchfmap.weld_vertices("
                    "vertices, faces) (vertex indices change: remap correspondences with the map it "
                    "returns).",
                    MeshWarning,
                    stacklevel=2,
                )
            faces, n_flipped = orient_faces(self.vertices, self.faces)
            if n_flipped:
                self.faces = np.ascontiguousarray(faces)
                report = dataclasses.replace(report, n_flipped_faces=n_flipped)
                warnings.warn(
                    f"{name or 'mesh'}: reversed the corner order of {n_flipped} of {len(faces)} faces so "
                    "that every component is consistently oriented (closed ones outward); vertex "
                    "order is unchanged. mesh.report.n_flipped_faces records it.",
                    MeshWarning,
                    stacklevel=2,
                )
            self._report = report

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def __len__(self) -> int:
        return self.n_vertices

    def __repr__(self) -> str:
        label = f"{self.name!r}, " if self.name else ""
        return f"Mesh({label}V={self.n_vertices}, F={self.n_faces})"

    @property
    def report(self) -> MeshReport:
        if self._report is None:
            flags = dict(allow_components=True, allow_unreferenced=True, allow_nonmanifold=True)
            self._report = validate_mesh(self.vertices, self.faces, **flags)
        return self._report

    @cached_property
    def face_areas(self) -> np.ndarray:
        """``(F,)`` triangle areas."""
        return _face_areas(self.vertices, self.faces)

    @property
    def area(self) -> float:
        """Total surface area ``|M|``."""
        return float(self.face_areas.sum())

    @cached_property
    def face_normals(self) -> np.ndarray:
        """``(F, 3)`` unit face normals (orientation from the face winding)."""
        v, f = self.vertices, self.faces
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)

    @cached_property
    def vertex_normals(self) -> np.ndarray:
        """``(V, 3)`` area-weighted unit vertex normals."""
        n = np.zeros_like(self.vertices)
        weighted = self.face_normals * self.face_areas[:, None]
        for c in range(3):
            np.add.at(n, self.faces[:, c], weighted)
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)

    @cached_property
    def _incidence(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return _edge_face_incidence(self.faces)

    @property
    def edges(self) -> np.ndarray:
        """``(E, 2)`` unique undirected edges, each sorted ``(i < j)``."""
        return self._incidence[0]

    @property
    def n_nonmanifold_edges(self) -> int:
        """Edges shared by more than two faces (0 on a manifold mesh)."""
        return int(np.count_nonzero(self._incidence[1] > 2))

    @property
    def edge_lengths(self) -> np.ndarray:
        """``(E,)`` lengths of :attr:`edges`."""
        e = self.edges
        return np.linalg.norm(self.vertices[e[:, 0]] - self.vertices[e[:, 1]], axis=1)

    @property
    def mean_edge_length(self) -> float:
        return float(self.edge_lengths.mean())

    @property
    def boundary_edges(self) -> np.ndarray:
        """``(Eb, 2)`` edges used by exactly one face."""
        edges, counts, _ = self._incidence
        return edges[counts == 1]

    @property
    def boundary_vertices(self) -> np.ndarray:
        """Sorted indices of vertices on a boundary (hole) edge."""
        return np.unique(self.boundary_edges)

    @cached_property
    def _components(self) -> tuple[int, np.ndarray]:
        return _edge_components(self.edges, self.n_vertices)

    @property
    def component_labels(self) -> np.ndarray:
        """``(V,)`` connected-component id of every vertex (isolated vertices get their own)."""
        return self._components[1]

    @property
    def n_components(self) -> int:
        return self.report.n_components

    def copy(self, vertices=None) -> Mesh:
        """A copy, optionally with new vertex positions of the same shape."""
        v = self.vertices.copy() if vertices is None else np.asarray(vertices, dtype=np.float64)
        if v.shape != self.vertices.shape:
            raise MeshError(f"new vertices must have shape {self.vertices.shape}, got {v.shape}.")
        out = Mesh(v, self.faces.copy(), validate=False, name=self.name)
        out._flags = dict(self._flags)
        return out

    def scaled(self, alpha: float) -> Mesh:
        """The mesh with coordinates multiplied by ``alpha`` (areas scale by ``alpha**2``)."""
        return self.copy(self.vertices * float(alpha))

    def normalized(self, center: bool = True) -> Mesh:
        """Scaled to unit total area (and centred at the area-weighted centroid)."""
        v = self.vertices
        if center:
            centroids = v[self.faces].mean(axis=1)
            v = v - (centroids * self.face_areas[:, None]).sum(axis=0) / self.area
        return self.copy(v / np.sqrt(self.area))

    def permuted(self, perm) -> Mesh:
        """Vertex ``i`` of the result is vertex ``perm[i]`` of this mesh (faces relabelled)."""
        perm = np.asarray(perm, dtype=np.int64)
        if np.sort(perm).tolist() != list(range(self.n_vertices)):
            raise MeshError("perm must be a permutation of range(V).")
        inv = np.empty_like(perm)
        inv[perm] = np.arange(len(perm))
        return Mesh(self.vertices[perm], inv[self.faces], validate=False, name=self.name)

    def without_faces(self, face_indices) -> Mesh:
        """The mesh with the given faces removed (vertices kept, so indices stay valid)."""
        keep = np.ones(self.n_faces, dtype=bool)
        keep[np.asarray(face_indices, dtype=np.int64)] = False
        return Mesh(self.vertices, self.faces[keep], validate=False, name=self.name)

    def referenced(self) -> tuple[Mesh, np.ndarray]:
        """``(mesh, vertex_ids)``: without unused vertices, ``mesh.vertices == self.vertices[vertex_ids]``."""
        ids = np.flatnonzero(np.bincount(self.faces.ravel(), minlength=self.n_vertices))
        remap = np.full(self.n_vertices, -1, dtype=np.int64)
        remap[ids] = np.arange(len(ids))
        return Mesh(self.vertices[ids], remap[self.faces], validate=False, name=self.name), ids

    def largest_component(self) -> tuple[Mesh, np.ndarray]:
        """``(mesh, vertex_ids)``: the largest component, ``mesh.vertices == self.vertices[vertex_ids]``."""
        labels = self.component_labels
        ids = np.flatnonzero(labels == np.argmax(np.bincount(labels)))
        remap = -np.ones(self.n_vertices, dtype=np.int64)
        remap[ids] = np.arange(len(ids))
        faces = remap[self.faces]
        faces = faces[(faces >= 0).all(axis=1)]
        return Mesh(self.vertices[ids], faces, name=self.name), ids

    def to_trimesh(self):
        """A ``trimesh.Trimesh`` view (``process=False``, same vertex order)."""
        return trimesh.Trimesh(self.vertices, self.faces, process=False)
