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


def test_density_grows_the_edges_along_a_direction_as_the_inversion_predicts(sphere4):
    """``density``: an inversion centred at distance D = R / (sqrt(density) - 1) before the
    sphere (diameter R) along u scales lengths by |x - c|^2, so edges whose midpoints lie at
    fraction f of the way along u are (D + f R)^2 long up to a constant: the mean edge of the
    far decile (f about 0.95) over the near one (f about 0.05) is ((D + 0.95 R) / (D + 0.05 R))^2,
    to the remesher's own spread of edge lengths (it splits above 4/3 and collapses below 4/5
    of its target); triangles keep their shape (the inversion is conformal)."""
    density, seed = 4.0, 3
    out = remesh(sphere4, 2000, "isotropic", density=density, seed=seed).mesh
    uniform = remesh(sphere4, 2000, "isotropic", seed=seed).mesh
    u = np.random.default_rng(seed).normal(size=3)  # the seed's first draw without a stretch
    u /= np.linalg.norm(u)
    edges = out.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    at = out.vertices[edges].mean(axis=1) @ u
    length = np.linalg.norm(out.vertices[edges[:, 0]] - out.vertices[edges[:, 1]], axis=1)
    near, far = np.quantile(at, [0.1, 0.9])
    R = 2.0
    D = R / (np.sqrt(density) - 1.0)
    expected = ((D + 0.95 * R) / (D + 0.05 * R)) ** 2
    assert 0.8 * expected < length[at >= far].mean() / length[at <= near].mean() < 1.25 * expected
    assert np.median(aspect(out)) < 1.25 * np.median(aspect(uniform))
    with pytest.raises(ParameterError, match="density"):
        remesh(sphere4, 1000, "isotropic", density=0.5)
    with pytest.raises(ParameterError, match="density"):
        remesh(sphere4, 1000, "decimate", density=2.0)


def test_remesh_refuses_bad_settings(sphere4):
    with pytest.raises(ParameterError, match="unknown remeshing method"):
        remesh(sphere4, 1000, "quad")
    with pytest.raises(ParameterError, match="n_vertices"):
        remesh(sphere4, 10)
    with pytest.raises(ParameterError, match="stretch"):
        remesh(sphere4, 1000, "anisotropic", stretch=1.0)
    with pytest.raises(ParameterError, match="direction"):
        remesh(sphere4, 1000, "anisotropic", direction=[0, 0, 0])
