"""Mesh validation on plain ``(vertices, faces)`` arrays: :func:`validate_mesh` and its :class:`MeshReport`,
:func:`orient_faces` (both run by :class:`~torchfmap.mesh.Mesh`) and :func:`weld_vertices`."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components
from scipy.spatial import cKDTree

from .errors import MeshError, _preview

log = logging.getLogger(__name__)

#: Faces whose area is below ``DEGENERATE_RTOL * mean_edge_length**2`` count as degenerate.
DEGENERATE_RTOL = 1e-12
#: Vertices closer than ``COINCIDENT_RTOL`` times the bbox diagonal share a position (:func:`weld_vertices`).
COINCIDENT_RTOL = 1e-9
#: Components with at most this fraction of boundary edges count as closed for orientation.
CLOSED_BOUNDARY_FRACTION = 0.02


@dataclass(frozen=True)
class MeshReport:
    """What :func:`validate_mesh` found: counts, and the ``unreferenced`` vertex indices."""

    n_vertices: int
    n_faces: int
    n_components: int
    n_boundary_edges: int
    n_boundary_loops: int
    unreferenced: np.ndarray = field(repr=False)
    euler_characteristic: int = 0
    #: faces whose corner order :class:`Mesh` reversed (:func:`orient_faces`)
    n_flipped_faces: int = 0
    #: edges shared by more than two faces (``allow_nonmanifold``; :func:`~torchfmap.bases.prepare_shape`)
    n_nonmanifold_edges: int = 0
    #: boundary vertices at the position of another boundary vertex (a seam; :func:`weld_vertices`)
    n_coincident_vertices: int = 0

    @property
    def is_closed(self) -> bool:
        return self.n_boundary_edges == 0

    def summary(self) -> str:
        holes = "closed" if self.is_closed else f"{self.n_boundary_loops} boundary loop(s)"
        flipped = f", {self.n_flipped_faces} faces re-oriented" if self.n_flipped_faces else ""
        n_seam = self.n_coincident_vertices
        seams = f", {n_seam} coincident vertices (seams)" if n_seam else ""
        return (
            f"{self.n_vertices} vertices, {self.n_faces} faces, {self.n_components} component(s), "
            f"{holes}, Euler characteristic {self.euler_characteristic}{flipped}{seams}"
        )


def coincident_groups(vertices, rtol: float = COINCIDENT_RTOL) -> np.ndarray:
    """``(V,)`` the lowest-index vertex at each vertex's position: vertices closer than ``rtol`` times the
    bounding-box diagonal share one (``rtol=0``: bit-identical coordinates only)."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    first = np.arange(len(v))
    if len(v) < 2:
        return first
    if rtol == 0:
        _, index, inverse = np.unique(v, axis=0, return_index=True, return_inverse=True)
        return index[inverse.ravel()]
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0))) or 1.0
    pairs = cKDTree(v).query_pairs(rtol * diag, output_type="ndarray")
    if not len(pairs):
        return first
    labels = _edge_components(pairs, len(v))[1]
    lowest = np.full(labels.max() + 1, len(v))
    np.minimum.at(lowest, labels, first)
    return lowest[labels]


def weld_vertices(
    vertices, faces, rtol: float = COINCIDENT_RTOL
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge vertices that share a position (:func:`coincident_groups`), kept in order of first
    appearance: ``(vertices (V', 3), faces (F, 3), old_to_new (V,))``. Collapsed faces are kept."""
    v, f = _as_arrays(vertices, faces)
    first = coincident_groups(v, rtol)
    keep = np.flatnonzero(first == np.arange(len(v)))
    new_index = np.full(len(v), -1, dtype=np.int64)
    new_index[keep] = np.arange(len(keep))
    old_to_new = new_index[first]
    return v[keep], old_to_new[f], old_to_new


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
    """``v`` divided by its largest absolute coordinate (if finite and > 0), for scale-free tests."""
    extent = float(np.abs(v).max())
    return v / extent if 0 < extent < np.inf else v


def _face_areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return 0.5 * np.linalg.norm(cross, axis=1)


def _edge_face_incidence(f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique edges ``(E, 2)``, faces per edge, face-edge ids ``(F, 3)`` (edge ``c``: opposite corner c)."""
    he = np.stack([f[:, [1, 2]], f[:, [2, 0]], f[:, [0, 1]]], axis=1).reshape(-1, 2)
    und = np.sort(he, axis=1)
    n = int(f.max()) + 1 if f.size else 1
    keys, inverse, counts = np.unique(und[:, 0] * n + und[:, 1], return_inverse=True, return_counts=True)
    edges = np.stack([keys // n, keys % n], axis=1)
    return edges, counts, inverse.reshape(-1, 3)


def _edge_components(edges: np.ndarray, n: int) -> tuple[int, np.ndarray]:
    """``(n_components, labels (n,))`` of the graph of ``edges (E, 2)`` on ``n`` vertices."""
    graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)


def _count_boundary_loops(boundary_edges: np.ndarray, n_vertices: int) -> int:
    if len(boundary_edges) == 0:
        return 0
    labels = _edge_components(boundary_edges, n_vertices)[1]
    return len(np.unique(labels[np.unique(boundary_edges)]))


def duplicate_faces(faces) -> np.ndarray:
    """Sorted indices of the faces ``(F, 3)`` that repeat an earlier face's vertex set (any order)."""
    f = np.sort(np.asarray(faces, dtype=np.int64), axis=1)
    if len(f) == 0:
        return np.zeros(0, dtype=np.int64)
    n = int(f.max()) + 1
    if n <= 2_000_000:  # one int64 key per face (n**3 < 2**63): far faster than axis=0
        _, first = np.unique((f[:, 0] * n + f[:, 1]) * n + f[:, 2], return_index=True)
    else:
        _, first = np.unique(f, axis=0, return_index=True)
    repeated = np.ones(len(f), dtype=bool)
    repeated[first] = False
    return np.flatnonzero(repeated)


def validate_mesh(
    vertices,
    faces,
    *,
    allow_components: bool = False,
    allow_unreferenced: bool = False,
    allow_nonmanifold: bool | str = False,
) -> MeshReport:
    """Check ``vertices (V, 3)`` and ``faces (F, 3)``; return a :class:`MeshReport` (holes are reported).
    Raises :class:`MeshError` for an empty mesh, non-finite coordinates, face indices out of range,
    degenerate faces, and (unless allowed by flag; ``allow_nonmanifold='warn'``: accepted, and
    :class:`~torchfmap.Mesh` warns) unreferenced vertices, non-manifold edges, several components."""
    v, f = _as_arrays(vertices, faces)
    if len(v) == 0 or len(f) == 0:
        raise MeshError(
            f"empty mesh ({len(v)} vertices, {len(f)} faces). Fix: check the file path and "
            "format; a point cloud needs `laplacian(points, scheme='robust')` instead."
        )
    bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
    if len(bad):
        raise MeshError(
            f"{len(bad)} vertices have NaN or infinite coordinates: vertices {_preview(bad)}. "
            "Fix: repair or remove them (and the faces using them) before building operators."
        )
    bad = np.flatnonzero(((f < 0) | (f >= len(v))).any(axis=1))
    if len(bad):
        one_based = f.min() == 1 and f.max() == len(v)  # every index in 1..V, none 0
        hint = (
            f"Every index is in 1..{len(v)} and none is 0: the faces are 1-based. Fix: subtract 1 "
            "from every face index (in the file: rewrite it 0-based, as OFF requires)."
            if one_based
            else "Fix: faces must be 0-based indices into the vertex array (subtract 1 if they come "
            "from a 1-based format)."
        )
        raise MeshError(
            f"{len(bad)} faces index vertices outside [0, {len(v)}): faces {_preview(bad)}. {hint}"
        )
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    # judged on unit-size coordinates: a tiny or huge mesh's areas must not under- or overflow
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
    used = np.zeros(len(v), dtype=bool)
    used[f.ravel()] = True
    unref = np.flatnonzero(~used)
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
            "`laplacian(mesh, scheme='robust')` (intrinsic tufted Laplacian) with "
            "allow_nonmanifold=True."
        )
    n_comp, labels = _edge_components(edges, len(v))
    n_comp_used = len(np.unique(labels[used]))
    boundary = edges[counts == 1]
    on_boundary = np.zeros(len(v), dtype=bool)
    on_boundary[boundary.ravel()] = True
    first = coincident_groups(v)
    # a seam: boundary vertices at one position (inner ones, each with a closed fan, are harmless)
    n_coincident = int(np.count_nonzero((first != np.arange(len(v))) & on_boundary & on_boundary[first]))
    if n_comp_used > 1 and n_coincident and not allow_components:
        soup = n_comp_used == len(f)
        raise MeshError(
            f"the mesh has {n_comp_used} connected components and {n_coincident} vertices that share "
            "their position with another: "
            + ("a triangle soup (every face has its own vertices)" if soup else "it is cut along seams")
            + ". Fix: weld coincident vertices first, e.g. torchfmap.weld_vertices(vertices, faces) "
            "(vertex indices change: remap correspondences with the map it returns), or MeshLab's "
            "'Merge Close Vertices'."
        )
    if n_comp_used > 1 and not allow_components:
        sizes = np.bincount(labels)
        raise MeshError(
            f"the mesh has {n_comp_used} connected components (sizes "
            f"{sorted(sizes[sizes > 1].tolist(), reverse=True)[:6]}). Fix: keep one with "
            "`mesh.largest_component()`, or pass allow_components=True and give every component "
            "a seed when building bases."
        )
    report = MeshReport(
        n_vertices=len(v),
        n_faces=len(f),
        n_components=n_comp_used,
        n_boundary_edges=len(boundary),
        n_boundary_loops=_count_boundary_loops(boundary, len(v)),
        unreferenced=unref,
        euler_characteristic=int(len(v) - len(unref) - len(edges) + len(f)),
        n_nonmanifold_edges=int(np.count_nonzero(counts > 2)),
        n_coincident_vertices=n_coincident,
    )
    if not report.is_closed:
        log.info("mesh has %d hole(s) (%d boundary edges)", report.n_boundary_loops, len(boundary))
    return report


def orient_faces(vertices, faces) -> tuple[np.ndarray, int]:
    """``(faces (F, 3), n_flipped)``: every component consistently oriented along a breadth-first
    spanning tree of its faces, keeping its majority orientation; components closed but for at most
    :data:`CLOSED_BOUNDARY_FRACTION` boundary edges, enclosing volume, are turned outward. Only corner
    order changes; ``n_flipped`` counts the reversed faces."""
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
        _, labels = connected_components(graph, directed=False)
        by_comp = np.argsort(labels, kind="stable")  # each component's faces, ascending
        for members in np.split(by_comp, np.flatnonzero(np.diff(labels[by_comp])) + 1):
            if len(members) == 1:
                continue
            # the component's own subgraph (searching the whole graph per component is quadratic)
            sub, rel = graph[members][:, members], relative[members][:, members]
            bfs, pred = breadth_first_order(sub, 0, directed=False, return_predecessors=True)
            kids = bfs[1:]
            needs = np.asarray(rel[kids, pred[kids]]).ravel() == 2
            tree = zip(members[kids].tolist(), members[pred[kids]].tolist(), needs.tolist(), strict=True)
            for face, parent, x in tree:
                flip[face] = flip[parent] ^ x  # parents come before children in BFS order
            if flip[members].sum() * 2 > len(members):  # keep the majority's orientation
                flip[members] = ~flip[members]
    out = f.copy()
    out[flip] = out[flip][:, ::-1]
    # closed (or nearly closed) components: outward normals (positive signed volume)
    vlabels = _edge_components(he, n)[1]
    flabels = vlabels[out[:, 0]]
    unit = _unit_coordinates(v)  # the sign test is scale-free: no overflow
    x0, x1, x2 = unit[out[:, 0]], unit[out[:, 1]], unit[out[:, 2]]
    centre = unit[np.unique(out)].mean(axis=0)
    vol = np.einsum("ij,ij->i", x0 - centre, np.cross(x1 - centre, x2 - centre)) / 6.0
    area = _face_areas(unit, out)
    comp_vol = np.bincount(flabels, weights=vol)
    comp_area = np.bincount(flabels, weights=area)
    boundary_he = first[counts == 1]
    comp_boundary = np.bincount(flabels[owner[order[boundary_he]]], minlength=len(comp_vol))
    comp_edges = np.bincount(flabels, minlength=len(comp_vol)) * 1.5
    closed = comp_boundary <= CLOSED_BOUNDARY_FRACTION * comp_edges
    inward = closed & (comp_vol < -0.01 * comp_area**1.5)
    turn = inward[flabels]
    out[turn] = out[turn][:, ::-1]
    flipped = flip ^ turn
    return out, int(flipped.sum())
