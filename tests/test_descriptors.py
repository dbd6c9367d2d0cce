"""Descriptors: HKS/WKS against the sphere's closed forms and a naive reference, invariances,
scale behaviour, landmark descriptors (heat and WKS), normalisation and checks.

Discretisation tolerance used below. The cotan Laplacian on a mesh with edges of length at
most ``h`` approximates an eigenvalue ``λ`` of the smooth surface with a relative error
``ε(λ) = λ h² / 12`` (consistency error of the cotan stencil: ``h²/12`` times the fourth
derivatives, which scale like ``λ²`` for an eigenfunction); the lumped-mass eigenfunctions
are pointwise accurate to the same relative order. On the unit sphere the eigenvalues are
``l(l+1)`` with multiplicity ``2l+1`` and ``Σ_m Y_lm(p)² = (2l+1)/|S|`` at every point.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
import scipy.linalg as sla

from torchfmap import Mesh, ParameterError, SeedError, laplacian, laplacian_eigenbasis, total_area
from torchfmap.data import icosphere
from torchfmap.descriptors import (
    check_descriptors,
    hks,
    landmark_descriptors,
    normalize_descriptors,
    shot,
    shot_support,
    wks,
)

from .conftest import bumpy_blob, random_rotation

L_MAX = 4  # degrees 0..4: (L_MAX + 1)² = 25 eigenpairs, whole eigenvalue clusters


def cotan_rel_error(lam, mesh) -> np.ndarray:
    """Relative eigenvalue / eigenfunction accuracy ``λ h² / 12`` (module docstring)."""
    return np.asarray(lam, dtype=float) * mesh.edge_lengths.max() ** 2 / 12


K_SPHERE = (L_MAX + 1) ** 2


@functools.cache
def sphere_setup(subdivisions: int):
    mesh = icosphere(subdivisions)
    basis = laplacian_eigenbasis(mesh, K_SPHERE)
    return mesh, basis


@pytest.mark.parametrize("subdivisions", [2, 3])
def test_hks_on_sphere_matches_closed_form(subdivisions):
    """HKS(p, t) = Σ_l (2l+1)/|S| e^{-l(l+1)t}, the same at every vertex.

    Tolerance: each degree contributes with relative error ε_l (eigenfunction) plus
    t·l(l+1)·ε_l (the eigenvalue shift in the exponent), ε_l = l(l+1)h²/12; the bound is their
    average weighted by the degree's share of the sum. The mesh area |S| (not 4π) is used: the
    inscribed polyhedron's area deficit is a separate O(h²) that we do not need to bound.
    """
    mesh, basis = sphere_setup(subdivisions)
    ls = np.arange(L_MAX + 1)
    ll = ls * (ls + 1.0)
    times = np.array([0.02, 0.05, 0.2, 1.0, 3.0])
    H = hks(basis.eigenvalues, basis.values, abs_times=times)
    assert H.shape == (mesh.n_vertices, len(times))
    weights = (2 * ls + 1)[:, None] * np.exp(-np.outer(ll, times))  # (L, T)
    closed = weights.sum(axis=0) / total_area(mesh)
    eps = cotan_rel_error(ll, mesh)[:, None]
    bound = (weights * eps * (1 + ll[:, None] * times)).sum(axis=0) / weights.sum(axis=0)
    rel = np.abs(H - closed) / closed  # (V, T): every vertex, every time
    assert np.all(rel <= bound), (rel.max(axis=0), bound)
    # constant over the vertices: each within `bound` of the same value
    assert np.all(np.ptp(H, axis=0) / closed <= 2 * bound)


def test_hks_on_sphere_converges_at_second_order():
    """The deviation from the closed form is O(h²): one subdivision halves h (ratio ~0.51),
    so the error must drop by ~3.9; we require more than 2 (i.e. better than first order)."""
    errors = []
    for s in (2, 3):
        mesh, basis = sphere_setup(s)
        ls = np.arange(L_MAX + 1)
        t = 0.1
        closed = ((2 * ls + 1) * np.exp(-ls * (ls + 1) * t)).sum() / total_area(mesh)
        errors.append(np.abs(hks(basis.eigenvalues, basis.values, abs_times=[t])[:, 0] - closed).max())
    assert errors[0] / errors[1] > 2.0, errors


def test_sphere_eigenvalues_cluster_as_spherical_harmonics():
    """The discrete spectrum (the input of HKS/WKS) has l(l+1) with multiplicity 2l+1, each
    within the cotan relative error l(l+1)h²/12."""
    mesh, basis = sphere_setup(3)
    exact = np.concatenate([[d * (d + 1.0)] * (2 * d + 1) for d in range(L_MAX + 1)])
    assert np.all(np.abs(basis.eigenvalues - exact) <= exact * cotan_rel_error(exact, mesh) + 1e-9)


def test_heat_trace_identity(blob):
    """Σ_v B_vv HKS(v, t) = Σ_k e^{-λ_k t} exactly (B-orthonormal eigenfunctions): the heat
    trace. Round-off only: orthonormality holds to ~1e-13, so rtol 1e-10."""
    basis = laplacian_eigenbasis(blob, 20)
    times = np.geomspace(1e-3, 1.0, 7)
    H = hks(basis.eigenvalues, basis.values, abs_times=times)
    mass = basis.mass.diagonal()
    trace = np.exp(-np.outer(np.maximum(basis.eigenvalues, 0), times)).sum(axis=0)
    np.testing.assert_allclose(mass @ H, trace, rtol=1e-10)


def test_hks_default_times_and_naive_sum(blob):
    """Default times: n_times values log-spaced from 4 ln10/λ_max to 4 ln10/λ_1 (Sun et al.);
    checked against the literal sum Σ_k e^{-λ_k t} φ_k(x)² (round-off: rtol 1e-12)."""
    basis = laplacian_eigenbasis(blob, 15)
    lam, phi = basis.eigenvalues, basis.values
    times = np.geomspace(4 * np.log(10) / lam[-1], 4 * np.log(10) / lam[1], 6)
    naive = np.zeros((blob.n_vertices, 6))
    for j, t in enumerate(times):
        for k in range(len(lam)):
            naive[:, j] += np.exp(-max(lam[k], 0) * t) * phi[:, k] ** 2
    np.testing.assert_allclose(hks(lam, phi, n_times=6), naive, rtol=1e-12)


def wks_reference(evals, evecs, n_energies, sigma_factor=7.0):
    """Aubry et al. 2011, written out: log-energies evenly spaced between the logs of the
    smallest non-zero and the largest eigenvalue, Gaussian width ``σ = factor·range/E``,
    each energy's weights normalised to sum 1, the zero eigenvalue left out."""
    out = np.zeros((evecs.shape[0], n_energies))
    nz = evals > 1e-10 * evals.max()
    logs = np.log(evals[nz])
    energies = np.linspace(logs.min(), logs.max(), n_energies)
    sigma = sigma_factor * (logs.max() - logs.min()) / n_energies
    for j, e in enumerate(energies):
        w = np.exp(-((e - logs) ** 2) / (2 * sigma**2))
        w /= w.sum()
        for wk, phi in zip(w, evecs[:, nz].T, strict=True):
            out[:, j] += wk * phi**2
    return out


def test_wks_matches_definition(blob):
    """WKS rows equal the definition written out naively on the same eigenpairs (round-off)."""
    basis = laplacian_eigenbasis(blob, 30)
    for n_e, factor in ((12, 7.0), (40, 3.0)):
        got = wks(basis.eigenvalues, basis.values, n_energies=n_e, sigma_factor=factor)
        np.testing.assert_allclose(
            got, wks_reference(basis.eigenvalues, basis.values, n_e, factor), rtol=1e-10
        )


def test_wks_integrates_to_one(blob):
    """Each energy's weights sum to 1 and every φ_k has unit B-norm, so ∫ WKS(·, e) = 1."""
    basis = laplacian_eigenbasis(blob, 30)
    W = wks(basis.eigenvalues, basis.values, n_energies=25)
    np.testing.assert_allclose(basis.mass.diagonal() @ W, 1.0, rtol=1e-10)


def test_wks_constant_on_sphere():
    """On the sphere every vertex sees the same (2l+1)/|S| per cluster; discrete values are
    within ε_max = λ_max h²/12 of that, so the spread over vertices is at most 2 ε_max."""
    mesh, basis = sphere_setup(3)
    W = wks(basis.eigenvalues, basis.values, n_energies=50)
    eps_max = cotan_rel_error(basis.eigenvalues.max(), mesh)
    assert np.all(np.ptp(W, axis=0) / W.mean(axis=0) <= 2 * eps_max)


def test_descriptors_invariant_to_rigid_motion_and_permutation(blob, rng):
    """Rigid motion and relabelling leave the operators unchanged (up to round-off), so HKS and
    WKS are unchanged / permuted. Eigenvectors move by round-off / spectral gap; with a relative
    gap above 1e-3 on this asymmetric blob that is ~1e-12: rtol 1e-8 leaves a wide margin."""
    k = 20
    base = laplacian_eigenbasis(blob, k)
    moved = blob.copy(blob.vertices @ random_rotation(rng).T + rng.normal(size=3))
    perm = rng.permutation(blob.n_vertices)
    for other, index in ((moved, np.arange(blob.n_vertices)), (blob.permuted(perm), perm)):
        b = laplacian_eigenbasis(other, k)
        np.testing.assert_allclose(
            b.eigenvalues, base.eigenvalues, rtol=1e-9, atol=1e-12 * base.eigenvalues[-1]
        )
        np.testing.assert_allclose(
            hks(b.eigenvalues, b.values), hks(base.eigenvalues, base.values)[index], rtol=1e-8
        )
        np.testing.assert_allclose(
            wks(b.eigenvalues, b.values, 16), wks(base.eigenvalues, base.values, 16)[index], rtol=1e-8
        )


def test_hks_scale_behaviour(blob):
    """Scaling by a: λ -> λ/a², φ -> φ/a. HKS at times a²t equals HKS(t)/a²; the default times
    (∝ 1/λ) follow the scale, so default HKS scales exactly by 1/a². WKS is scale-free up to
    1/a² as well (log-energies shift, weights do not change). Round-off: rtol 1e-8."""
    a = 2.5
    b0 = laplacian_eigenbasis(blob, 15)
    b1 = laplacian_eigenbasis(blob.scaled(a), 15)
    t = np.array([1e-2, 1e-1])
    np.testing.assert_allclose(
        hks(b1.eigenvalues, b1.values, abs_times=a**2 * t),
        hks(b0.eigenvalues, b0.values, abs_times=t) / a**2,
        rtol=1e-8,
    )
    np.testing.assert_allclose(
        hks(b1.eigenvalues, b1.values), hks(b0.eigenvalues, b0.values) / a**2, rtol=1e-8
    )
    np.testing.assert_allclose(
        wks(b1.eigenvalues, b1.values, 10), wks(b0.eigenvalues, b0.values, 10) / a**2, rtol=1e-8
    )


def test_spectral_descriptor_errors():
    phi = np.ones((10, 3))
    with pytest.raises(ParameterError, match="disagree"):
        hks(np.ones(2), phi)
    with pytest.raises(ParameterError, match="at least 2"):
        wks(np.ones(1), np.ones((10, 1)))
    with pytest.raises(ParameterError, match="times must be finite and > 0"):
        hks(np.array([0.0, 1.0, 2.0]), phi, abs_times=[0.1, -1.0])


def test_landmark_heat_equals_spectral_kernel(sphere2):
    """kernel='heat' is K_t(l, x) = Σ_k e^{-λ_k t} φ_k(l) φ_k(x) with the full spectrum (dense
    eigh on 162 vertices) at absolute times t·|M|; columns ordered (landmark, time). The Krylov
    heat solver's target accuracy is `tol`=1e-8 relative: compare at 1e-6 of the kernel's max."""
    L, B = laplacian(sphere2)
    lam, phi = sla.eigh(L.toarray(), B.toarray())
    lm = np.array([0, 17, 90])
    rel_times = np.array([1e-3, 1e-2])
    D = landmark_descriptors(lm, operators=(L, B), times=rel_times, tol=1e-8)
    assert D.shape == (sphere2.n_vertices, len(lm) * len(rel_times))
    area = B.sum()
    for i, vertex in enumerate(lm):
        for j, t in enumerate(rel_times * area):
            ref = phi @ (np.exp(-np.maximum(lam, 0) * t) * phi[vertex])
            np.testing.assert_allclose(D[:, i * len(rel_times) + j], ref, atol=1e-6 * np.abs(ref).max())
    # `area` overrides |M|: times are relative to the given area
    D2 = landmark_descriptors(lm, operators=(L, B), times=rel_times * area / 2.0, area=2.0, tol=1e-8)
    np.testing.assert_allclose(D2, D, atol=1e-6 * np.abs(D).max())


def test_landmark_wks_matches_definition_and_is_symmetric(blob):
    """kernel='wks': column (l, e) is Σ_k w_e(λ_k) φ_k(l) φ_k(·) with WKS weights; the kernel is
    symmetric (value of l's column at l' equals l''s column at l); its value at the landmark
    itself is the WKS of the landmark. Round-off only."""
    basis = laplacian_eigenbasis(blob, 30)
    lam, phi = basis.eigenvalues, basis.values
    lm = np.array([3, 100, 400])
    E = 8
    D = landmark_descriptors(lm, kernel="wks", evals=lam, evecs=phi, n_energies=E)
    assert D.shape == (blob.n_vertices, len(lm) * E)
    D3 = D.reshape(blob.n_vertices, len(lm), E)
    scale = np.abs(D).max()
    np.testing.assert_allclose(D3[lm[0], 1], D3[lm[1], 0], atol=1e-12 * scale)
    np.testing.assert_allclose(D3[lm, np.arange(3)], wks(lam, phi, E)[lm], atol=1e-12 * scale)
    # naive: the reference WKS weights from the reference WKS of an indicator-free evaluation
    nz = lam > 1e-10 * lam.max()
    logs = np.log(lam[nz])
    energies = np.linspace(logs.min(), logs.max(), E)
    sigma = 7.0 * (logs.max() - logs.min()) / E
    for e_idx, e in enumerate(energies):
        w = np.exp(-((e - logs) ** 2) / (2 * sigma**2))
        w /= w.sum()
        ref = phi[:, nz] @ (w * phi[lm[2], nz])
        np.testing.assert_allclose(D3[:, 2, e_idx], ref, atol=1e-12 * scale)


def test_landmark_descriptor_errors(sphere2):
    ops = laplacian(sphere2)
    with pytest.raises(ParameterError, match="need operators"):
        landmark_descriptors([0])
    with pytest.raises(ParameterError, match="unknown landmark descriptor kernel 'bogus'"):
        landmark_descriptors([0], kernel="bogus", operators=ops)
    with pytest.raises(ParameterError, match="disagree"):
        landmark_descriptors([0], kernel="wks", evals=np.ones(3), evecs=np.ones((5, 2)))
    with pytest.raises(SeedError, match="out of range for a mesh of 162 vertices"):
        landmark_descriptors([sphere2.n_vertices], operators=ops)


def test_normalize_descriptors(blob, rng):
    F = rng.normal(size=(blob.n_vertices, 4))
    F[:, 2] = 0.0
    N = normalize_descriptors(F)
    np.testing.assert_allclose(np.linalg.norm(N, axis=0), [1, 1, 0, 1], rtol=1e-12)
    np.testing.assert_allclose(N[:, 0] * np.linalg.norm(F[:, 0]), F[:, 0], rtol=1e-12)  # direction kept
    _, B = laplacian(blob)
    NB = normalize_descriptors(F, mass=B)
    np.testing.assert_allclose(np.einsum("ij,ij->j", NB, B @ NB), [1, 1, 0, 1], rtol=1e-12)


def test_check_descriptors(blob, rng):
    F = rng.normal(size=(blob.n_vertices, 7))
    assert check_descriptors(F[:, 0], blob.n_vertices).shape == (blob.n_vertices, 1)
    with pytest.raises(ParameterError, match="must be \\(V, D\\) with V=642"):
        check_descriptors(F[:-1], blob.n_vertices)
    bad = F.copy()
    bad[5, 4] = np.nan
    with pytest.raises(ParameterError, match=r"non-finite values in columns \[4\]"):
        check_descriptors(bad, blob.n_vertices, "descriptors")


def test_no_nan_from_bad_descriptor_parameters(sphere2):
    from torchfmap import laplacian_eigenbasis
    from torchfmap.descriptors import hks, wks

    basis = laplacian_eigenbasis(sphere2, 10)
    for t in (float("nan"), float("inf"), -1.0):
        with pytest.raises(ParameterError, match="HKS times must be finite"):
            hks(basis.eigenvalues, basis.values, abs_times=[t])
    for s in (0.0, -1.0, float("nan")):
        with pytest.raises(ParameterError, match="sigma_factor"):
            wks(basis.eigenvalues, basis.values, sigma_factor=s)


def test_shot_of_a_dense_mesh_reads_a_voxel_quadrature_that_moves_with_it():
    """Above ``support`` vertices SHOT reads a voxel quadrature of the surface: it errs less than the
    exact SHOT of the mesh before subdivision (a quarter of the vertices, about half the quadrature's
    points) does, conserves the area, and a rigid motion with a uniform scale moves its cubes with the
    surface (same signatures but where round-off decides a border, as for the exact SHOT)."""
    import trimesh

    coarse = bumpy_blob(4)
    v, f = trimesh.remesh.subdivide(coarse.vertices, coarse.faces)  # old vertices first
    fine = Mesh(np.asarray(v), np.asarray(f, dtype=np.int64))
    radius, n0 = 0.15 * np.sqrt(fine.area), coarse.n_vertices
    exact = shot(fine, radius, support=10**9)
    sampled = shot(fine, radius, support=5000)  # twice the coarse mesh's vertices

    def agree(a, b):
        return float(np.mean(np.einsum("ij,ij->i", a, b)))

    assert agree(sampled, exact) > agree(shot(coarse, radius)[:n0], exact[:n0])
    areas = np.bincount(fine.faces.ravel(), np.repeat(fine.face_areas / 3, 3), fine.n_vertices)
    points, total, normals = shot_support(fine.vertices, areas, fine.vertex_normals, 2500)
    assert 2500 / 2 <= len(points) <= 4 * 2500 and np.isclose(total.sum(), fine.area, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    R = random_rotation(np.random.default_rng(1))
    moved = fine.copy(vertices=2.0 * fine.vertices @ R.T + 5.0)
    same = np.abs(shot(moved, 2.0 * radius, support=5000) - sampled).max(axis=1) < 1e-8
    assert same.mean() > 0.98
    with pytest.raises(ParameterError, match="support"):
        shot(fine, radius, support=10)
