"""B-orthonormalisation (MGS and Cholesky-QR2), the Basis type, support statistics."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import Basis, ParameterError, basis_stack, farthest_point_sampling, laplacian
from torchfmap.bases import Column, CorruptFileError, cholqr, mgs, orthonormalize, support_fraction

from .conftest import bumpy_blob


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


def test_stack_order_and_orthonormality(blob):
    seeds = farthest_point_sampling(blob, 8, metric="euclidean")
    stack = basis_stack(blob, seeds, times=[1e-2, 1e-3], n_eigen=20)
    kinds = [c.kind for c in stack.provenance]
    n_diff = 16
    assert kinds == ["diffusion"] * n_diff + ["harmonic"] * 8 + ["laplacian"] * 20
    assert [c.time for c in stack.provenance[:n_diff]] == [1e-3] * 8 + [1e-2] * 8
    assert np.abs(stack.gram() - np.eye(stack.k)).max() < 1e-10
    # the constant eigenfunction lies in the span of the harmonic functions (they sum to 1)
    assert any(c.kind == "laplacian" and c.index == 0 for c in stack.dropped)
    W = stack.projected_laplacian()
    assert W.shape == (stack.k, stack.k) and np.allclose(W, W.T)


def test_project_reconstruct_round_trip(blob):
    seeds = farthest_point_sampling(blob, 10, metric="euclidean")
    basis = basis_stack(blob, seeds, times=[1e-2])
    f = basis.values @ np.arange(basis.k, dtype=float)
    assert np.allclose(basis.project(f), np.arange(basis.k))
    assert np.allclose(basis.reconstruct(basis.project(f)), f)
    raw = basis_stack(blob, seeds, times=[1e-2], harmonic=False)
    nonorth = Basis(raw.values * 3.0 + 0.1 * raw.values[:, :1], raw.mass)
    target = nonorth.values[:, 2]
    assert np.allclose(nonorth.reconstruct(nonorth.least_squares(target)), target)
    with pytest.raises(ParameterError, match="rows"):
        basis.reconstruct(np.ones(basis.k + 1))


def test_save_load_round_trip_and_corruption(blob, tmp_path):
    seeds = farthest_point_sampling(blob, 6, metric="euclidean")
    basis = basis_stack(blob, seeds, times=[1e-2], n_eigen=5)
    path = basis.save(tmp_path / "basis.npz")
    back = Basis.load(path)
    assert np.array_equal(back.values, basis.values) and back.orthonormal
    assert back.provenance == basis.provenance
    assert abs(back.mass - basis.mass).max() == 0 and abs(back.stiffness - basis.stiffness).max() == 0
    assert [p.name for p in tmp_path.iterdir()] == ["basis.npz"]  # atomic: no temp file left
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # truncated
    with pytest.raises(CorruptFileError, match="rebuild"):
        Basis.load(path)
    # altered values inside a valid container
    basis.save(path)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["values"] = arrays["values"] + 1e-9
    np.savez(path, **arrays)
    with pytest.raises(CorruptFileError, match="checksum"):
        Basis.load(path)


def test_support_fraction_by_hand():
    f = np.array([[1.0, 0.0], [0.5, 0.0], [1e-4, 2.0], [0.0, -1.0]])
    assert support_fraction(f, eps=1e-3).tolist() == [0.5, 0.5]
    assert support_fraction(f[:, 0], eps=1e-5) == 0.75
    mass = np.diag([1.0, 1.0, 2.0, 4.0])
    assert np.allclose(support_fraction(f, eps=1e-3, mass=mass), [2 / 8, 6 / 8])
