"""Laplacian eigenbasis: orthonormality, eigenvalues, sign convention invariance, bad k."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, laplacian_eigenbasis
from torchfmap.bases import laplacian as eig_module

from .conftest import random_rotation


@pytest.mark.parametrize("dense_limit", [10**6, 10])  # dense eigh and sparse eigsh paths
def test_orthonormal_sorted_and_paths_agree(blob, monkeypatch, dense_limit):
    monkeypatch.setattr(eig_module, "DENSE_LIMIT", dense_limit)
    basis = laplacian_eigenbasis(blob, 20)
    assert np.abs(basis.gram() - np.eye(20)).max() < 1e-10
    lam = basis.eigenvalues
    assert np.all(np.diff(lam) >= -1e-10) and abs(lam[0]) < 1e-8
    W = basis.projected_laplacian()
    assert np.allclose(W, np.diag(lam), atol=1e-8)


def test_sparse_and_dense_give_same_functions(blob, monkeypatch):
    dense = laplacian_eigenbasis(blob, 12).values
    monkeypatch.setattr(eig_module, "DENSE_LIMIT", 10)
    sparse = laplacian_eigenbasis(blob, 12).values
    assert np.abs(dense - sparse).max() < 1e-6  # same signs thanks to the convention


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
