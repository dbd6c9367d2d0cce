"""Mesh validation (``torchfmap.mesh_checks.validate_mesh``): the report, degenerate faces, holes
reported not raised."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import Mesh, MeshError, MeshWarning, validate_mesh, weld_vertices

from .conftest import TET_F, TET_V


def test_valid_tetrahedron_report():
    rep = validate_mesh(TET_V, TET_F)
    assert (rep.n_vertices, rep.n_faces, rep.n_components) == (4, 4, 1)
    assert rep.is_closed and rep.n_boundary_loops == 0
    assert rep.euler_characteristic == 2


def test_degenerate_zero_area_face():
    v = np.vstack([TET_V, [0.5, 0.5, 0.0]])  # vertex 4 on the edge 1-2
    f = np.vstack([TET_F, [1, 2, 4]])
    with pytest.raises(MeshError, match=r"1 degenerate faces .*faces \[4\]"):
        validate_mesh(v, f, allow_nonmanifold=True)


def test_holes_reported_not_raised(sphere2):
    # remove the faces around vertex 0: one hole
    ring = np.flatnonzero((sphere2.faces == 0).any(axis=1))
    holed = sphere2.without_faces(ring)
    rep = validate_mesh(holed.vertices, holed.faces, allow_unreferenced=True)
    assert rep.n_boundary_loops == 1 and not rep.is_closed
    assert rep.n_boundary_edges == len(ring)
    # two separate holes
    far = int(np.argmin(sphere2.vertices @ sphere2.vertices[0]))
    ring2 = np.flatnonzero((sphere2.faces == far).any(axis=1))
    rep2 = sphere2.without_faces(np.concatenate([ring, ring2])).report
    assert rep2.n_boundary_loops == 2


def test_weld_vertices_keeps_first_appearance_order_and_maps_old_to_new():
    soup = np.array([[2.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 0, 0]])
    v, f, old_to_new = weld_vertices(soup, np.array([[0, 1, 3], [2, 1, 3]]), rtol=0)
    assert v.tolist() == [[2, 0, 0], [1, 0, 0], [0, 0, 0]]
    assert f.tolist() == [[0, 1, 2], [0, 1, 2]]
    assert old_to_new.tolist() == [0, 1, 0, 2]
    # within the tolerance (relative to the bounding-box diagonal, 2 here) positions are one
    near = soup + np.array([[0, 0, 0], [0, 0, 0], [1e-10, 0, 0], [0, 0, 0]])
    assert weld_vertices(near, [[0, 1, 3]], rtol=1e-9)[0].shape == (3, 3)
    assert weld_vertices(near, [[0, 1, 3]], rtol=0)[0].shape == (4, 3)


def _soup(mesh_v, mesh_f):
    """Every face with its own three vertices (as an STL or a naive exporter writes them)."""
    return mesh_v[mesh_f].reshape(-1, 3), np.arange(3 * len(mesh_f)).reshape(-1, 3)


def test_a_triangle_soup_is_told_to_weld_and_welding_restores_the_mesh(sphere2):
    v, f = _soup(sphere2.vertices, sphere2.faces)
    with pytest.raises(MeshError, match=r"triangle soup.*weld coincident vertices.*weld_vertices"):
        validate_mesh(v, f)
    wv, wf, old_to_new = weld_vertices(v, f)
    report = validate_mesh(wv, wf)
    assert report.n_components == 1 and report.is_closed and report.n_coincident_vertices == 0
    np.testing.assert_array_equal(wv[old_to_new], v)  # the map carries every old vertex


def test_a_seam_of_coincident_vertices_is_reported_and_warned(sphere2):
    """Cut the sphere's faces on one side of a great circle loose from the other by duplicating
    the vertices they share: one component still (the poles join them), a seam reported."""
    v, f = sphere2.vertices, sphere2.faces.copy()
    side = v[f].mean(axis=1)[:, 0] > 0
    shared = np.intersect1d(f[side], f[~side])
    shared = shared[v[shared, 1] > 0.2]  # part of the circle: the mesh stays one piece
    copies = len(v) + np.arange(len(shared))
    remap = np.arange(len(v))
    remap[shared] = copies
    f[side] = remap[f[side]]
    v2 = np.vstack([v, v[shared]])
    report = validate_mesh(v2, f)
    assert report.n_components == 1 and report.n_coincident_vertices == len(shared)
    assert "coincident vertices (seams)" in report.summary()
    with pytest.warns(MeshWarning, match=rf"{len(shared)} vertices share their position.*weld_vertices"):
        Mesh(v2, f)


def test_orientation_of_many_components_is_fixed_one_component_at_a_time(sphere2):
    """Each component is searched in its own subgraph (a search of the whole face graph per
    component made a mesh of many components quadratic): every copy of a sphere with faces
    flipped, and one single face, come out consistent and outward, as one sphere alone does."""
    from torchfmap.mesh_checks import orient_faces

    n, nv = 60, sphere2.n_vertices
    faces = sphere2.faces.copy()
    faces[::3] = faces[::3, ::-1]
    one, flipped_one = orient_faces(sphere2.vertices, faces)
    verts = np.vstack([sphere2.vertices + 3 * c for c in range(n)] + [np.eye(3) + 3 * n])
    many = np.vstack([faces + c * nv for c in range(n)] + [[[n * nv, n * nv + 1, n * nv + 2]]])
    out, flipped = orient_faces(verts, many)
    np.testing.assert_array_equal(out[:-1], np.vstack([one + c * nv for c in range(n)]))
    assert flipped == n * flipped_one and out[-1].tolist() == many[-1].tolist()


def test_duplicate_faces_with_indices_beyond_the_int64_key():
    """Faces are keyed by one int64 per face while ``V**3`` fits; larger indices take the
    row-wise path, with the same answer (the later copies, any corner order)."""
    from torchfmap.mesh_checks import duplicate_faces

    f = np.array([[0, 1, 2], [2, 1, 0], [3, 4, 5], [1, 2, 0], [5, 4, 6]])
    np.testing.assert_array_equal(duplicate_faces(f), [1, 3])
    np.testing.assert_array_equal(duplicate_faces(f + 3_000_000), [1, 3])
    assert duplicate_faces(np.zeros((0, 3), dtype=int)).size == 0
