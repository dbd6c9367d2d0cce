"""The Mesh type (``torchfmap.mesh``): every bad input raises MeshError naming the problem; flipped
and duplicated faces are repaired with a warning; lazy geometry and permutation."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import Mesh, MeshError, MeshWarning, validate_mesh

from .conftest import TET_F, TET_V, bumpy_blob


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


@pytest.mark.parametrize("which", ["all", "half"])
def test_flipped_faces_are_reoriented_and_reported(which):
    """A target with flipped faces (all, or every other one) used to be matched as its mirror
    image through the orientation term. The mesh is re-oriented on construction (closed
    components outward), with a MeshWarning, and matches exactly like the original."""
    from torchfmap import Mesh, MeshWarning, match

    from .conftest import bend, bumpy_blob

    x = bumpy_blob(2)
    y = x.copy(bend(x.vertices, 0.3))
    faces = y.faces.copy()
    rows = slice(None) if which == "all" else slice(None, None, 2)
    faces[rows] = faces[rows][:, ::-1]
    with pytest.warns(MeshWarning, match="reversed the corner order"):
        flipped = Mesh(y.vertices, faces)
    assert flipped.report.n_flipped_faces == len(faces[rows])
    np.testing.assert_array_equal(flipped.faces, y.faces)
    a = match(x, y, k=15, k_descriptors=30)
    b = match(x, flipped, k=15, k_descriptors=30)
    np.testing.assert_array_equal(a.p2p_yx, b.p2p_yx)


def test_consistent_mesh_is_left_alone(sphere2):
    """An outward, consistent mesh is not touched (no warning, same faces)."""
    import warnings

    from torchfmap import Mesh

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = Mesh(sphere2.vertices, sphere2.faces)
    assert m.report.n_flipped_faces == 0
    np.testing.assert_array_equal(m.faces, sphere2.faces)


def test_duplicated_faces_are_dropped_with_a_warning_and_the_operators_are_unchanged():
    from torchfmap import Mesh
    from torchfmap.operators import laplacian

    mesh = bumpy_blob(1)
    doubled = np.concatenate([mesh.faces, mesh.faces[[3]][:, ::-1]])  # the same face, another corner order
    with pytest.warns(MeshWarning, match="dropped 1 duplicated faces"):
        twin = Mesh(mesh.vertices, doubled, allow_nonmanifold=True)
    assert twin.n_faces == mesh.n_faces
    a, b = laplacian(mesh), laplacian(twin)
    assert abs(a.stiffness - b.stiffness).max() == 0 and abs(a.mass - b.mass).max() == 0
