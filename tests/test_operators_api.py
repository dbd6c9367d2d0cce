"""Operators, factorisations, geodesics, point-cloud Laplacians, sign fixing, heat_apply, the
error hierarchy, mesh reports and the seed helpers."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla
import scipy.sparse.linalg as spla

from torchfmap import (
    ConvergenceError,
    Factorization,
    Mesh,
    MeshError,
    MeshReport,
    MeshWarning,
    Operators,
    ParameterError,
    SeedError,
    TorchFmapError,
    factorize,
    geodesic_distances,
    laplacian,
    point_cloud_laplacian,
    validate_mesh,
)
from torchfmap.data import icosphere
from torchfmap.operators import check_vertex_indices, heat_apply
from torchfmap.operators.eigen import fix_signs
from torchfmap.seeds import check_seeds_cover_components, max_curvature_vertex

from .conftest import bumpy_blob


def test_operators_unpack_and_factorization_solves(sphere2, rng):
    ops = laplacian(sphere2)
    assert isinstance(ops, Operators)
    L, B = ops
    assert L is ops.stiffness and B is ops.mass
    A = (L + 0.5 * B).tocsc()  # SPD
    fac = factorize(A, spd=True)
    assert isinstance(fac, Factorization)
    b = rng.normal(size=(sphere2.n_vertices, 3))
    # backward-stable direct solve: residual ~ eps·cond(A)·|b|; cond(L + B/2) here < 1e4
    for rhs in (b, b[:, 0]):
        x = fac.solve(rhs)
        assert x.shape == rhs.shape
        np.testing.assert_allclose(x, spla.spsolve(A, rhs), rtol=1e-9, atol=1e-12)


def test_geodesic_distances_on_sphere(sphere3):
    """Unit sphere: d(p, q) = arccos(p·q). Heat method with t = h² is first order: error ≤ h_max
    (distances ≤ π, constant O(1))."""
    v = sphere3.vertices
    src = np.array([0, 100, 400])
    D = geodesic_distances(sphere3, src)
    assert D.shape == (3, sphere3.n_vertices)
    exact = np.arccos(np.clip(v[src] @ v.T, -1, 1))
    assert np.abs(D - exact).max() <= sphere3.edge_lengths.max()
    np.testing.assert_allclose(D[np.arange(3), src], 0.0, atol=1e-12)


def test_point_cloud_laplacian(sphere3, rng):
    """Symmetric, constants in the kernel (round-off), mass = area of the sampled sphere up to
    an inscribed triangulation's O(h²) deficit, equivariant under relabelling the points."""
    L, B = point_cloud_laplacian(sphere3.vertices)
    n = sphere3.n_vertices
    assert abs(L - L.T).max() <= 1e-12 * abs(L).max()
    assert np.abs(L @ np.ones(n)).max() <= 1e-12 * abs(L).max()
    assert abs(B.sum() - 4 * np.pi) / (4 * np.pi) <= sphere3.edge_lengths.max() ** 2
    perm = rng.permutation(n)
    Lp, Bp = point_cloud_laplacian(sphere3.vertices[perm])
    np.testing.assert_allclose(Bp.diagonal(), B.diagonal()[perm], rtol=1e-10)
    with pytest.raises(MeshError, match="V>=4, 3"):
        point_cloud_laplacian(np.zeros((3, 3)))


def test_check_vertex_indices():
    np.testing.assert_array_equal(check_vertex_indices([3, 1], 5), [3, 1])
    np.testing.assert_array_equal(check_vertex_indices(np.array([2.0, 4.0]), 5), [2, 4])
    for bad, msg in (
        ([1, 1], "duplicates"),
        ([], "empty"),
        ([0.5], "integer"),
        ([[0, 1]], "1-D"),
        ([5], "out of range"),
    ):
        with pytest.raises(SeedError, match=msg):
            check_vertex_indices(bad, 5)


def test_fix_signs(blob, rng):
    """After fixing, every column's B-weighted third moment Σ m_v φ_v³ is positive, and the
    result does not depend on the input signs."""
    L, B = laplacian(blob)
    _, phi = sla.eigh(L.toarray(), B.toarray(), subset_by_index=(1, 6))
    fixed = fix_signs(phi, B)
    m = np.asarray(B.sum(axis=1)).ravel()
    assert np.all(m @ fixed**3 > 0)
    flips = rng.choice([-1.0, 1.0], size=phi.shape[1])
    np.testing.assert_array_equal(fix_signs(phi * flips, B), fixed)
    np.testing.assert_array_equal(np.abs(fixed), np.abs(phi))


def test_heat_apply_equals_spectral_exponential(sphere2, rng):
    """exp(-t B⁻¹L) X = Φ e^{-Λt} Φᵀ B X with the full dense spectrum (162 vertices). Krylov
    accuracy target tol = 1e-8 relative: compared at 1e-6 of max |result|."""
    L, B = laplacian(sphere2)
    lam, phi = sla.eigh(L.toarray(), B.toarray())
    X = rng.normal(size=(sphere2.n_vertices, 2))
    times = np.array([1e-3, 1e-1, 1.0])
    out = heat_apply((L, B), X, times, tol=1e-8)
    assert out.shape == (3, sphere2.n_vertices, 2)
    for j, t in enumerate(times):
        ref = phi @ (np.exp(-np.maximum(lam, 0) * t)[:, None] * (phi.T @ (B @ X)))
        np.testing.assert_allclose(out[j], ref, atol=1e-6 * np.abs(ref).max())


def test_error_hierarchy_and_mesh_report(sphere2):
    for cls in (MeshError, SeedError, ParameterError, ConvergenceError):
        assert issubclass(cls, TorchFmapError) and issubclass(cls, ValueError)
    assert issubclass(MeshWarning, UserWarning) and not issubclass(MeshWarning, TorchFmapError)
    with pytest.raises(TorchFmapError):
        check_vertex_indices([9], 5)
    report = validate_mesh(sphere2.vertices, sphere2.faces)
    assert isinstance(report, MeshReport)
    assert (report.n_vertices, report.n_faces) == (162, 320)
    assert report.n_components == 1 and report.n_boundary_edges == 0 and report.euler_characteristic == 2


def test_check_seeds_cover_components():
    a, b = icosphere(1), icosphere(1)
    two = Mesh(
        np.vstack([a.vertices, b.vertices + 3.0]),
        np.vstack([a.faces, b.faces + a.n_vertices]),
        validate=False,
    )
    check_seeds_cover_components(two, np.array([0, a.n_vertices]))  # one seed per component: fine
    with pytest.raises(SeedError, match="1 connected component\\(s\\) have no seed"):
        check_seeds_cover_components(two, np.array([0, 1]))


def test_max_curvature_vertex_finds_a_spike():
    """A sphere with one vertex pulled out by 40%: the largest |mean curvature| (after 1-ring
    smoothing) is at the spike or in its 1-ring."""
    mesh = icosphere(3)
    spike = 77
    v = mesh.vertices.copy()
    v[spike] *= 1.4
    spiky = mesh.copy(v)
    ring = np.unique(mesh.faces[np.any(mesh.faces == spike, axis=1)])
    assert max_curvature_vertex(spiky) in ring
    assert max_curvature_vertex(spiky, smooth_steps=0) == spike
    # and on the asymmetric blob it is a vertex index, stable under rigid motion
    blob = bumpy_blob(2)
    assert max_curvature_vertex(blob) == max_curvature_vertex(blob.copy(blob.vertices + 5.0))
