"""B-orthonormalisation (``torchfmap.bases.orthonormalize``): MGS and Cholesky-QR2, dropped columns
and their provenance, pairs of bases."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import Basis, ParameterError, laplacian
from torchfmap.bases import Column, cholqr, mgs, orthonormalize

from ..conftest import bumpy_blob


@pytest.fixture(scope="module")
def stack_input(request):
    mesh = bumpy_blob(3)
    L, B = laplacian(mesh)
    rng = np.random.default_rng(3)
    F = rng.normal(size=(mesh.n_vertices, 12))
    F[:, 4] = 2 * F[:, 0] - F[:, 2]  # exactly dependent
    F[:, 9] = F[:, 7] + 1e-13 * rng.normal(size=mesh.n_vertices)  # numerically dependent
    return mesh, (L, B), F


@pytest.mark.parametrize("fn", [mgs, cholqr])
def test_orthonormal_and_drops_dependent_columns(stack_input, fn):
    mesh, (L, B), F = stack_input
    Q, kept = fn(F, B)
    assert np.abs(Q.T @ B @ Q - np.eye(Q.shape[1])).max() < 1e-10
    assert kept.tolist() == [0, 1, 2, 3, 5, 6, 7, 8, 10, 11]
    # span preserved: every input column (dropped ones included) is reproduced
    coeffs = Q.T @ (B @ F)
    assert np.abs(Q @ coeffs - F).max() < 1e-8 * np.abs(F).max()


def test_mgs_and_cholqr_agree_on_span(stack_input):
    mesh, (L, B), F = stack_input
    Q1, k1 = mgs(F, B)
    Q2, k2 = cholqr(F, B)
    assert np.array_equal(k1, k2)
    M = Q1.T @ B @ Q2  # orthogonal iff the spans agree
    assert np.abs(M.T @ M - np.eye(len(k1))).max() < 1e-10
    # processing order is kept: the triangular structure makes the columns agree up to sign
    assert np.allclose(np.abs(np.diag(M)), 1.0, atol=1e-8)


def test_orthonormalize_records_provenance(stack_input):
    mesh, (L, B), F = stack_input
    prov = [Column("custom", seed=i) for i in range(F.shape[1])]
    ortho = orthonormalize(Basis(F, B, prov), scheme="mgs")
    assert ortho.orthonormal and ortho.k == 10
    assert [c.seed for c in ortho.dropped] == [4, 9]
    assert [c.seed for c in ortho.columns] == [0, 1, 2, 3, 5, 6, 7, 8, 10, 11]
    # orthonormalising again drops nothing more
    assert orthonormalize(ortho).k == 10


@pytest.mark.parametrize("method", ["mgs", "cholqr"])
def test_pair_drops_the_same_columns_on_both_shapes(stack_input, method):
    from torchfmap import orthonormalize_pair

    mesh, (L, B), F = stack_input
    G = F.copy()
    G[:, 4] = np.random.default_rng(9).normal(size=mesh.n_vertices)  # independent on y only
    G[:, 6] = G[:, 1] + G[:, 3]  # dependent on y only
    prov = [Column("custom", seed=i) for i in range(F.shape[1])]
    alone = orthonormalize(Basis(F, B, prov), method), orthonormalize(Basis(G, B, prov), method)
    assert [c.seed for c in alone[0].dropped] == [4, 9] and [c.seed for c in alone[1].dropped] == [6, 9]
    bx, by = orthonormalize_pair(Basis(F, B, prov), Basis(G, B, prov), method)
    for b, inputs in ((bx, F), (by, G)):
        assert [c.seed for c in b.dropped] == [4, 6, 9]
        assert np.abs(b.values.T @ B @ b.values - np.eye(b.k)).max() < 1e-10
        kept = [c.seed for c in b.columns]
        # column i is built from the same inputs: Q = F_kept R with R upper triangular
        R = b.values.T @ (B @ inputs[:, kept])
        assert np.abs(np.tril(R, -1)).max() < 1e-8 * np.abs(R).max()
        assert np.abs(b.values @ R - inputs[:, kept]).max() < 1e-8 * np.abs(inputs).max()
    with pytest.raises(ParameterError, match="same columns"):
        orthonormalize_pair(Basis(F, B, prov), Basis(G[:, :5], B, prov[:5]))


def test_bad_orthonormalisation_arguments(stack_input):
    mesh, (L, B), F = stack_input
    basis = Basis(F, B)
    with pytest.raises(ParameterError, match="unknown orthonormalisation scheme"):
        orthonormalize(basis, scheme="householder")
    with pytest.raises(ParameterError, match="cholqr resolves linear dependence only down to"):
        orthonormalize(basis, scheme="cholqr", tol=1e-10)
    with pytest.raises(ParameterError, match=r"tol must be in \(0, 1\)"):
        orthonormalize(basis, tol=0)


def test_mgs_by_panels_drops_what_column_by_column_gram_schmidt_drops():
    """Wider than several panels (the block passes run): dependences that reach back across
    panels are found, each column is judged by its remainder against *all* earlier kept
    columns, and orthogonality holds to round-off (the contract of the column-by-column
    scheme, whose reference runs here in the test)."""
    from torchfmap.bases.orthonormalize import MGS_PANEL

    mesh = bumpy_blob(3)
    _, B = laplacian(mesh)
    rng = np.random.default_rng(5)
    K = 3 * MGS_PANEL + 5
    F = rng.normal(size=(mesh.n_vertices, K))
    F[:, MGS_PANEL + 3] = F[:, 0] - 3 * F[:, MGS_PANEL - 1]  # on two columns of panel 0
    F[:, 2 * MGS_PANEL + 1] = F[:, 5] + F[:, MGS_PANEL + 7] + 1e-11 * rng.normal(size=mesh.n_vertices)
    F[:, 3 * MGS_PANEL] = F[:, 2 * MGS_PANEL + 2] + 1e-5 * rng.normal(size=mesh.n_vertices)  # independent
    tol = 1e-8
    Q, kept = mgs(F, B, tol)
    # reference: classical Gram-Schmidt twice, one column at a time, dense
    Bd = B.toarray()
    ref_q, ref_kept = np.zeros((mesh.n_vertices, 0)), []
    for j in range(K):
        v = F[:, j].copy()
        norm0 = np.sqrt(v @ Bd @ v)
        for _ in range(2):
            v -= ref_q @ (ref_q.T @ (Bd @ v))
        norm = np.sqrt(v @ Bd @ v)
        if norm > tol * norm0:
            ref_q = np.column_stack([ref_q, v / norm])
            ref_kept.append(j)
    assert kept.tolist() == ref_kept
    assert MGS_PANEL + 3 not in ref_kept and 2 * MGS_PANEL + 1 not in ref_kept and 3 * MGS_PANEL in ref_kept
    # orthonormal to round-off: a few ulps times the number of columns
    assert np.abs(Q.T @ (B @ Q) - np.eye(len(kept))).max() < 100 * K * np.finfo(float).eps
    # the same columns up to round-off amplified by the smallest kept remainder (1e-5)
    assert np.abs(Q - ref_q).max() < K * np.finfo(float).eps / 1e-5 * np.abs(ref_q).max()


def test_a_lumped_mass_is_applied_elementwise_whatever_its_form():
    """A diagonal mass given as ``(V,)``, as a sparse diagonal matrix or as a dense one gives the
    same columns (the product is elementwise, no sparse product); a mass with off-diagonal
    entries keeps the sparse product and still gives B-orthonormal columns."""
    import scipy.sparse as sp

    from torchfmap.bases.orthonormalize import mgs

    rng = np.random.default_rng(0)
    F = rng.normal(size=(60, 8))
    d = rng.uniform(0.5, 2.0, size=60)
    ref = mgs(F, d)
    for form in (sp.diags(d), sp.diags(d).tocsr(), np.diag(d)):
        Q, kept = mgs(F, form)
        np.testing.assert_array_equal(kept, ref[1])
        np.testing.assert_allclose(Q, ref[0], rtol=0, atol=1e-12)
    offdiag = sp.diags(d) + 0.1 * sp.diags(np.ones(59), 1) + 0.1 * sp.diags(np.ones(59), -1)
    Q, _ = mgs(F, offdiag)
    np.testing.assert_allclose(Q.T @ (offdiag @ Q), np.eye(Q.shape[1]), atol=1e-12)
