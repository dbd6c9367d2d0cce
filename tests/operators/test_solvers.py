"""Sparse factorisations (``torchfmap.operators.solvers``): every backend, complex and non-
symmetric systems, the fallback when not SPD, singular matrices, bad arguments."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from torchfmap import ParameterError, available_backends, factorize, laplacian


@pytest.mark.parametrize("backend", available_backends())
def test_factorize_backends_solve_spd(blob, backend):
    L, B = laplacian(blob)
    A = L + B
    rhs = np.random.default_rng(0).normal(size=(blob.n_vertices, 3))
    fac = factorize(A, spd=True, backend=backend)
    assert fac.backend == backend
    x = fac.solve(rhs)
    assert np.linalg.norm(A @ x - rhs) < 1e-10 * np.linalg.norm(rhs)
    assert x.flags.c_contiguous  # callers update solutions in place with C-order BLAS calls
    x1 = fac.solve(rhs[:, 0])
    assert x1.shape == (blob.n_vertices,) and np.allclose(x1, x[:, 0])
    out = np.full_like(rhs, np.nan)  # solved in place: every entry written, the same solution
    assert fac.solve(rhs, out=out) is out
    np.testing.assert_allclose(out, x, rtol=0, atol=1e-12 * np.abs(x).max())
    with pytest.raises(ParameterError, match="C-ordered float64"):
        fac.solve(rhs, out=np.empty((blob.n_vertices, 2)))
    with pytest.raises(ParameterError, match="real"):
        fac.solve(rhs + 1j, out=out)


def test_factorize_complex_and_nonsymmetric(blob):
    L, B = laplacian(blob, scheme="mean_value")
    A = (L + B).astype(complex) + 1j * B
    rhs = np.ones(blob.n_vertices)
    x = factorize(A).solve(rhs)
    assert np.linalg.norm(A @ x - rhs) < 1e-10 * np.linalg.norm(rhs)
    # complex right-hand side on a real matrix
    Ls, Bs = laplacian(blob)
    fac = factorize(Ls + Bs, spd=True)
    z = fac.solve(rhs + 2j * rhs)
    assert np.allclose((Ls + Bs) @ z, rhs + 2j * rhs)


def test_factorize_auto_falls_back_when_not_spd(blob):
    L, B = laplacian(blob)
    A = L - 3.0 * B  # indefinite
    rhs = np.ones(blob.n_vertices)
    fac = factorize(A, spd=True)  # the caller was wrong: auto falls back to LU
    assert fac.backend == "splu"
    assert np.linalg.norm(A @ fac.solve(rhs) - rhs) < 1e-8 * np.linalg.norm(rhs) * 1e3
    for backend in set(available_backends()) - {"splu"}:
        with pytest.raises(ParameterError, match="not positive definite"):
            factorize(A, spd=True, backend=backend)


def test_factorize_bad_arguments(blob):
    L, B = laplacian(blob)
    with pytest.raises(ParameterError, match="unknown solver backend"):
        factorize(L + B, backend="magic")
    with pytest.raises(ParameterError, match="square"):
        factorize(sp.random(4, 5, density=0.5))
    with pytest.raises(ParameterError, match="spd=True"):
        factorize(L + B, backend="cholespy")
    with pytest.raises(ParameterError, match="rows"):
        factorize(L + B, spd=True).solve(np.ones(3))


def test_singular_matrix_is_refused_by_factorize(sphere2):
    """L alone is singular (constants in its kernel): spd=True used to return values ~1e16."""
    from torchfmap import factorize
    from torchfmap.errors import NotPositiveDefiniteError

    L, B = laplacian(sphere2)
    with pytest.raises(NotPositiveDefiniteError, match="singular.*Fix"):
        factorize(L, spd=True)
    x = factorize(L + 1e-3 * B, spd=True).solve(B @ np.ones(sphere2.n_vertices))
    assert np.isfinite(x).all()
