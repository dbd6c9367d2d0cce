"""Shared input checks (``torchfmap._util.checks``): symmetry tolerance, lumped mass, vertex indices
(also through every basis builder), seeds on every component."""

from __future__ import annotations

import os

import numpy as np
import pytest
import scipy.sparse as sp

from torchfmap import Mesh, ParameterError, SeedError, basis_stack, diffusion_basis, harmonic_basis, laplacian
from torchfmap._util.checks import (
    check_lumped_mass,
    check_symmetric,
    check_vertex_indices,
    is_symmetric,
    lumped_diagonal,
    symmetry_tolerance,
)
from torchfmap.data import icosphere
from torchfmap.seeds import check_seeds_cover_components


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_symmetry_rule_is_scale_free_and_separates_kinds(blob, scale):
    for kind in ("cotan", "robust"):
        L = laplacian(blob.scaled(scale), kind)[0] * scale
        assert is_symmetric(L)
        check_symmetric(L, "test")
    L_mv = laplacian(blob, "mean_value")[0]
    assert not is_symmetric(L_mv)
    with pytest.raises(ParameterError, match="symmetric Laplacian.*Fix:"):
        check_symmetric(L_mv, "heat kernels")


def test_symmetry_rule_accepts_round_off_rejects_more(blob):
    L = sp.csr_matrix(laplacian(blob)[0])
    tol = symmetry_tolerance(L)
    m = np.diff(L.indptr).max()
    assert tol == pytest.approx(8 * m * np.finfo(float).eps * abs(L).max())
    i, j = L.nonzero()
    off = np.flatnonzero(i != j)[0]
    E = sp.csr_matrix(([1.0], ([i[off]], [j[off]])), shape=L.shape)
    assert is_symmetric(L + 0.5 * tol * E)  # round-off-sized asymmetry
    assert not is_symmetric(L + 2.0 * tol * E)
    assert is_symmetric(L.toarray()) and is_symmetric(sp.csr_matrix(L.shape))


def test_lumped_mass_one_rule(blob):
    B = laplacian(blob, mass="voronoi")[1]
    assert np.array_equal(lumped_diagonal(B), B.diagonal())
    assert lumped_diagonal(laplacian(blob, mass="fem")[1]) is None
    # explicitly stored zeros (off the diagonal, or a zero-mass vertex) do not matter
    d = np.array([1.0, 0.0, 2.0])
    stored = sp.csr_matrix((np.array([1.0, 0.0, 0.0, 2.0]), ([0, 0, 1, 2], [0, 1, 1, 2])), shape=(3, 3))
    assert np.array_equal(lumped_diagonal(stored), d)
    assert np.array_equal(lumped_diagonal(np.diag(d)), d)
    with pytest.raises(ParameterError, match="lumped.*Fix: .*voronoi"):
        check_lumped_mass(laplacian(blob, mass="fem")[1])


def test_vertex_index_messages_name_the_fix():
    for bad in ([], [[1, 2]], [0.5], [7], [1, 1]):
        with pytest.raises(SeedError, match="Fix:"):
            check_vertex_indices(bad, 5, "seeds")
    assert check_vertex_indices([3.0, 1], 5).dtype == np.int64


def test_check_vertex_indices():
    np.testing.assert_array_equal(check_vertex_indices([3, 1], 5), [3, 1])
    np.testing.assert_array_equal(check_vertex_indices(np.array([2.0, 4.0]), 5), [2, 4])
    for bad, msg in (
        ([1, 1], "duplicates"),
        ([], "empty"),
        ([0.5], "integer"),
        ([[0, 1]], "1-D"),
        ([5], "out of range"),
    ):
        with pytest.raises(SeedError, match=msg):
            check_vertex_indices(bad, 5)


def test_check_seeds_cover_components():
    a, b = icosphere(1), icosphere(1)
    two = Mesh(
        np.vstack([a.vertices, b.vertices + 3.0]),
        np.vstack([a.faces, b.faces + a.n_vertices]),
        validate=False,
    )
    check_seeds_cover_components(two, np.array([0, a.n_vertices]))  # one seed per component: fine
    with pytest.raises(SeedError, match="1 connected component\\(s\\) have no seed"):
        check_seeds_cover_components(two, np.array([0, 1]))


@pytest.mark.parametrize("build", [harmonic_basis, diffusion_basis, basis_stack])
def test_duplicate_out_of_range_and_empty_seeds(blob, build):
    with pytest.raises(SeedError, match=r"duplicates \[5\].*np.unique"):
        build(blob, [1, 5, 5])
    with pytest.raises(SeedError, match=r"\[642\] are out of range .*0-based"):
        build(blob, [0, 642])
    with pytest.raises(SeedError, match="empty"):
        build(blob, [])
    with pytest.raises(SeedError, match="integer"):
        build(blob, [0.5, 2.0])


def test_a_computation_beyond_the_available_memory_is_refused_before_any_work(monkeypatch):
    """A mesh and k whose eigenpairs would not fit (e.g. a 2M-vertex scan on a small machine, or
    k=2000) are refused at once with the estimate and the fix, instead of swapping for hours."""
    import time

    import torchfmap._util.checks as checks
    from torchfmap.bases.prepared import prepare_shape
    from torchfmap.data import icosphere
    from torchfmap.operators import eigenpairs, laplacian

    mesh = icosphere(3)  # 642 vertices
    L, B = laplacian(mesh)
    need = mesh.n_vertices * (checks.BYTES_PER_VERTEX + 8 * checks.EIGEN_VECTORS * 100)
    monkeypatch.setattr(checks, "available_memory", lambda: need - 1)
    start = time.perf_counter()
    with pytest.raises(
        ParameterError, match=r"642 vertices and 100 eigenpairs need about .* GiB.*Fix: decimate"
    ):
        eigenpairs(L, B, 100)
    with pytest.raises(ParameterError, match="preparing .*Fix: decimate"):
        prepare_shape(mesh, 100)
    assert time.perf_counter() - start < 1.0  # refused before the work
    monkeypatch.setattr(checks, "available_memory", lambda: need)
    assert eigenpairs(L, B, 100)[1].shape == (642, 100)
    monkeypatch.setattr(checks, "available_memory", lambda: None)  # not Linux: no estimate, no refusal
    assert prepare_shape(mesh, 10).n_eigen == 10
    monkeypatch.undo()
    if os.path.exists("/proc/meminfo"):
        assert 0 < checks.available_memory() < os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") + 1
