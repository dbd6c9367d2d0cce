"""Heat kernels (``torchfmap.operators.heat``) against ``scipy.linalg.expm`` and the spectral
exponential: every method, locality, tolerances, a kernel independent of the seeds solved with
it."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from torchfmap import ParameterError, available_backends, basis_stack, diffusion_basis, laplacian
from torchfmap.operators import heat_apply
from torchfmap.operators.heat import cf_poles, heat_kernels


def rel_err(K, ref):
    """Per (time, seed): max |K - ref| / max |ref|."""
    return np.abs(K - ref).max(axis=1) / np.abs(ref).max(axis=1)


@pytest.mark.parametrize(("method", "tol", "bound"), [("krylov", 1e-8, 1e-8), ("rational", 1e-8, 1e-9)])
def test_spectrum_free_methods_match_expm(heat_setting, method, tol, bound):
    mesh, ops, seeds, times, ref = heat_setting
    K = heat_kernels(ops, seeds, times, method, tol=tol)
    assert rel_err(K, ref).max() < bound


@pytest.mark.parametrize("backend", available_backends())
def test_krylov_matches_expm_on_every_backend(heat_setting, backend, monkeypatch):
    """Multi-column Krylov blocks on each sparse solver: SuperLU (the fallback where no
    Cholesky package is installed) returns Fortran-ordered solutions, which the in-place
    recurrence must not leave untouched."""
    import torchfmap.operators.krylov as krylov

    mesh, ops, seeds, times, ref = heat_setting
    real = krylov.factorize
    monkeypatch.setattr(krylov, "factorize", lambda a, spd=False, **kw: real(a, spd=spd, backend=backend))
    assert rel_err(heat_kernels(ops, seeds, times, "krylov", tol=1e-8), ref).max() < 1e-8


def test_krylov_meets_each_tolerance(heat_setting):
    mesh, ops, seeds, times, ref = heat_setting
    for tol in (1e-4, 1e-6, 1e-10):
        assert rel_err(heat_kernels(ops, seeds, times, "krylov", tol=tol), ref).max() < tol


def test_kept_factorisations_are_reused_and_change_nothing(heat_setting, monkeypatch):
    """A caller's ``factors`` dict is filled on the first call and read on the next: the same
    kernels, no second factorisation."""
    import torchfmap.operators.krylov as krylov

    mesh, ops, seeds, times, ref = heat_setting
    calls = []
    real = krylov.factorize
    monkeypatch.setattr(krylov, "factorize", lambda *a, **kw: calls.append(1) or real(*a, **kw))
    factors: dict = {}
    first = heat_kernels(ops, seeds[:2], times, "krylov", tol=1e-8, factors=factors)
    n_first = len(calls)
    assert n_first >= 1 and len(factors) == n_first
    again = heat_kernels(ops, seeds, times, "krylov", tol=1e-8, factors=factors)
    assert len(calls) == n_first  # nothing factorised again
    np.testing.assert_allclose(again[:, :, :2], first, rtol=0, atol=1e-12 * np.abs(first).max())
    assert rel_err(again, ref).max() < 1e-8


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


def test_backward_euler_is_first_order(heat_setting):
    mesh, ops, seeds, times, ref = heat_setting
    errs = [
        rel_err(heat_kernels(ops, seeds, times[2:3], "backward_euler", n_steps=n), ref[2:3]).max()
        for n in (4, 16, 64)
    ]
    assert errs[0] > errs[1] > errs[2]
    assert 2.5 < errs[1] / errs[2] < 6  # ~4x per 4x more steps: first order


def test_spectral_with_full_spectrum_is_exact_truncated_is_not(heat_setting):
    mesh, ops, seeds, times, ref = heat_setting
    full = heat_kernels(ops, seeds, times, "spectral", n_eigen=mesh.n_vertices)
    assert rel_err(full, ref).max() < 1e-8
    truncated = heat_kernels(ops, seeds, times, "spectral", n_eigen=50)
    err = rel_err(truncated, ref).max(axis=1)
    assert err[0] > 0.1 and err[-1] < 1e-6  # Eq. 1 truncation fails at small t only


def test_local_mode_matches_global(heat_setting):
    mesh, ops, seeds, times, ref = heat_setting
    for local in (True, "auto"):
        K = heat_kernels(ops, seeds, times, "krylov", tol=1e-8, local=local, vertices=mesh.vertices)
        assert rel_err(K, ref).max() < 1e-7
    # the local solve really is local at the smallest time
    K = heat_kernels(ops, seeds, times[:1], local=True, vertices=mesh.vertices)
    assert (np.abs(K[0]) > 0).mean() < 0.3


def test_kernel_properties(heat_setting):
    mesh, (L, B), seeds, times, ref = heat_setting
    K = heat_kernels((L, B), seeds, times, tol=1e-10)
    # delta kernel: integrates to one (closed mesh), symmetric K_t(p, q) = K_t(q, p)
    assert np.allclose(np.ones(mesh.n_vertices) @ (B @ K[2]), 1.0, atol=1e-8)
    assert np.allclose(K[2][seeds], K[2][seeds].T, rtol=1e-7)
    indicator = heat_kernels((L, B), seeds, times, kernel="indicator", tol=1e-10)
    assert np.allclose(indicator, K * B.diagonal()[seeds], rtol=1e-7, atol=1e-12)


def test_mean_value_weights_rejected(heat_setting):
    mesh, ops, seeds, times, ref = heat_setting
    with pytest.raises(ParameterError, match="symmetric Laplacian"):
        heat_kernels(laplacian(mesh, scheme="mean_value"), seeds, times)


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


def test_heat_apply_equals_spectral_exponential(sphere2, rng):
    """exp(-t B⁻¹L) X = Φ e^{-Λt} Φᵀ B X with the full dense spectrum (162 vertices). Krylov
    accuracy target tol = 1e-8 relative: compared at 1e-6 of max |result|."""
    L, B = laplacian(sphere2)
    lam, phi = sla.eigh(L.toarray(), B.toarray())
    X = rng.normal(size=(sphere2.n_vertices, 2))
    times = np.array([1e-3, 1e-1, 1.0])
    out = heat_apply((L, B), X, times, tol=1e-8)
    assert out.shape == (3, sphere2.n_vertices, 2)
    for j, t in enumerate(times):
        ref = phi @ (np.exp(-np.maximum(lam, 0) * t)[:, None] * (phi.T @ (B @ X)))
        np.testing.assert_allclose(out[j], ref, atol=1e-6 * np.abs(ref).max())


BAD_TOLERANCES = [0.0, -1.0, float("nan"), float("inf"), 2.0, 1.0, 1e-20]


@pytest.mark.parametrize("tol", BAD_TOLERANCES)
def test_heat_tolerance_out_of_range_is_refused(sphere2, tol):
    """tol <= 0 or NaN used to loop for ever growing local patches; tol >= 1 returned kernels
    that were mostly wrong; tol=0 divided by zero. Each is now refused before any work."""
    ops = laplacian(sphere2)
    with pytest.raises(ParameterError, match=r"tol must be a relative accuracy.*Fix"):
        heat_kernels(ops, [0, 5], [1e-3], tol=tol, local=True, vertices=sphere2.vertices)
    with pytest.raises(ParameterError, match="tol must be"):
        diffusion_basis(sphere2, [0, 5], [1e-3], tol=tol)
    with pytest.raises(ParameterError, match="tol must be"):
        basis_stack(sphere2, [0, 5], times=[1e-3], heat_tol=tol)


def test_heat_tolerance_in_range_is_accepted(sphere2):
    """The bounds are inclusive at the bottom: the most demanding accepted tolerance still works."""
    K = heat_kernels(laplacian(sphere2), [0], [1e-2], tol=1e-14)
    assert np.isfinite(K).all()


def test_krylov_blocks_fit_their_memory_budget():
    """A block of Lanczos vectors stays within ``KRYLOV_BLOCK_BYTES`` (at least one column, at
    most ``KRYLOV_BLOCK_COLUMNS``), so a million-vertex mesh gets narrower blocks, not more memory."""
    from torchfmap.operators import krylov

    cap = krylov.KRYLOV_STORE + 1
    for n in (1_000, 300_000, 1_100_000, 50_000_000):
        block = krylov.block_columns(n, 200, cap)
        assert 1 <= block <= krylov.KRYLOV_BLOCK_COLUMNS
        assert block == 1 or 8 * n * cap * block <= krylov.KRYLOV_BLOCK_BYTES
    assert krylov.block_columns(1_000, 3, cap) == 3  # never wider than the columns asked


def test_time_major_columns_are_a_view_of_the_kernels(heat_setting):
    """``heat_kernels`` returns ``(T, V, S)`` laid out as ``(V, T, S)``: the diffusion basis'
    time-major ``(V, T·S)`` values are a reshape of it, not a second copy."""
    mesh, ops, seeds, times, ref = heat_setting
    K = heat_kernels(ops, seeds, times, "krylov", tol=1e-8)
    flat = K.transpose(1, 0, 2).reshape(mesh.n_vertices, -1)
    assert np.shares_memory(flat, K)
    np.testing.assert_array_equal(flat[:, len(seeds) : 2 * len(seeds)], K[1])
