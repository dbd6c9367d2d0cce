"""Triangle meshes: the :class:`Mesh` type and its validation.

A :class:`Mesh` holds ``vertices`` ``(V, 3)`` float64 and ``faces`` ``(F, 3)`` int64 and
never reorders either: vertex ``i`` of the file is vertex ``i`` here, because ground-truth
correspondences are lists of vertex indices. Derived quantities (areas, normals, edges,
boundary, components) are computed lazily and cached.

Validation (:func:`validate_mesh`) raises :class:`~torchfmap.errors.MeshError` for inputs
that would give silently wrong operators, with a message naming the problem and the fix,
and reports (without failing) properties such as holes. :class:`Mesh` also orients every
component consistently (:func:`orient_faces`), warns when it had to, and records it in
``mesh.report.n_flipped_faces``: the orientation term of the functional-map solver reads the
normals, and a shape with flipped faces would otherwise be matched as its mirror image.
"""

from __future__ import annotations

import dataclasses
import logging
import warnings
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp
import trimesh
from scipy.sparse.csgraph import breadth_first_order, connected_components

from .errors import MeshError, MeshWarning, _preview

log = logging.getLogger(__name__)

#: Faces whose area is below ``DEGENERATE_RTOL * mean_edge_length**2`` count as degenerate.
DEGENERATE_RTOL = 1e-12
#: Components with at most this fraction of boundary edges count as closed for orientation.
CLOSED_BOUNDARY_FRACTION = 0.02


@dataclass(frozen=True)
class MeshReport:
    """What validation found. Fields are counts / index arrays; see :func:`validate_mesh`."""

    n_vertices: int
    n_faces: int
    n_components: int
    n_boundary_edges: int
    n_boundary_loops: int
    unreferenced: np.ndarray = field(repr=False)
    euler_characteristic: int = 0
    #: faces whose corner order :class:`Mesh` reversed to orient every component consistently
    #: (and closed components outward); 0 when the file was already consistent.
    n_flipped_faces: int = 0

    @property
    def is_closed(self) -> bool:
        return self.n_boundary_edges == 0

    def summary(self) -> str:
        holes = "closed" if self.is_closed else f"{self.n_boundary_loops} boundary loop(s)"
        flipped = f", {self.n_flipped_faces} faces re-oriented" if self.n_flipped_faces else ""
        return (
            f"{self.n_vertices} vertices, {self.n_faces} faces, {self.n_components} component(s), "
            f"{holes}, Euler characteristic {self.euler_characteristic}{flipped}"
        )


def _as_arrays(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"vertices must have shape (V, 3), got {v.shape}. Fix: pass xyz coordinates.")
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshError(
            f"faces must have shape (F, 3), got {f.shape}. Fix: triangulate the mesh first "
            "(e.g. trimesh's `triangulate` or `load_mesh`, which triangulates polygons)."
        )
    if not np.issubdtype(v.dtype, np.number):
        raise MeshError(f"vertices must be numeric, got dtype {v.dtype}.")
    if f.size and not np.issubdtype(f.dtype, np.integer):
        if np.issubdtype(f.dtype, np.floating) and np.all(np.mod(f, 1) == 0):
            f = f.astype(np.int64)
        else:
            raise MeshError(f"faces must be integer vertex indices, got dtype {f.dtype}.")
    return v.astype(np.float64, copy=False), f.astype(np.int64, copy=False)


def _unit_coordinates(v: np.ndarray) -> np.ndarray:
    """``v`` divided by its largest absolute coordinate (unchanged if that is 0 or not finite),
    for scale-free tests that must not over- or underflow."""
    extent = float(np.abs(v).max())
    return v / extent if 0 < extent < np.inf else v


def _face_areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return 0.5 * np.linalg.norm(cross, axis=1)


def _edge_face_incidence(f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique undirected edges ``(E, 2)``, how many faces hold each, and face-edge ids ``(F, 3)``.

    Half-edge ``c`` of face ``f`` is the edge opposite corner ``c``: ``(f[(c+1)%3], f[(c+2)%3])``.
    """
    he = np.stack([f[:, [1, 2]], f[:, [2, 0]], f[:, [0, 1]]], axis=1).reshape(-1, 2)
    und = np.sort(he, axis=1)
    n = int(f.max()) + 1 if f.size else 1
    keys, inverse, counts = np.unique(und[:, 0] * n + und[:, 1], return_inverse=True, return_counts=True)
    edges = np.stack([keys // n, keys % n], axis=1)
    return edges, counts, inverse.reshape(-1, 3)


def _count_boundary_loops(boundary_edges: np.ndarray, n_vertices: int) -> int:
    if len(boundary_edges) == 0:
        return 0
    a = sp.coo_matrix(
        (np.ones(len(boundary_edges)), (boundary_edges[:, 0], boundary_edges[:, 1])),
        shape=(n_vertices, n_vertices),
    )
    n, labels = connected_components(a, directed=False)
    on_boundary = np.unique(boundary_edges)
    return len(np.unique(labels[on_boundary]))


def validate_mesh(
    vertices,
    faces,
    *,
    allow_components: bool = False,
    allow_unreferenced: bool = False,
    allow_nonmanifold: bool = False,
) -> MeshReport:
    """Check a triangle mesh and return a :class:`MeshReport`.

    Raises :class:`MeshError` (message names the problem and the fix) for: an empty mesh,
    NaN/inf coordinates, face indices out of range, degenerate faces (a repeated index or
    zero area), unreferenced vertices, non-manifold edges (shared by more than two faces) and
    several connected components. The last three can be allowed by flag. Holes (boundary
    loops) are reported, never an error: many scanned and TOSCA meshes have them.

    Args:
        vertices: ``(V, 3)`` coordinates.
        faces: ``(F, 3)`` vertex indices.
    """
    v, f = _as_arrays(vertices, faces)
    if len(v) == 0 or len(f) == 0:
        raise MeshError(
            f"empty mesh ({len(v)} vertices, {len(f)} faces). Fix: check the file path and "
            "format; a point cloud needs `laplacian(points, kind='robust')` instead."
        )
    bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
    if len(bad):
        raise MeshError(
            f"{len(bad)} vertices have NaN or infinite coordinates: vertices {_preview(bad)}. "
            "Fix: repair or remove them (and the faces using them) before building operators."
        )
    bad = np.flatnonzero(((f < 0) | (f >= len(v))).any(axis=1))
    if len(bad):
        raise MeshError(
            f"{len(bad)} faces index vertices outside [0, {len(v)}): faces {_preview(bad)}. "
            "Fix: faces must be 0-based indices into the vertex array (subtract 1 if they come "
            "from a 1-based format)."
        )
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    # degeneracy is scale-free: judge it on coordinates scaled to unit size, so that a tiny or
    # huge mesh is not called degenerate because its areas under- or overflow
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        unit = _unit_coordinates(v)
        areas = _face_areas(unit, f)
        mean_edge = float(np.mean(np.linalg.norm(unit[f[:, 1]] - unit[f[:, 0]], axis=1))) or 1.0
    bad = np.flatnonzero(repeated | (areas <= DEGENERATE_RTOL * mean_edge**2))
    if len(bad):
        raise MeshError(
            f"{len(bad)} degenerate faces (zero area or a repeated vertex): faces {_preview(bad)}. "
            "Fix: remove them, e.g. `mesh.without_faces(idx)`, or collapse the short edges; "
            "cotangent weights of a zero-area face are infinite."
        )
    unref = np.setdiff1d(np.arange(len(v)), np.unique(f))
    if len(unref) and not allow_unreferenced:
        raise MeshError(
            f"{len(unref)} vertices are not used by any face: vertices {_preview(unref)}. "
            "Fix: remove them (this changes vertex indices: remap your correspondences), or pass "
            "allow_unreferenced=True to load the mesh as it is and work on `mesh.referenced()` "
            "(operators refuse vertices that no face uses)."
        )
    edges, counts, _ = _edge_face_incidence(f)
    bad = np.flatnonzero(counts > 2)
    if len(bad) and not allow_nonmanifold:
        raise MeshError(
            f"{len(bad)} non-manifold edges are shared by more than two faces, e.g. edges "
            f"{[tuple(int(x) for x in e) for e in edges[bad[:4]]]}. Fix: repair the mesh, or use "
            "`laplacian(mesh, kind='robust')` (intrinsic tufted Laplacian) with "
            "allow_nonmanifold=True."
        )
    adj = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(v), len(v)))
    n_comp, labels = connected_components(adj, directed=False)
    n_comp_used = len(np.unique(labels[np.unique(f)]))
    if n_comp_used > 1 and not allow_components:
        sizes = np.bincount(labels)
        raise MeshError(
            f"the mesh has {n_comp_used} connected components (sizes "
            f"{sorted(sizes[sizes > 1].tolist(), reverse=True)[:6]}). Fix: keep one with "
            "`mesh.largest_component()`, or pass allow_components=True and give every component "
            "a seed when building bases."
        )
    boundary = edges[counts == 1]
    report = MeshReport(
        n_vertices=len(v),
        n_faces=len(f),
        n_components=n_comp_used,
        n_boundary_edges=len(boundary),
        n_boundary_loops=_count_boundary_loops(boundary, len(v)),
        unreferenced=unref,
        euler_characteristic=int(len(v) - len(unref) - len(edges) + len(f)),
    )
    if not report.is_closed:
        log.info("mesh has %d hole(s) (%d boundary edges)", report.n_boundary_loops, len(boundary))
    return report


def orient_faces(vertices, faces) -> tuple[np.ndarray, int]:
    """Faces with a consistent orientation on every connected component: ``(faces (F, 3), n_flipped)``.

    Two faces sharing an edge are consistent when they traverse it in opposite directions.
    Each component is oriented like a breadth-first spanning tree of its faces (edges shared by
    exactly two faces), keeping the orientation that most of its input faces already had; a
    component that is closed or nearly so (at most :data:`CLOSED_BOUNDARY_FRACTION` of its edges
    on a boundary: small holes) and encloses volume (``|signed volume| > 1 %`` of ``area^1.5``)
    is then turned outward. Corner order changes,
    vertex order never does. Non-orientable components (a Möbius band) keep a valid
    orientation on the spanning tree and their remaining conflicts. ``n_flipped`` counts the
    faces whose corner order was reversed.
    """
    v, f = _as_arrays(vertices, faces)
    nf = len(f)
    he = np.stack([f[:, [1, 2]], f[:, [2, 0]], f[:, [0, 1]]], axis=1).reshape(-1, 2)
    owner = np.repeat(np.arange(nf), 3)
    n = len(v)
    key = np.minimum(he[:, 0], he[:, 1]) * n + np.maximum(he[:, 0], he[:, 1])
    order = np.argsort(key, kind="stable")
    k_sorted = key[order]
    first = np.flatnonzero(np.r_[True, k_sorted[1:] != k_sorted[:-1]])
    counts = np.diff(np.r_[first, len(k_sorted)])
    pairs = first[counts == 2]  # manifold interior edges: half-edges order[p], order[p + 1]
    h0, h1 = order[pairs], order[pairs + 1]
    same_dir = he[h0, 0] == he[h1, 0]  # both faces traverse the edge the same way: inconsistent
    flip = np.zeros(nf, dtype=bool)
    if same_dir.any():
        a, b = owner[h0], owner[h1]
        graph = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(nf, nf)).tocsr()
        graph = graph + graph.T
        relative = sp.coo_matrix((same_dir.astype(np.int8) + 1, (a, b)), shape=(nf, nf)).tocsr()
        relative = relative + relative.T  # 2: needs a flip relative to the neighbour, 1: does not
        n_comp, labels = connected_components(graph, directed=False)
        for c in range(n_comp):
            root = int(np.flatnonzero(labels == c)[0])
            bfs, pred = breadth_first_order(graph, root, directed=False, return_predecessors=True)
            kids = bfs[1:]
            needs = np.asarray(relative[kids, pred[kids]]).ravel() == 2
            for face, parent, x in zip(kids.tolist(), pred[kids].tolist(), needs.tolist(), strict=True):
                flip[face] = flip[parent] ^ x  # parents come before children in BFS order
            members = labels == c
            if flip[members].sum() * 2 > members.sum():  # keep the majority's orientation
                flip[members] = ~flip[members]
    out = f.copy()
    out[flip] = out[flip][:, ::-1]
    # closed (or nearly closed) components: outward normals (positive signed volume)
    adj = sp.coo_matrix((np.ones(3 * nf), (he[:, 0], he[:, 1])), shape=(n, n))
    _, vlabels = connected_components(adj, directed=False)
    flabels = vlabels[out[:, 0]]
    unit = _unit_coordinates(v)  # the sign test is scale-free: no overflow
    x0, x1, x2 = unit[out[:, 0]], unit[out[:, 1]], unit[out[:, 2]]
    centre = unit[np.unique(out)].mean(axis=0)
    vol = np.einsum("ij,ij->i", x0 - centre, np.cross(x1 - centre, x2 - centre)) / 6.0
    area = _face_areas(unit, out)
    comp_vol = np.bincount(flabels, weights=vol)
    comp_area = np.bincount(flabels, weights=area)
    # "closed enough": at most CLOSED_BOUNDARY_FRACTION of the component's edges on a boundary
    boundary_he = first[counts == 1]
    comp_boundary = np.bincount(flabels[owner[order[boundary_he]]], minlength=len(comp_vol))
    comp_edges = np.bincount(flabels, minlength=len(comp_vol)) * 1.5
    closed = comp_boundary <= CLOSED_BOUNDARY_FRACTION * comp_edges
    inward = closed & (comp_vol < -0.01 * comp_area**1.5)
    turn = inward[flabels]
    out[turn] = out[turn][:, ::-1]
    flipped = flip ^ turn
    return out, int(flipped.sum())


class Mesh:
    """A validated triangle mesh. Vertex order is never changed.

    Args:
        vertices: ``(V, 3)`` coordinates, stored as float64.
        faces: ``(F, 3)`` 0-based vertex indices, stored as int64.
        validate: run :func:`validate_mesh` (default). Keyword flags are passed on to it.

    Attributes (lazy): ``face_areas (F,)``, ``area``, ``face_normals (F, 3)``,
    ``vertex_normals (V, 3)``, ``edges (E, 2)``, ``boundary_edges``, ``boundary_vertices``,
    ``component_labels (V,)``, ``n_components``, ``report`` (a :class:`MeshReport`).
    """

    def __init__(
        self,
        vertices,
        faces,
        *,
        validate: bool = True,
        allow_components: bool = False,
        allow_unreferenced: bool = False,
        allow_nonmanifold: bool = False,
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
            report = validate_mesh(self.vertices, self.faces, **self._flags)
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

    # -- basic sizes -------------------------------------------------------------------------
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
            self._report = validate_mesh(
                self.vertices,
                self.faces,
                allow_components=True,
                allow_unreferenced=True,
                allow_nonmanifold=True,
            )
        return self._report

    # -- geometry ----------------------------------------------------------------------------
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
        e = self.edges
        adj = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(self.n_vertices, self.n_vertices))
        return connected_components(adj, directed=False)

    @property
    def component_labels(self) -> np.ndarray:
        """``(V,)`` connected-component id of every vertex (isolated vertices get their own)."""
        return self._components[1]

    @property
    def n_components(self) -> int:
        return self.report.n_components

    # -- transformations (vertex order is kept) -----------------------------------------------
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
        """The mesh without the vertices that no face uses, and the original indices of the
        kept vertices: ``(mesh, vertex_ids)`` with ``mesh.vertices == self.vertices[vertex_ids]``
        (relative order preserved). A map computed on the result maps back through
        ``vertex_ids``: vertex ``i`` there is vertex ``vertex_ids[i]`` here."""
        ids = np.flatnonzero(np.bincount(self.faces.ravel(), minlength=self.n_vertices))
        remap = np.full(self.n_vertices, -1, dtype=np.int64)
        remap[ids] = np.arange(len(ids))
        return Mesh(self.vertices[ids], remap[self.faces], validate=False, name=self.name), ids

    def largest_component(self) -> tuple[Mesh, np.ndarray]:
        """The largest connected component and the original indices of its vertices.

        Returns ``(mesh, vertex_ids)`` with ``mesh.vertices == self.vertices[vertex_ids]``;
        relative order of the kept vertices is preserved.
        """
        labels = self.component_labels
        biggest = np.argmax(np.bincount(labels))
        ids = np.flatnonzero(labels == biggest)
        remap = -np.ones(self.n_vertices, dtype=np.int64)
        remap[ids] = np.arange(len(ids))
        faces = remap[self.faces]
        faces = faces[(faces >= 0).all(axis=1)]
        return Mesh(self.vertices[ids], faces, name=self.name), ids

    def to_trimesh(self):
        """A ``trimesh.Trimesh`` view (``process=False``, same vertex order)."""
        return trimesh.Trimesh(self.vertices, self.faces, process=False)
