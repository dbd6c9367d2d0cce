"""Eigensolvers (``torchfmap.operators.eigen``): dense, ARPACK and block Lanczos paths, the sign
convention, scale covariance."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from torchfmap import ParameterError, laplacian
from torchfmap.operators import eigen as eig_module
from torchfmap.operators.eigen import fix_signs


@pytest.mark.parametrize("solver", ["arpack", "block"])
def test_sparse_and_dense_give_same_functions(blob, monkeypatch, solver):
    """Both sparse solvers stop at residual ARPACK_TOL·θ: eigenvalues to ~1e-10 relative,
    vectors to ~residual/gap (the blob's first gaps are O(1), so 1e-6 is generous)."""
    L, B = laplacian(blob)
    dense_lam, dense = eig_module.eigenpairs(L, B, 24)
    monkeypatch.setattr(eig_module, "DENSE_LIMIT", 10)
    lam, sparse = eig_module.eigenpairs(L, B, 24, solver=solver)
    assert np.abs(lam[1:] - dense_lam[1:]).max() < 1e-8 * dense_lam[-1]
    simple = [
        i
        for i in range(1, 23)
        if min(dense_lam[i] - dense_lam[i - 1], dense_lam[i + 1] - dense_lam[i]) > 1e-3
    ]
    assert len(simple) > 10
    assert np.abs(dense[:, simple] - sparse[:, simple]).max() < 1e-6  # same signs thanks to the convention


def test_block_lanczos_on_a_known_spectrum_with_multiplicities():
    """A symmetric operator with eigenvalues 1/(l(l+1)+1), multiplicity 2l+1 (the sphere's
    pattern, shift-inverted): the k largest come out to the convergence tolerance, the
    vectors orthonormal and spanning the exact eigenspaces; a second run is identical."""
    rng = np.random.default_rng(0)
    lam = np.concatenate([np.full(2 * deg + 1, deg * (deg + 1.0)) for deg in range(30)])[:600]
    Q, _ = np.linalg.qr(rng.standard_normal((600, 600)))
    A = (Q / (lam + 1.0)) @ Q.T
    k = 36  # l = 0..5 exactly
    theta, Y = eig_module.block_lanczos(lambda X: A @ X, 600, k, block=8)
    np.testing.assert_allclose(theta, 1.0 / (lam[:k] + 1.0), rtol=1e-9)
    np.testing.assert_allclose(Y.T @ Y, np.eye(k), atol=1e-12)
    exact = Q[:, :k]
    assert np.linalg.svd(exact.T @ Y, compute_uv=False).min() > 1 - 1e-9  # same invariant subspace
    theta2, Y2 = eig_module.block_lanczos(lambda X: A @ X, 600, k, block=8)
    np.testing.assert_array_equal(Y, Y2)


def test_block_lanczos_raises_when_not_converged_and_unknown_solver(blob, monkeypatch):
    from torchfmap.errors import ConvergenceError

    monkeypatch.setattr(eig_module, "BLOCK_MAX_CYCLES", 2)
    A = np.diag(1.0 / np.arange(1.0, 201.0))
    with pytest.raises(ConvergenceError, match="solver='arpack'"):
        eig_module.block_lanczos(lambda X: A @ X, 200, 20, block=4, tol=0.0)
    L, B = laplacian(blob)
    with pytest.raises(ParameterError, match="eigensolver"):
        eig_module.eigenpairs(L, B, 10, solver="lobpcg")


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


@pytest.mark.parametrize("alpha", [1e-6, 1e5, 1e12])
def test_eigenpairs_are_scale_covariant(alpha):
    """Scaling a mesh by alpha scales L's eigenvalues by 1/alpha² and the B-orthonormal
    eigenvectors by 1/alpha (cotan L is scale-free, B scales with alpha²). The fixed absolute
    shift used to make cost and result depend on units (wrong maps from 1e8 on)."""
    from torchfmap.operators import eigenpairs

    from ..conftest import bumpy_blob

    mesh = bumpy_blob(4)  # above the dense limit: the shift-invert ARPACK path
    lam, phi = eigenpairs(*laplacian(mesh), 12)
    lam_s, phi_s = eigenpairs(*laplacian(mesh.scaled(alpha)), 12)
    # ARPACK converges each pair to ARPACK_TOL relative, in both runs
    np.testing.assert_allclose(lam_s * alpha**2, lam, rtol=1e-6, atol=1e-8 * lam[-1])
    np.testing.assert_allclose(np.abs(phi_s * alpha), np.abs(phi), atol=1e-4 * np.abs(phi).max())


def test_many_eigenpairs_of_a_large_mesh_warn_of_the_cost_and_still_run(blob, monkeypatch):
    """Past MANY_EIGENPAIRS on a mesh beyond DENSE_LIMIT a CostWarning says what it costs and the
    fix; the pairs are the same as without the warning (limits lowered so the blob crosses them)."""
    import warnings

    from torchfmap import CostWarning

    L, B = laplacian(blob)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CostWarning)  # not at the usual sizes
        lam_quiet, _ = eig_module.eigenpairs(L, B, 12)
    monkeypatch.setattr(eig_module, "DENSE_LIMIT", 10)
    monkeypatch.setattr(eig_module, "MANY_EIGENPAIRS", 8)
    with pytest.warns(CostWarning, match=r"computing 12 eigenpairs of a \d+-vertex mesh.*Fix: a smaller k"):
        lam, _ = eig_module.eigenpairs(L, B, 12)
    assert np.abs(lam[1:] - lam_quiet[1:]).max() < 1e-8 * lam_quiet[-1]
