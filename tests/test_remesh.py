"""Remeshing (torchfmap.remesh, optional extra 'remesh'): target sizes, carried ground truth,
and operators that do not depend on the meshing (sphere spectrum on anisotropic triangles)."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError
from torchfmap.operators import laplacian

from .conftest import smallest_eigenvalues

pytest.importorskip("pymeshlab")
from torchfmap.remesh import remesh  # noqa: E402


@pytest.mark.parametrize("method", ["isotropic", "anisotropic", "decimate"])
def test_remesh_reaches_the_target_and_carries_vertices(sphere4, method):
    out = remesh(sphere4, 1500, method, seed=3)
    m = out.mesh
    assert abs(m.n_vertices - 1500) <= 0.1 * 1500
    assert m.n_components == 1 and m.report.euler_characteristic == 2
    # to_new: the nearest new vertex of every old vertex, so within about one new edge
    gap = np.linalg.norm(m.vertices[out.to_new] - sphere4.vertices, axis=1)
    assert gap.max() <= 1.5 * m.edge_lengths.max()
    brute = np.argmin(((sphere4.vertices[:50, None] - m.vertices[None]) ** 2).sum(-1), axis=1)
    np.testing.assert_array_equal(out.to_new[:50], brute)


def aspect(mesh) -> np.ndarray:
    """Longest edge over the height on it, per face (1.15 for an equilateral triangle)."""
    v, f = mesh.vertices, mesh.faces
    e = np.stack([np.linalg.norm(v[f[:, (i + 1) % 3]] - v[f[:, i]], axis=1) for i in range(3)], 1)
    longest = e.max(1)
    return longest**2 / (2 * mesh.face_areas)


def test_anisotropic_triangles_are_elongated_and_the_spectrum_stays(sphere4):
    iso = remesh(sphere4, 1500, "isotropic").mesh
    aniso = remesh(sphere4, 1500, "anisotropic", stretch=3.0, direction=[0, 0, 1]).mesh
    assert np.median(aspect(aniso)) > 1.8 * np.median(aspect(iso))
    # the cotangent Laplacian converges on any (non-degenerate) triangulation: the first
    # eigenvalues of the unit sphere stay l(l+1); the error is O(h^2) with h the longest
    # edge (stretched triangles have longer edges), bounded here by 4 h^2 l(l+1)
    exact = np.array([0] + [2] * 3 + [6] * 5, dtype=float)
    for m in (iso, aniso):
        L, B = laplacian(m)
        h = m.edge_lengths.max()
        got = smallest_eigenvalues(L, B, 9)
        assert np.all(np.abs(got - exact) <= 4 * h**2 * np.maximum(exact, 1) + 1e-8), (got, h)


def test_remesh_refuses_bad_settings(sphere4):
    with pytest.raises(ParameterError, match="unknown remeshing method"):
        remesh(sphere4, 1000, "quad")
    with pytest.raises(ParameterError, match="n_vertices"):
        remesh(sphere4, 10)
    with pytest.raises(ParameterError, match="stretch"):
        remesh(sphere4, 1000, "anisotropic", stretch=1.0)
    with pytest.raises(ParameterError, match="direction"):
        remesh(sphere4, 1000, "anisotropic", direction=[0, 0, 0])
