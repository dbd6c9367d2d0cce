"""Laplacian eigenbasis: orthonormality, eigenvalues, sign convention invariance, bad k."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, laplacian, laplacian_eigenbasis
from torchfmap.operators import eigen as eig_module

from .conftest import random_rotation


@pytest.mark.parametrize(
    "dense_limit, solver", [(10**6, "auto"), (10, "arpack"), (10, "block")]
)  # dense eigh, sparse eigsh and block Lanczos paths
def test_orthonormal_sorted_and_paths_agree(blob, monkeypatch, dense_limit, solver):
    monkeypatch.setattr(eig_module, "DENSE_LIMIT", dense_limit)
    monkeypatch.setattr(eig_module, "BLOCK_MIN_WORK", 0 if solver == "block" else 10**18)
    basis = laplacian_eigenbasis(blob, 20)
    assert np.abs(basis.gram() - np.eye(20)).max() < 1e-10
    lam = basis.eigenvalues
    assert np.all(np.diff(lam) >= -1e-10) and abs(lam[0]) < 1e-8
    W = basis.projected_laplacian()
    # the eigenvalues are the vectors' Rayleigh quotients: W's diagonal to round-off
    np.testing.assert_allclose(np.diag(W), lam, rtol=1e-12, atol=1e-12 * lam.max())
    # off the diagonal, the sparse solvers' vectors carry their residual: ARPACK_TOL relative
    # to the shift-inverted Ritz value 1/λ, i.e. errors of order ARPACK_TOL·λ² in W (x100 for the
    # constants of the bound); the dense path is exact to round-off
    tol = 1e-12 * lam.max() if dense_limit > 10 else 100 * eig_module.ARPACK_TOL * lam.max() ** 2
    np.testing.assert_allclose(W, np.diag(lam), atol=tol)


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


def test_sign_convention_invariant_under_motion_and_permutation(blob, rng):
    base = laplacian_eigenbasis(blob, 12)
    gaps = np.diff(base.eigenvalues)
    simple = [i for i in range(1, 11) if gaps[i - 1] > 1e-3 and gaps[i] > 1e-3]  # non-degenerate
    assert len(simple) >= 5
    moved = laplacian_eigenbasis(blob.copy(blob.vertices @ random_rotation(rng).T), 12)
    assert np.abs(moved.values[:, simple] - base.values[:, simple]).max() < 1e-6
    perm = rng.permutation(blob.n_vertices)
    permuted = laplacian_eigenbasis(blob.permuted(perm), 12)
    assert np.abs(permuted.values[:, simple] - base.values[perm][:, simple]).max() < 1e-6


def test_eigenvalues_survive_save_load(blob, tmp_path):
    from torchfmap import Basis

    basis = laplacian_eigenbasis(blob, 6)
    back = Basis.load(basis.save(tmp_path / "eig.npz"))
    assert np.array_equal(back.eigenvalues, basis.eigenvalues)


def test_k_out_of_range(blob):
    with pytest.raises(ParameterError, match=r"k must be in \[1, 642\].*k=643"):
        laplacian_eigenbasis(blob, 643)
    with pytest.raises(ParameterError, match="k must be"):
        laplacian_eigenbasis(blob, 0)


def test_mean_value_rejected(blob):
    from torchfmap import laplacian

    with pytest.raises(ParameterError, match="symmetric"):
        laplacian_eigenbasis(blob, 5, operators=laplacian(blob, kind="mean_value"))
