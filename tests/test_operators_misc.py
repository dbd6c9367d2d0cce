"""Geodesics, sparse solver backends and scipy <-> torch conversion."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from torchfmap import (
    GeodesicSolver,
    ParameterError,
    SeedError,
    available_backends,
    factorize,
    laplacian,
    scipy_to_torch,
    torch_to_scipy,
)
from torchfmap.data import icosphere
from torchfmap.operators import geodesic


@pytest.fixture(scope="module")
def sphere4():
    return icosphere(4)


def test_heat_geodesics_on_sphere(sphere4):
    solver = GeodesicSolver(sphere4)
    exact = np.arccos(np.clip(sphere4.vertices @ sphere4.vertices[0], -1, 1))
    d = solver.distance(0)
    assert d[0] == pytest.approx(0.0, abs=1e-6)
    assert np.abs(d - exact).max() < 0.03 * np.pi
    rows = solver.distances([0, 10, 20])
    assert rows.shape == (3, sphere4.n_vertices) and np.allclose(rows[0], d)
    nearest = solver.distance_to_set([0, 10, 20])
    assert np.abs(nearest - rows.min(axis=0)).max() < 0.03 * np.pi


def test_distance_matrix_small_and_guard(sphere4, monkeypatch):
    small = icosphere(1)
    D = GeodesicSolver(small).distance_matrix()
    assert D.shape == (42, 42) and np.allclose(D, D.T) and np.allclose(np.diag(D), 0, atol=1e-6)
    monkeypatch.setattr(geodesic, "FULL_MATRIX_LIMIT", 100)
    with pytest.raises(ParameterError, match=r"full distance matrix .* `distances\(rows\)`"):
        GeodesicSolver(sphere4).distance_matrix()


def test_geodesic_bad_sources(sphere4):
    solver = GeodesicSolver(icosphere(1))
    with pytest.raises(SeedError, match="out of range"):
        solver.distance(42)
    with pytest.raises(SeedError, match="duplicates"):
        solver.distances([1, 2, 1])
    with pytest.raises(SeedError, match="empty"):
        solver.distances([])
    with pytest.raises(SeedError, match="integer"):
        solver.distances([0.5])


@pytest.mark.parametrize("backend", available_backends())
def test_factorize_backends_solve_spd(blob, backend):
    L, B = laplacian(blob)
    A = L + B
    rhs = np.random.default_rng(0).normal(size=(blob.n_vertices, 3))
    fac = factorize(A, spd=True, backend=backend)
    assert fac.backend == backend
    x = fac.solve(rhs)
    assert np.linalg.norm(A @ x - rhs) < 1e-10 * np.linalg.norm(rhs)
    x1 = fac.solve(rhs[:, 0])
    assert x1.shape == (blob.n_vertices,) and np.allclose(x1, x[:, 0])


def test_factorize_complex_and_nonsymmetric(blob):
    L, B = laplacian(blob, kind="mean_value")
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


def test_scipy_torch_round_trip(blob):
    L, _ = laplacian(blob)
    t = scipy_to_torch(L)
    assert t.dtype == torch.float64 and t.is_sparse
    assert abs(torch_to_scipy(t) - L).max() == 0
    x = np.random.default_rng(0).normal(size=blob.n_vertices)
    assert np.allclose((t @ torch.from_numpy(x)).numpy(), L @ x)
    t32 = scipy_to_torch(L, dtype=torch.float32, layout=torch.sparse_csr)
    assert t32.dtype == torch.float32 and t32.layout == torch.sparse_csr
    assert abs(torch_to_scipy(t32) - L).max() < 1e-4 * abs(L).max()
    assert abs(torch_to_scipy(t.to_dense()) - L).max() == 0
