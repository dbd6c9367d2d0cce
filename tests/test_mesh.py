"""Mesh validation: every bad input raises MeshError naming the problem; holes are reported."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import Mesh, MeshError, validate_mesh
from torchfmap.data import icosphere

TET_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def test_valid_tetrahedron_report():
    rep = validate_mesh(TET_V, TET_F)
    assert (rep.n_vertices, rep.n_faces, rep.n_components) == (4, 4, 1)
    assert rep.is_closed and rep.n_boundary_loops == 0
    assert rep.euler_characteristic == 2


def test_empty_mesh():
    with pytest.raises(MeshError, match="empty mesh"):
        Mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int))


def test_wrong_shapes():
    with pytest.raises(MeshError, match=r"vertices must have shape \(V, 3\)"):
        Mesh(np.zeros((4, 2)), TET_F)
    with pytest.raises(MeshError, match="triangulate"):
        Mesh(TET_V, np.array([[0, 1, 2, 3]]))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_vertices(bad):
    v = TET_V.copy()
    v[2, 1] = bad
    with pytest.raises(MeshError, match=r"NaN or infinite coordinates: vertices \[2\]"):
        Mesh(v, TET_F)


@pytest.mark.parametrize("index", [4, -1])
def test_face_index_out_of_range(index):
    f = TET_F.copy()
    f[3, 2] = index
    with pytest.raises(MeshError, match=r"outside \[0, 4\).*1-based"):
        Mesh(TET_V, f)


def test_degenerate_zero_area_face():
    v = np.vstack([TET_V, [0.5, 0.5, 0.0]])  # vertex 4 on the edge 1-2
    f = np.vstack([TET_F, [1, 2, 4]])
    with pytest.raises(MeshError, match=r"1 degenerate faces .*faces \[4\]"):
        validate_mesh(v, f, allow_nonmanifold=True)


def test_degenerate_repeated_vertex():
    f = TET_F.copy()
    f[0] = [0, 0, 1]
    with pytest.raises(MeshError, match="degenerate faces"):
        Mesh(TET_V, f)


def test_unreferenced_vertices():
    v = np.vstack([TET_V, [5.0, 5, 5]])
    with pytest.raises(MeshError, match=r"not used by any face: vertices \[4\]"):
        Mesh(v, TET_F)
    rep = validate_mesh(v, TET_F, allow_unreferenced=True)
    assert rep.unreferenced.tolist() == [4]


def test_nonmanifold_edge():
    # three triangles hinged on the edge 0-1
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]])
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(MeshError, match=r"non-manifold edges .*\(0, 1\).*robust"):
        Mesh(v, f)
    assert Mesh(v, f, allow_nonmanifold=True).n_faces == 3


def test_several_components():
    two = np.vstack([TET_V, TET_V + 3.0])
    faces = np.vstack([TET_F, TET_F + 4])
    with pytest.raises(MeshError, match="2 connected components.*largest_component"):
        Mesh(two, faces)
    mesh = Mesh(two, faces, allow_components=True)
    assert mesh.n_components == 2
    part, ids = mesh.largest_component()
    assert part.n_vertices == 4 and np.allclose(part.vertices, two[ids])


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


def test_lazy_geometry(sphere3):
    assert sphere3.area == pytest.approx(4 * np.pi, rel=1e-2)
    assert sphere3.edges.shape == (3 * sphere3.n_faces // 2, 2)
    assert sphere3.boundary_edges.shape == (0, 2)
    # outward normals on the unit sphere
    assert np.min(np.einsum("ij,ij->i", sphere3.vertex_normals, sphere3.vertices)) > 0.99
    assert np.unique(sphere3.component_labels).size == 1


def test_permuted_mesh_is_same_surface(sphere2, rng):
    perm = rng.permutation(sphere2.n_vertices)
    p = sphere2.permuted(perm)
    assert np.allclose(p.vertices, sphere2.vertices[perm])
    assert p.area == pytest.approx(sphere2.area, rel=1e-14)
    with pytest.raises(MeshError, match="permutation"):
        sphere2.permuted(np.zeros(sphere2.n_vertices, dtype=int))


def test_icosphere_sizes():
    for s in range(4):
        assert icosphere(s).n_vertices == 10 * 4**s + 2
