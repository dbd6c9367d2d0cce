"""Functional-map solver (``torchfmap.fmap.solver``): closed forms, rotation exactness, each term
against a dense least-squares solve, priors, multiplication operators, a real isometric pair,
bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfmap import (
    ParameterError,
    SeedError,
    farthest_point_sampling,
    laplacian,
    laplacian_eigenbasis,
    load_mesh,
)
from torchfmap.bases import basis_stack
from torchfmap.bases.prepared import prepare_shape
from torchfmap.data import icosphere
from torchfmap.descriptors import hks, landmark_descriptors, normalize_descriptors, wks
from torchfmap.evaluate.scores import evaluate_map, gt_identity
from torchfmap.fmap import FmapProblem, build_problem, fmap_to_p2p, multiplication_operator, solve_fmap
from torchfmap.matching.solve import match_bases
from torchfmap.operators import eigenpairs

from ..conftest import bend, bumpy_blob, data_path, np_mask


def descriptors(mesh, k=30):
    basis = laplacian_eigenbasis(mesh, k)
    return normalize_descriptors(
        np.hstack([wks(basis.eigenvalues, basis.values, 20), hks(basis.eigenvalues, basis.values, 8)])
    )


@pytest.fixture(scope="module")
def pair():
    """The demo blob and a deformed copy with the same connectivity (identity ground truth)."""
    x = bumpy_blob(3)
    y = x.copy(bend(x.vertices, 0.25))
    return x, y


def vec_solve(A_x, A_y, W_x, W_y, w_desc, w_lap):
    """Brute-force k^2 x k^2 least squares of w_desc |C A_x - A_y|^2 + w_lap |C W_x - W_y C|^2."""
    ky, kx = A_y.shape[0], A_x.shape[0]
    # vec(C A_x) = (A_x^T kron I) vec(C) with column-major vec
    M1 = np.kron(A_x.T, np.eye(ky))
    M2 = np.kron(W_x.T, np.eye(ky)) - np.kron(np.eye(kx), W_y)
    M = np.vstack([np.sqrt(w_desc) * M1, np.sqrt(w_lap) * M2])
    rhs = np.concatenate([np.sqrt(w_desc) * A_y.ravel(order="F"), np.zeros(kx * ky)])
    return np.linalg.lstsq(M, rhs, rcond=None)[0].reshape((ky, kx), order="F")


def test_eigenbasis_matches_direct_least_squares(pair):
    x, y = pair
    bx, by = laplacian_eigenbasis(x, 12), laplacian_eigenbasis(y, 10)
    dx, dy = descriptors(x), descriptors(y)
    C = solve_fmap(bx, by, dx, dy, w_lap=1e-2)
    prob = build_problem(bx, by, dx, dy, w_lap=1e-2)
    # the mask is normalised to mean one: compare with the same scaled Laplacian term
    scale = np.mean((bx.eigenvalues[None, :] - by.eigenvalues[:, None]) ** 2)
    ref = vec_solve(
        bx.project(dx), by.project(dy), np.diag(bx.eigenvalues), np.diag(by.eigenvalues), 1.0, 1e-2 / scale
    )
    assert C.shape == (10, 12)
    assert np.abs(C - ref).max() < 1e-8 * np.abs(ref).max()
    assert prob.energy(prob.solve()) <= prob.energy(prob.solve() + 1e-4) + 1e-12


def test_general_basis_rotation_equals_full_solve(pair):
    x, y = pair
    seeds = farthest_point_sampling(x, 6, metric="euclidean")
    bx = basis_stack(x, seeds, times=[1e-2], n_eigen=4)
    by = basis_stack(y, seeds, times=[1e-2], n_eigen=4)
    W_x, W_y = bx.projected_laplacian(), by.projected_laplacian()
    assert np.abs(W_x - np.diag(np.diag(W_x))).max() > 1e-3  # genuinely non-diagonal
    dx, dy = descriptors(x), descriptors(y)
    C = solve_fmap(bx, by, dx, dy, w_lap=1e-2)
    lam_x, lam_y = np.linalg.eigvalsh(W_x), np.linalg.eigvalsh(W_y)
    scale = np.mean((lam_x[None, :] - lam_y[:, None]) ** 2)
    ref = vec_solve(bx.project(dx), by.project(dy), W_x, W_y, 1.0, 1e-2 / scale)
    assert np.abs(C - ref).max() < 1e-7 * np.abs(ref).max()


def test_extra_terms_solved_by_cg_match_dense(pair):
    x, y = pair
    bx, by = laplacian_eigenbasis(x, 8), laplacian_eigenbasis(y, 8)
    dx, dy = descriptors(x)[:, :6], descriptors(y)[:, :6]
    lm = np.array([[10, 10], [200, 200], [400, 400]])
    prob = build_problem(bx, by, dx, dy, w_lap=1e-2, w_dcomm=1e-1, landmarks=lm, w_lmk=1.0)
    Cr = prob.solve()
    # dense normal equations of the same quadratic energy
    n = Cr.size
    H = np.column_stack([prob.normal_matvec(e.reshape(Cr.shape)).ravel() for e in np.eye(n)])
    ref = np.linalg.solve(H, prob.normal_rhs().ravel()).reshape(Cr.shape)
    # CG stops at a relative residual of 1e-8 (solve's tol), so the solution's relative error is
    # at most cond(H) times that (plus the dense solve's own rounding); 2x for rounding in both
    bound = 2 * (np.linalg.cond(H) * 1e-8 + 1e-12)
    assert np.linalg.norm(Cr - ref) <= bound * np.linalg.norm(ref)
    # the energy is at its minimum: any perturbation increases it
    e0 = prob.energy(Cr)
    for d in np.random.default_rng(0).normal(size=(5,) + Cr.shape):
        assert prob.energy(Cr + 1e-3 * d) > e0


def dense_hessian(prob):
    shape = prob.shape
    n = shape[0] * shape[1]
    return np.column_stack([prob.normal_matvec(e.reshape(shape)).ravel() for e in np.eye(n)])


def test_preconditioner_blocks_are_the_hessian_diagonal_blocks(pair):
    x, y = pair
    bx, by = laplacian_eigenbasis(x, 7), laplacian_eigenbasis(y, 6)
    dx, dy = descriptors(x)[:, :5], descriptors(y)[:, :5]
    lm = np.array([[10, 10], [200, 200]])
    prob = build_problem(
        bx, by, dx, dy, w_lap=1e-2, w_dcomm=1e-1, w_orient=1e-1, meshes=(x, y), landmarks=lm, w_lmk=1.0
    )
    H = dense_hessian(prob)
    ky, kx = prob.shape
    blocks = prob.row_blocks()
    for i in range(ky):  # row-major vec: row i of C' is entries i*kx ... (i+1)*kx - 1
        ref = H[i * kx : (i + 1) * kx, i * kx : (i + 1) * kx]
        assert np.abs(blocks[i] - ref).max() < 1e-12 * np.abs(ref).max()
    # and the full solve with orientation (reversing sign too) is the dense minimiser
    for reversing in (False, True):
        prob = build_problem(
            bx, by, dx, dy, w_orient=1e-1, orient_reversing=reversing, meshes=(x, y), landmarks=lm, w_lmk=1.0
        )
        ref = np.linalg.solve(dense_hessian(prob), prob.normal_rhs().ravel()).reshape(prob.shape)
        assert np.abs(prob.solve() - ref).max() < 1e-6 * np.abs(ref).max()


def test_unconverged_solve_raises(pair):
    from torchfmap import ConvergenceError

    x, y = pair
    bx, by = laplacian_eigenbasis(x, 10), laplacian_eigenbasis(y, 10)
    dx, dy = descriptors(x)[:, :6], descriptors(y)[:, :6]
    prob = build_problem(bx, by, dx, dy, w_dcomm=1.0)
    with pytest.raises(ConvergenceError, match="did not converge"):
        prob.solve(tol=1e-14, maxiter=1)


def test_landmark_term_is_scale_free(pair):
    """Scaling the meshes by alpha (basis / alpha, mass * alpha^2) must not change C_xy."""
    from torchfmap.bases import Basis

    x, y = pair
    lm = np.array([[10, 10], [200, 200], [400, 400]])
    bases = laplacian_eigenbasis(x, 10), laplacian_eigenbasis(y, 10)
    raw = descriptors(x)[:, :6], descriptors(y)[:, :6]
    maps = []
    for alpha in (1.0, 37.0):
        bx, by = (
            Basis(
                b.values / alpha, b.mass * alpha**2, b.provenance, True, b.stiffness, b.eigenvalues / alpha**2
            )
            for b in bases
        )
        dx, dy = normalize_descriptors(raw[0], bx.mass), normalize_descriptors(raw[1], by.mass)
        prob = build_problem(bx, by, dx, dy, landmarks=lm, w_lmk=1.0, w_lap=1e-3)
        maps.append(prob.unrotate(prob.solve(tol=1e-10)))
    # CG stops at relative residual <= tol, so each map's relative error is <= cond(H) * tol
    # (H the normal-equation operator, built column by column here; the frame rotations are
    # orthogonal, so they change neither norms nor cond): the two maps agree to
    # twice that. Before the landmark rows were scaled they differed by 25 %.
    k = prob.shape[0] * prob.shape[1]
    H = np.stack([prob.normal_matvec(e.reshape(prob.shape)).ravel() for e in np.eye(k)], axis=1)
    bound = 2 * np.linalg.cond(H) * 1e-10
    assert np.abs(maps[0] - maps[1]).max() <= bound * np.abs(maps[0]).max()


def test_orientation_term_runs_and_is_finite(pair):
    x, y = pair
    bx, by = laplacian_eigenbasis(x, 10), laplacian_eigenbasis(y, 10)
    dx, dy = descriptors(x)[:, :4], descriptors(y)[:, :4]
    C = solve_fmap(bx, by, dx, dy, w_orient=1e-1, meshes=(x, y))
    assert np.isfinite(C).all()
    with pytest.raises(ParameterError, match="meshes"):
        solve_fmap(bx, by, dx, dy, w_orient=1e-1)


def test_isometric_wolf_pair_near_diagonal_and_low_error():
    folder = data_path("tosca_hires_wolf")
    x, y = load_mesh(folder / "wolf0.off"), load_mesh(folder / "wolf1.off")
    k = 30
    bx, by = laplacian_eigenbasis(x, k), laplacian_eigenbasis(y, k)
    dx = normalize_descriptors(wks(bx.eigenvalues, bx.values, 50), laplacian(x)[1])
    dy = normalize_descriptors(wks(by.eigenvalues, by.values, 50), laplacian(y)[1])
    lm = np.array([[i, i] for i in (0, 1000, 2000, 3000, 4000)])
    lx = landmark_descriptors(lm[:, 0], operators=laplacian(x))
    ly = landmark_descriptors(lm[:, 1], operators=laplacian(y))
    C = solve_fmap(
        bx, by, np.hstack([dx, normalize_descriptors(lx)]), np.hstack([dy, normalize_descriptors(ly)])
    )
    # energy concentrates near the diagonal (blocks of near-equal eigenvalues)
    band = np.abs(np.subtract.outer(np.arange(k), np.arange(k))) <= 2
    assert np.sum(C[band] ** 2) / np.sum(C**2) > 0.8
    report, _ = evaluate_map(x, y, fmap_to_p2p(C, bx, by), gt_identity(x.n_vertices), max_points=400)
    assert report.mean_error < 0.05


def test_bad_inputs(pair):
    x, y = pair
    bx, by = laplacian_eigenbasis(x, 8), laplacian_eigenbasis(y, 8)
    dx, dy = descriptors(x), descriptors(y)
    with pytest.raises(ParameterError, match="descriptor counts differ"):
        solve_fmap(bx, by, dx, dy[:, :5])
    with pytest.raises(ParameterError, match=r"desc_x must be \(V, D\) with V=642"):
        solve_fmap(bx, by, dx[:100], dy)
    bad = dx.copy()
    bad[3, 2] = np.nan
    with pytest.raises(ParameterError, match=r"non-finite values in columns \[2\]"):
        solve_fmap(bx, by, bad, dy)
    with pytest.raises(SeedError, match=r"target landmarks \[5000\] are out of range for a mesh of"):
        solve_fmap(bx, by, dx, dy, landmarks=[[0, 5000]], w_lmk=1.0)
    from torchfmap import harmonic_basis

    with pytest.raises(ParameterError, match="not B-orthonormal"):
        solve_fmap(harmonic_basis(x, [0, 10, 20]), by, dx, dy)


def _orientation_by_gradients(mesh, basis, F):
    """Reference: per-face gradients of hat functions, n × ∇f, dotted with ∇φ, lumped by A/3."""
    v, f = mesh.vertices, mesh.faces
    n, area = mesh.face_normals, mesh.face_areas
    grads = []  # grads[c]: (F, 3) gradient of the hat function of corner c
    for c in range(3):
        e = v[f[:, (c + 2) % 3]] - v[f[:, (c + 1) % 3]]
        grads.append(np.cross(n, e) / (2 * area)[:, None])
    phi = basis.values
    grad_phi = sum(grads[c][:, :, None] * phi[f[:, c]][:, None, :] for c in range(3))  # (F, 3, K)
    corner_sum = phi[f[:, 0]] + phi[f[:, 1]] + phi[f[:, 2]]  # (F, K)
    out = []
    for j in range(F.shape[1]):
        grad_f = sum(grads[c] * F[f[:, c], j][:, None] for c in range(3))
        field = np.cross(n, grad_f)
        along = np.einsum("fd,fdk->fk", field, grad_phi)  # (n × ∇f)·∇φ_l per face
        out.append((corner_sum * (area / 3)[:, None]).T @ along)
    return out


def test_orientation_operators_match_gradient_definition(pair):
    from torchfmap.fmap import orientation_operators

    mesh = pair[1]
    basis = laplacian_eigenbasis(mesh, 25)
    F = descriptors(mesh)[:, :5]
    fast = orientation_operators(mesh, basis, F)
    ref = _orientation_by_gradients(mesh, basis, F)
    for a, b in zip(fast, ref, strict=True):
        assert a.shape == (25, 25)
        np.testing.assert_allclose(a, b, atol=1e-12 * np.abs(b).max())
    single = orientation_operators(mesh, basis, F, np.float32)  # what build_problem uses
    for a, b in zip(single, ref, strict=True):
        assert a.dtype == np.float64
        np.testing.assert_allclose(a, b, atol=1e-5 * np.abs(b).max())


def test_orientation_operator_planar_closed_form():
    """On the plane z = 0 (normal +z), n × ∇x = ŷ, so (n × ∇x)·∇g = ∂g/∂y: in the raw
    'basis' (1, x, y), O[k, l] = ∫ φ_k ∂φ_l/∂y, i.e. O[:, 2] = (area, ∫x, ∫y) and O[:, :2] = 0."""
    from torchfmap.bases import Basis
    from torchfmap.fmap import orientation_operators

    from ..conftest import planar_grid

    mesh = planar_grid(7, jitter=0.25)
    x, y = mesh.vertices[:, 0], mesh.vertices[:, 1]
    _, B = laplacian(mesh)
    basis = Basis(np.stack([np.ones_like(x), x, y], axis=1), B)
    op_x, O_y = orientation_operators(mesh, basis, np.stack([x, y], axis=1))
    # lumped face quadrature (A/3 per corner) is exact for linear integrands
    integral = lambda g: float(sum(mesh.face_areas * g[mesh.faces].mean(axis=1)))  # noqa: E731
    np.testing.assert_allclose(op_x[:, 2], [integral(np.ones_like(x)), integral(x), integral(y)], rtol=1e-12)
    np.testing.assert_allclose(op_x[:, :2], 0.0, atol=1e-12)
    # rotating f by 90 degrees in the plane: f = y gives n × ∇y = -x̂, so O[:, 1] = -(area, ∫x, ∫y)
    np.testing.assert_allclose(O_y[:, 1], -op_x[:, 2], rtol=1e-12)


def test_classical_solve_runs_its_small_torch_work_single_threaded(pair, monkeypatch):
    """The eigen-decompositions and row-wise systems of the classical solve are small: they run
    with one torch thread (torch's threads otherwise wait for cores held by BLAS's spinning
    threads after numpy work), and the caller's torch thread count comes back afterwards."""
    from torchfmap._util.threads import thread_limit, torch_threads
    from torchfmap.fmap import core

    x, y = pair
    bx, by = laplacian_eigenbasis(x, 20), laplacian_eigenbasis(y, 20)
    dx = normalize_descriptors(wks(bx.eigenvalues, bx.values, 10), bx.mass)
    dy = normalize_descriptors(wks(by.eigenvalues, by.values, 10), by.mass)
    seen = []
    for name in ("spectral_frame", "solve_rowwise", "laplacian_mask"):
        real = getattr(core, name)
        monkeypatch.setattr(
            core,
            name,
            lambda *a, _real=real, _n=name, **k: seen.append((_n, torch.get_num_threads())) or _real(*a, **k),
        )
    before = torch.get_num_threads()
    with torch_threads(2):  # as on a multi-core machine, whatever this one has
        C = solve_fmap(bx, by, dx, dy)
        assert torch.get_num_threads() == 2
    assert torch.get_num_threads() == before and np.isfinite(C).all()
    assert {n for n, _ in seen} == {"spectral_frame", "solve_rowwise", "laplacian_mask"}
    assert all(t == 1 for _, t in seen)
    with pytest.raises(RuntimeError, match="inside"), thread_limit(1):
        assert torch.get_num_threads() == 1
        raise RuntimeError("inside")
    assert torch.get_num_threads() == before


def test_identity_prior_solve_recovers_the_identity(permuted_pair):
    """Exactly corresponding bases and descriptors: C = I zeroes every term of the energy, so
    the solve returns it (up to the row-wise solve's round-off) for any prior weight."""
    x, y, perm, lm = permuted_pair
    sx, sy = prepare_shape(x, 0), prepare_shape(y, 0)
    bx, by, _ = match_bases(sx, sy, "diffusion", 20, lm)
    F = np.random.default_rng(0).normal(size=(x.n_vertices, 8))
    for w_prior in (0.1, 10.0):
        C = solve_fmap(bx, by, F, F[perm], w_lap=1.0, prior=np.eye(20), w_prior=w_prior)
        np.testing.assert_allclose(C, np.eye(20), atol=1e-8)


def test_build_problem_uses_mask(sphere2):
    """FmapProblem carries the mask of the frames' eigenvalues."""
    basis = laplacian_eigenbasis(sphere2, 9)
    F = np.random.default_rng(0).normal(size=(sphere2.n_vertices, 4))
    prob = build_problem(basis, basis, F, F, mask="resolvent")
    assert isinstance(prob, FmapProblem)
    np.testing.assert_allclose(prob.mask, np_mask(prob.frame_x.lam, prob.frame_y.lam, "resolvent"))


def test_multiplication_operator_algebra():
    """In the FULL eigenbasis (K = V, lumped mass) Φ Φᵀ B = I, so D_f D_g = D_{fg} and
    D_1 = I exactly; D_f is symmetric. Round-off of dense eigh on 42 vertices: atol 1e-10."""
    mesh = icosphere(1)
    L, B = laplacian(mesh)
    from torchfmap import Basis

    lam, phi = eigenpairs(L, B, mesh.n_vertices)
    basis = Basis(phi, B, orthonormal=True, stiffness=L, eigenvalues=lam)
    f, g = mesh.vertices[:, 0], mesh.vertices[:, 1] ** 2
    Df, Dg = multiplication_operator(basis, f), multiplication_operator(basis, g)
    np.testing.assert_allclose(Df @ Dg, multiplication_operator(basis, f * g), atol=1e-10)
    np.testing.assert_allclose(
        multiplication_operator(basis, np.ones(mesh.n_vertices)), np.eye(42), atol=1e-10
    )
    np.testing.assert_allclose(Df, Df.T, atol=1e-12)


def test_overflowing_descriptors_are_refused(sphere2):
    from torchfmap import laplacian_eigenbasis, solve_fmap

    basis = laplacian_eigenbasis(sphere2, 8)
    F = np.full((sphere2.n_vertices, 3), 1e300)
    with pytest.raises(ParameterError, match="overflow.*normalize_descriptors"):
        solve_fmap(basis, basis, F, F)


def test_a_solve_too_large_for_the_memory_is_refused_before_any_work(monkeypatch, blob):
    """The (K_y, K_x, K_x) row systems are counted twice (systems and factors, or blocks and
    inverse) in the estimate; a solve above the memory available is refused with the estimate,
    what is available and the fix, an unreadable memory refuses nothing. (An irregular mesh: a
    sphere's WKS is constant up to discretisation noise, so whether its systems are singular
    depends on the BLAS.)"""
    from torchfmap import MemoryEstimateError
    from torchfmap.fmap import solver

    assert solver.solve_bytes(2000, 2000) >= 2 * 8 * 2000**3  # the 59.6 GiB row blocks, and a twin
    assert solver.solve_bytes(60, 40) == 8 * (
        2 * 40 * 60 * 60 + 2 * solver.MAX_OPERATOR_DESCRIPTORS * (60**2 + 40**2)
    )
    basis = laplacian_eigenbasis(blob, 20)
    desc = normalize_descriptors(wks(basis.eigenvalues, basis.values, 8))
    monkeypatch.setattr("torchfmap._util.checks.available_memory", lambda: solver.solve_bytes(20, 20) - 1)
    monkeypatch.setattr(solver, "build_problem", lambda *a, **k: pytest.fail("the work started"))
    refused = r"k = 20 needs an estimated 0\.0 GiB .*GiB is available\. Fix: a smaller k"
    with pytest.raises(MemoryEstimateError, match=refused) as info:
        solve_fmap(basis, basis, desc, desc)
    assert isinstance(info.value, ParameterError) and isinstance(info.value, MemoryError)
    monkeypatch.undo()
    monkeypatch.setattr("torchfmap._util.checks.available_memory", lambda: None)  # not Linux: nothing refused
    C = solve_fmap(basis, basis, desc, desc)
    assert C.shape == (20, 20) and np.isfinite(C).all()


def test_multiplication_operator_with_a_shared_mass_product(sphere2):
    """Several operators of one basis may share ``B Φ`` (computed once): the same operator."""
    from torchfmap.bases.basis import Basis

    L, B = laplacian(sphere2)  # a mass that is not diagonal: the identity Φᵀ B diag(f) Φ = (f ⊙ BΦ)ᵀ Φ
    basis = laplacian_eigenbasis(sphere2, 12)
    fem = Basis(basis.values, B + 0.1 * abs(L), basis.provenance, stiffness=L)
    f = np.cos(3 * sphere2.vertices[:, 0])
    direct = fem.values.T @ (fem.mass @ (f[:, None] * fem.values))
    np.testing.assert_allclose(multiplication_operator(fem, f), direct, atol=1e-12)
    shared = fem.mass @ fem.values
    np.testing.assert_allclose(multiplication_operator(fem, f, shared), direct, atol=1e-12)
