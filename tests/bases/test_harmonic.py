"""Harmonic basis (``torchfmap.bases.harmonic``): interpolation, partition of unity, maximum
principle, one factorisation."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import Mesh, SeedError, farthest_point_sampling, harmonic_basis, laplacian
from torchfmap.bases import harmonic_functions
from torchfmap.operators import solvers

from ..conftest import bumpy_blob


@pytest.fixture(scope="module")
def seeds_blob(request):
    mesh = bumpy_blob(3)
    return mesh, farthest_point_sampling(mesh, 12, metric="euclidean")


@pytest.mark.parametrize("kind", ["cotan", "robust", "mean_value"])
def test_interpolation_partition_of_unity(seeds_blob, kind):
    mesh, seeds = seeds_blob
    psi = harmonic_basis(mesh, seeds, scheme=kind).values
    assert np.array_equal(psi[seeds], np.eye(len(seeds)))  # exactly delta_ij
    assert np.abs(psi.sum(axis=1) - 1).max() < 1e-10
    assert np.linalg.matrix_rank(psi) == len(seeds)


@pytest.mark.parametrize("kind", ["robust", "mean_value"])
def test_maximum_principle_nonnegative_weights(seeds_blob, kind):
    mesh, seeds = seeds_blob
    psi = harmonic_basis(mesh, seeds, scheme=kind).values
    assert psi.min() >= -1e-12 and psi.max() <= 1 + 1e-12
    assert np.array_equal(np.argmax(psi, axis=0), seeds)  # each peaks at its own seed


def test_cotan_on_delaunay_sphere_obeys_maximum_principle(sphere3):
    seeds = farthest_point_sampling(sphere3, 10, metric="euclidean")
    psi = harmonic_basis(sphere3, seeds).values
    assert psi.min() >= -1e-12 and psi.max() <= 1 + 1e-12
    assert np.array_equal(np.argmax(psi, axis=0), seeds)


def test_harmonic_means_discrete_laplace_zero_off_seeds(seeds_blob):
    mesh, seeds = seeds_blob
    L, _ = laplacian(mesh, scheme="mean_value")
    psi = harmonic_functions(L, seeds)
    free = np.setdiff1d(np.arange(mesh.n_vertices), seeds)
    assert np.abs((L @ psi)[free]).max() < 1e-10


def test_one_factorisation_for_all_seeds(seeds_blob, monkeypatch):
    mesh, seeds = seeds_blob
    calls = []
    original = solvers.factorize

    def counting(*args, **kwargs):
        calls.append(kwargs.get("spd"))
        return original(*args, **kwargs)

    monkeypatch.setattr("torchfmap.bases.harmonic.factorize", counting)
    harmonic_basis(mesh, seeds)
    harmonic_basis(mesh, seeds, scheme="mean_value")
    assert calls == [True, False]  # Cholesky for cotan, LU for non-symmetric mean-value weights


def test_components_need_seeds():
    from torchfmap.data import icosphere

    s = icosphere(2)
    two = Mesh(
        np.vstack([s.vertices, s.vertices + 5.0]),
        np.vstack([s.faces, s.faces + s.n_vertices]),
        allow_components=True,
    )
    with pytest.raises(SeedError, match=r"1 connected component\(s\) have no seed .*vertex 162"):
        harmonic_basis(two, [0, 5, 9])
    psi = harmonic_basis(two, [0, 5, 170]).values
    assert np.allclose(psi.sum(axis=1), 1)
    assert np.allclose(psi[s.n_vertices :, 2], 1)  # the only seed of the second sphere


def test_provenance(seeds_blob):
    mesh, seeds = seeds_blob
    basis = harmonic_basis(mesh, seeds)
    assert [c.seed for c in basis.columns] == seeds.tolist()
    assert {c.family for c in basis.columns} == {"harmonic"}
