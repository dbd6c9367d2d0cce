"""Prepared shapes (``torchfmap.bases.prepared``): the unit-area frame, the per-shape cache of heat
kernels."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap.bases.prepared import prepare_shape, with_eigenpairs
from torchfmap.operators import gradient_operator

from ..conftest import SCALES, bumpy_blob


def test_seed_kernels_are_solved_once_per_seed_and_agree_with_the_diffusion_basis():
    """The per-shape kernel cache solves only new (seed, time) pairs, and a basis assembled
    from it equals ``diffusion_basis`` at the same seeds to within both solves' tolerance."""
    from torchfmap.bases import diffusion_basis
    from torchfmap.bases.prepared import SEED_HEAT_TOL, seed_kernels

    x = bumpy_blob(3)
    shape = prepare_shape(x, 0)
    seeds, t = np.array([5, 300, 500, 120]), 0.05
    first = seed_kernels(shape, seeds[:3], (t,))
    assert set(shape.kernels) == {(int(s), t) for s in seeds[:3]}
    cached = {key: value.copy() for key, value in shape.kernels.items()}
    both = seed_kernels(shape, seeds, (t,))
    assert len(shape.kernels) == 4  # only seed 120 was solved
    for key, value in cached.items():
        np.testing.assert_array_equal(shape.kernels[key], value)
    np.testing.assert_array_equal(both.values[:, :3], first.values)
    unit = x.scaled(shape.scale)  # the frame the prepared shape's operators live in
    reference = diffusion_basis(unit, seeds, (t,), operators=shape.operators, tol=SEED_HEAT_TOL, local=False)
    # each solve is within SEED_HEAT_TOL (relative to the kernel's size) of the exact kernel
    scale = np.abs(reference.values).max(axis=0)
    assert np.all(np.abs(both.values - reference.values).max(axis=0) <= 2 * SEED_HEAT_TOL * scale)
    assert [(c.seed, c.time) for c in both.columns] == [(c.seed, c.time) for c in reference.columns]


def test_prepared_shapes_live_in_the_unit_area_frame(small_bent_pair):
    x, _, _ = small_bent_pair
    for c in SCALES:
        shape = prepare_shape(x.scaled(c), 10)
        assert shape.area == pytest.approx(1.0, rel=1e-12)
        assert shape.operators[1].sum() == pytest.approx(1.0, rel=1e-12)
        lam, ref = shape.eigenbasis.eigenvalues, prepare_shape(x, 10).eigenbasis.eigenvalues
        # the first eigenvalue is 0 up to the solver's round-off relative to the spectrum
        np.testing.assert_allclose(lam, ref, rtol=1e-8, atol=1e-10 * ref.max())
    L, B = prepare_shape(x, 0).operators
    given = prepare_shape(x.scaled(3.0), 0, operators=(L, 9.0 * B))
    assert given.scale == 1.0 and given.area == pytest.approx(9.0)  # the given mass's total


def test_a_prepared_shape_derives_each_quantity_once(blob):
    shape = prepare_shape(blob, 0)
    calls = []
    first = shape.derive("x", lambda: calls.append(1) or np.arange(3))
    assert shape.derive("x", lambda: calls.append(1) or np.arange(5)) is first and calls == [1]
    grad = shape.gradient()
    assert shape.gradient() is grad
    assert shape.frame is shape.frame and np.isclose(shape.frame.area, 1.0)
    ref = gradient_operator(blob.scaled(shape.scale))
    for key in ref:
        np.testing.assert_allclose(grad[key], ref[key], rtol=1e-12, atol=0, err_msg=key)
    grown = with_eigenpairs(shape, 8)
    assert grown is shape and shape.n_eigen == 8 and shape.derive("x", None) is first


def test_seed_kernels_solve_all_times_of_a_call_together(monkeypatch):
    """Several times are one Krylov solve per seed block (one factorisation for times within
    ``KRYLOV_SPAN``), not one per time; pairs already held are kept as they were, and every
    kernel is within the cache's tolerance of the exact one."""
    import torchfmap.operators.krylov as krylov
    from torchfmap.bases import diffusion_basis
    from torchfmap.bases.prepared import SEED_HEAT_TOL, seed_kernels

    x = bumpy_blob(3)
    shape = prepare_shape(x, 0)
    times = (0.01, 0.03, 0.1)  # within KRYLOV_SPAN of each other
    assert times[-1] / times[0] <= krylov.KRYLOV_SPAN
    seed_kernels(shape, [5], (0.03,))
    held = shape.kernels[5, 0.03].copy()
    calls = []
    real = krylov.krylov_block
    monkeypatch.setattr(krylov, "krylov_block", lambda *a, **kw: calls.append(a[3]) or real(*a, **kw))
    basis = seed_kernels(shape, [5, 300], times)
    assert len(calls) == 1 and len(calls[0]) == len(times)  # one block, all three times
    np.testing.assert_array_equal(shape.kernels[5, 0.03], held)
    unit = x.scaled(shape.scale)
    exact = diffusion_basis(unit, [5, 300], times, operators=shape.operators, tol=1e-12, local=False)
    scale = np.abs(exact.values).max(axis=0)
    assert np.all(np.abs(basis.values - exact.values).max(axis=0) <= 2 * SEED_HEAT_TOL * scale)
