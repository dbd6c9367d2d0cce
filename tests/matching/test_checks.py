"""Checks of match's arguments (``torchfmap.matching.checks``): given bases of meshes of different
sizes, as ``torchfmap basis SRC TGT --landmarks`` writes them for any real pair."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import Mesh, ParameterError, match, prepare_shape
from torchfmap.matching.checks import check_meshes
from torchfmap.matching.solve import match_bases
from torchfmap.seeds import farthest_point_sampling

from ..conftest import bumpy_blob


def test_given_bases_of_meshes_of_different_sizes_solve_and_refine():
    """The pair (642 and 162 vertices) built together at corresponding landmarks, given back to
    match: solved in them (no comparison of per-vertex arrays of different lengths)."""
    x, y = bumpy_blob(3), bumpy_blob(2)  # one shape at two resolutions: vertex i of y is vertex i of x
    lm_y = farthest_point_sampling(y, 6)
    landmarks = np.stack([lm_y, lm_y], axis=1)
    sx, sy = prepare_shape(x, 0), prepare_shape(y, 0)
    bx, by, _ = match_bases(sx, sy, "diffusion", 12, landmarks)
    result = match(x, y, bases=(bx, by), refine="icp")
    assert result.p2p_yx.shape == (y.n_vertices,) and result.kind == "diffusion"
    assert result.p2p_yx.max() < x.n_vertices


def test_what_is_not_a_mesh_is_named_with_how_to_make_one(tmp_path):
    x = bumpy_blob(1)
    with pytest.raises(ParameterError, match=r"mesh_x is a str, not a torchfmap Mesh.*load_mesh\('a.off'\)"):
        match("a.off", x)
    with pytest.raises(ParameterError, match=r"mesh_y is a PosixPath.*load_mesh"):
        check_meshes(x, tmp_path / "b.off")
    soup = type("Trimeshish", (), {"vertices": x.vertices, "faces": x.faces})()
    with pytest.raises(ParameterError, match=r"Mesh\(m.vertices, m.faces\)"):
        check_meshes(soup, x)
    with pytest.raises(ParameterError, match=r"is a ndarray.*Mesh\(vertices \(V, 3\), faces"):
        check_meshes(x.vertices, x)
    check_meshes(x, Mesh(x.vertices, x.faces))  # meshes pass


def _cut(mesh: Mesh, axis: int = 2) -> Mesh:
    """The faces of ``mesh`` above the plane through its centroid (a part, vertices re-indexed)."""
    keep = mesh.vertices[mesh.faces].mean(axis=1)[:, axis] > mesh.vertices[:, axis].mean()
    part, _ = Mesh(mesh.vertices, mesh.faces[keep], allow_unreferenced=True).referenced()
    return part


def test_a_part_matched_to_a_whole_shape_is_warned_with_the_fix():
    import warnings

    from torchfmap.errors import MapWarning
    from torchfmap.matching.checks import boundary_length, warn_if_partial

    whole, part = bumpy_blob(2), _cut(bumpy_blob(2))
    assert boundary_length(whole) == 0 and boundary_length(part) > 1.0
    assert boundary_length(part.scaled(30.0)) == pytest.approx(boundary_length(part))  # scale-free
    with pytest.warns(MapWarning, match=r"mesh_y looks partial: its boundary is .* ratio 0\.\d+.*landmarks"):
        match(whole, part, k=8)
    with pytest.warns(MapWarning, match="mesh_x looks partial"):
        warn_if_partial(part, whole)
    with warnings.catch_warnings():
        warnings.simplefilter("error", MapWarning)
        warn_if_partial(whole, whole.scaled(3.0))  # whole shapes, any units: no word
        warn_if_partial(part, _cut(bumpy_blob(2), axis=1))  # two parts: no word either


def _open_seam(mesh: Mesh) -> Mesh:
    """``mesh`` slit open along a chain of edges: the chain's inner vertices duplicated for the
    faces on one side (same positions), its two ends shared, so the mesh stays connected."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import shortest_path

    v, f = mesh.vertices, mesh.faces
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    lengths = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    graph = sp.coo_matrix((lengths, (e[:, 0], e[:, 1])), shape=(len(v), len(v))).tocsr()
    a, b = int(np.argmax(v[:, 2])), int(np.argmax(v[:, 0]))  # north pole to the equator
    _, pred = shortest_path(graph, indices=a, return_predecessors=True)
    chain = [b]
    while chain[-1] != a:
        chain.append(int(pred[chain[-1]]))
    inner = np.array(chain[1:-1])
    side = v[f].mean(axis=1)[:, 1] > 0  # the faces on one side of the chain's plane y = 0 (about)
    copy = {int(i): len(v) + j for j, i in enumerate(inner)}
    faces = f.copy()
    for row in np.flatnonzero(side):
        faces[row] = [copy.get(int(i), int(i)) for i in f[row]]
    return Mesh(np.vstack([v, v[inner]]), faces, allow_unreferenced=True)


def test_a_whole_shape_with_an_open_seam_gets_the_seam_advice_only():
    """An open seam (duplicated vertices along a chain, the mesh still connected) is a boundary
    that a weld closes, not the edge of a cut: the mesh's warning says weld, and no 'looks
    partial' follows it (it told users to match with --partial)."""
    import warnings

    from torchfmap.errors import MapWarning, MeshWarning
    from torchfmap.matching.checks import boundary_length, warn_if_partial

    whole = bumpy_blob(2)
    with pytest.warns(MeshWarning, match="weld"):
        seamed = _open_seam(whole)
    assert len(seamed.boundary_edges) > 0 and seamed.n_vertices > whole.n_vertices  # really open
    assert boundary_length(seamed) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error", MapWarning)
        warn_if_partial(whole, seamed)
    part = _cut(bumpy_blob(2))  # a cut still counts, seam or not
    assert boundary_length(part) > 1.0
