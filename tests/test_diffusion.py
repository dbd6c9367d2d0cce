"""Heat kernels against scipy.linalg.expm, locality, invariances, real remeshed pairs."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from torchfmap import ParameterError, diffusion_basis, laplacian, load_mesh
from torchfmap.operators.heat import cf_poles, heat_kernels

from .conftest import bumpy_blob, data_path, random_rotation

REL_TIMES = np.array([1e-4, 1e-3, 1e-2, 1e-1])


@pytest.fixture(scope="module")
def setting():
    mesh = bumpy_blob(3)
    L, B = laplacian(mesh)
    seeds = np.array([0, 101, 333])
    times = REL_TIMES * mesh.area
    d = B.diagonal()
    ref = np.stack([sla.expm(-t * (L.toarray() / d[:, None]))[:, seeds] / d[seeds] for t in times])
    return mesh, (L, B), seeds, times, ref


def rel_err(K, ref):
    """Per (time, seed): max |K - ref| / max |ref|."""
    return np.abs(K - ref).max(axis=1) / np.abs(ref).max(axis=1)


@pytest.mark.parametrize(("method", "tol", "bound"), [("krylov", 1e-8, 1e-8), ("rational", 1e-8, 1e-9)])
def test_spectrum_free_methods_match_expm(setting, method, tol, bound):
    mesh, ops, seeds, times, ref = setting
    K = heat_kernels(ops, seeds, times, method, tol=tol)
    assert rel_err(K, ref).max() < bound


def test_krylov_meets_each_tolerance(setting):
    mesh, ops, seeds, times, ref = setting
    for tol in (1e-4, 1e-6, 1e-10):
        assert rel_err(heat_kernels(ops, seeds, times, "krylov", tol=tol), ref).max() < tol


def test_cf_rational_approximation_scalar():
    x = -np.concatenate([np.linspace(0, 40, 4001), np.logspace(-6, 6, 2001)])
    for n in (8, 12):
        z, c, level = cf_poles(n)
        r = np.array([np.sum(c / (xi - z)) for xi in x])
        assert np.abs(r.imag).max() < 1e-12
        assert np.abs(r.real - np.exp(x)).max() < 1.5 * level
    assert cf_poles(12)[2] < 1e-11
    with pytest.raises(ParameterError, match="CF order"):
        cf_poles(16)


def test_backward_euler_is_first_order(setting):
    mesh, ops, seeds, times, ref = setting
    errs = [
        rel_err(heat_kernels(ops, seeds, times[2:3], "backward_euler", n_steps=n), ref[2:3]).max()
        for n in (4, 16, 64)
    ]
    assert errs[0] > errs[1] > errs[2]
    assert 2.5 < errs[1] / errs[2] < 6  # ~4x per 4x more steps: first order


def test_spectral_with_full_spectrum_is_exact_truncated_is_not(setting):
    mesh, ops, seeds, times, ref = setting
    full = heat_kernels(ops, seeds, times, "spectral", n_eigen=mesh.n_vertices)
    assert rel_err(full, ref).max() < 1e-8
    truncated = heat_kernels(ops, seeds, times, "spectral", n_eigen=50)
    err = rel_err(truncated, ref).max(axis=1)
    assert err[0] > 0.1 and err[-1] < 1e-6  # Eq. 1 truncation fails at small t only


def test_local_mode_matches_global(setting):
    mesh, ops, seeds, times, ref = setting
    for local in (True, "auto"):
        K = heat_kernels(ops, seeds, times, "krylov", tol=1e-8, local=local, vertices=mesh.vertices)
        assert rel_err(K, ref).max() < 1e-7
    # the local solve really is local at the smallest time
    K = heat_kernels(ops, seeds, times[:1], local=True, vertices=mesh.vertices)
    assert (np.abs(K[0]) > 0).mean() < 0.3


def test_kernel_properties(setting):
    mesh, (L, B), seeds, times, ref = setting
    K = heat_kernels((L, B), seeds, times, tol=1e-10)
    # delta kernel: integrates to one (closed mesh), symmetric K_t(p, q) = K_t(q, p)
    assert np.allclose(np.ones(mesh.n_vertices) @ (B @ K[2]), 1.0, atol=1e-8)
    assert np.allclose(K[2][seeds], K[2][seeds].T, rtol=1e-7)
    indicator = heat_kernels((L, B), seeds, times, kernel="indicator", tol=1e-10)
    assert np.allclose(indicator, K * B.diagonal()[seeds], rtol=1e-7, atol=1e-12)


def test_scale_invariance_relative_times(setting):
    mesh, ops, seeds, times, ref = setting
    alpha = 3.0
    a = diffusion_basis(mesh, seeds, REL_TIMES[1:], local=False).values
    b = diffusion_basis(mesh.scaled(alpha), seeds, REL_TIMES[1:], local=False).values
    assert np.abs(alpha**2 * b - a).max() < 1e-6 * np.abs(a).max()  # delta kernels scale by 1/alpha^2


def test_rigid_motion_and_permutation_invariance(setting, rng):
    mesh, ops, seeds, times, ref = setting
    base = diffusion_basis(mesh, seeds, REL_TIMES[1:], local=False).values
    moved = mesh.copy(mesh.vertices @ random_rotation(rng).T + 4.0)
    assert (
        np.abs(diffusion_basis(moved, seeds, REL_TIMES[1:], local=False).values - base).max()
        < 1e-6 * base.max()
    )
    perm = rng.permutation(mesh.n_vertices)
    inv = np.argsort(perm)
    permuted = diffusion_basis(mesh.permuted(perm), inv[seeds], REL_TIMES[1:], local=False).values
    assert np.abs(permuted - base[perm]).max() < 1e-6 * base.max()


def test_column_order_and_provenance(setting):
    mesh, ops, seeds, times, ref = setting
    basis = diffusion_basis(mesh, seeds, [1e-2, 1e-3], local=False)  # given unsorted
    assert [c.time for c in basis.columns] == [1e-3] * 3 + [1e-2] * 3  # small to large
    assert [c.seed for c in basis.columns] == seeds.tolist() * 2


@pytest.mark.parametrize("bad", [0.0, -1e-3, np.nan])
def test_bad_times(setting, bad):
    mesh, ops, seeds, times, ref = setting
    with pytest.raises(ParameterError, match="times must be finite and > 0"):
        diffusion_basis(mesh, seeds, [1e-3, bad])
    with pytest.raises(ParameterError, match="> 0"):
        heat_kernels(ops, seeds, [bad])


def test_mean_value_weights_rejected(setting):
    mesh, ops, seeds, times, ref = setting
    with pytest.raises(ParameterError, match="symmetric Laplacian"):
        heat_kernels(laplacian(mesh, kind="mean_value"), seeds, times)


def test_remeshed_pose_pair_agrees_through_ground_truth():
    """cat0 and cat1 have different connectivity: kernels at corresponding points agree."""
    folder = data_path("tosca5k_dev")
    m0, m1 = load_mesh(folder / "cat0.off"), load_mesh(folder / "cat1.off")
    v0 = np.loadtxt(folder / "corres" / "cat0.vts", dtype=int) - 1
    v1 = np.loadtxt(folder / "corres" / "cat1.vts", dtype=int) - 1
    rows = np.array([100, 2000, 4000])
    k0 = diffusion_basis(m0, v0[rows], [1e-2], tol=1e-6).values[v0]
    k1 = diffusion_basis(m1, v1[rows], [1e-2], tol=1e-6).values[v1]
    # delta kernels divide by the area: compare the scale-free t|M| K
    k0, k1 = k0 * m0.area, k1 * m1.area
    for j in range(len(rows)):
        corr = np.corrcoef(k0[:, j], k1[:, j])[0, 1]
        rel = np.linalg.norm(k0[:, j] - k1[:, j]) / np.linalg.norm(k0[:, j])
        assert corr > 0.95 and rel < 0.3, (corr, rel)


def test_a_kernel_does_not_depend_on_the_seeds_solved_with_it():
    """Seeds are solved in blocks, but each column stops at its own convergence, so a kernel is
    the same alone or among others (up to round-off of multi-column solves, far below tol);
    caches of kernels (``PreparedShape.kernels``) then give the same maps in any pair order."""
    from torchfmap.data import demo_pair

    mesh = demo_pair()[0]
    ops = laplacian(mesh)
    t = [0.01 * mesh.area]
    seeds = [5, 300, 900, 1500, 2100, 2500]
    together = heat_kernels(ops, seeds, t, tol=1e-4)[0]
    for j, seed in enumerate(seeds):
        alone = heat_kernels(ops, [seed], t, tol=1e-4)[0][:, 0]
        scale = np.abs(alone).max()
        assert np.abs(together[:, j] - alone).max() <= 1e-10 * scale
