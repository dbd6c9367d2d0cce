"""Feature-aware matching with few landmarks: corresponding seeds, k-column bases, identity prior."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfmap import ParameterError, SeedError, match
from torchfmap.data import stretch_deform
from torchfmap.fmap import build_problem, core, solve_fmap
from torchfmap.pipeline import match_bases, prepare_shape
from torchfmap.seeds import corresponding_seeds

from .conftest import bend, bumpy_blob


@pytest.fixture(scope="module")
def permuted_pair():
    """A mesh and its vertex-permuted copy: y vertex i is x vertex perm[i]."""
    x = bumpy_blob(3)
    perm = np.random.default_rng(4).permutation(x.n_vertices)
    inverse = np.argsort(perm)
    y = x.permuted(perm)
    landmarks = np.array([[v, inverse[v]] for v in (3, 200, 450, 600)])
    return x, y, perm, landmarks


@pytest.mark.parametrize("kind", ["diffusion", "harmonic", "stack"])
def test_feature_bases_have_exactly_k_orthonormal_corresponding_columns(kind):
    """Every feature-aware basis honours k: k B-orthonormal columns on both shapes, column i
    built at seed pair i (landmarks first)."""
    x = bumpy_blob(3)
    y = x.copy(bend(x.vertices, 0.3))
    lm = np.array([[5, 5], [300, 300], [500, 500]])
    sx, sy = prepare_shape(x, 0), prepare_shape(y, 0)
    bx, by, seeds = match_bases(sx, sy, kind, 25, lm)
    assert bx.k == by.k == 25
    # modified Gram-Schmidt with re-orthogonalisation: orthogonality to a few eps per column
    tol = 100 * 25 * np.finfo(float).eps
    np.testing.assert_allclose(bx.gram(), np.eye(25), atol=tol)
    np.testing.assert_allclose(by.gram(), np.eye(25), atol=tol)
    np.testing.assert_array_equal(seeds[: len(lm)], lm)
    seed_of = {int(a): int(b) for a, b in seeds}
    for cx, cy in zip(bx.columns, by.columns, strict=True):
        assert cx.kind == cy.kind and cx.time == cy.time and seed_of[cx.seed] == cy.seed


def test_exact_seeds_on_a_permuted_copy_give_the_identity_map(permuted_pair):
    """With an exact copy, trilateration places every seed exactly, the bases correspond
    exactly, C = I and the point map is the permutation, raw and refined."""
    x, y, perm, lm = permuted_pair
    result = match(x, y, landmarks=lm, basis="diffusion", k=30, refine="zoomout")
    inverse = np.argsort(perm)
    np.testing.assert_array_equal(result.seeds[:, 1], inverse[result.seeds[:, 0]])
    np.testing.assert_array_equal(result.p2p_yx_initial, perm)
    np.testing.assert_array_equal(result.p2p_yx, perm)


def test_identity_prior_solve_recovers_the_identity(permuted_pair):
    """Exactly corresponding bases and descriptors: C = I zeroes every term of the energy, so
    the solve returns it (up to the row-wise solve's round-off) for any prior weight."""
    x, y, perm, lm = permuted_pair
    sx, sy = prepare_shape(x, 0), prepare_shape(y, 0)
    bx, by, _ = match_bases(sx, sy, "diffusion", 20, lm)
    F = np.random.default_rng(0).normal(size=(x.n_vertices, 8))
    for w_prior in (0.1, 10.0):
        C = solve_fmap(bx, by, F, F[perm], w_lap=1.0, prior=np.eye(20), w_prior=w_prior)
        np.testing.assert_allclose(C, np.eye(20), atol=1e-8)


def test_prior_pulls_the_core_solution_and_matches_the_classical_path():
    """w_prior -> inf gives the prior; w_prior = 0 ignores it; the classical problem with a
    prior equals the core's rotate_and_solve with the same prior."""
    g = torch.Generator().manual_seed(1)
    A_x, A_y = (
        torch.randn(6, 9, generator=g, dtype=torch.float64),
        torch.randn(5, 9, generator=g, dtype=torch.float64),
    )
    lam_x, U_x = core.spectral_frame(torch.diag(torch.rand(6, generator=g, dtype=torch.float64)))
    lam_y, U_y = core.spectral_frame(torch.diag(torch.rand(5, generator=g, dtype=torch.float64)))
    P = torch.randn(5, 6, generator=g, dtype=torch.float64)
    args = (A_x, A_y, lam_x, U_x, lam_y, U_y)
    free = core.rotate_and_solve(*args, w_desc=1.0, w_lap=0.1)
    torch.testing.assert_close(
        core.rotate_and_solve(*args, w_desc=1.0, w_lap=0.1, prior=P, w_prior=0.0), free
    )
    strong = core.rotate_and_solve(*args, w_desc=1.0, w_lap=0.1, prior=P, w_prior=1e12)
    torch.testing.assert_close(strong, P, atol=1e-9, rtol=0)


def test_corresponding_seeds_bad_input(permuted_pair):
    x, y, _, lm = permuted_pair
    with pytest.raises(ParameterError, match="n_seeds"):
        corresponding_seeds(x, y, lm, 2)
    with pytest.raises(ParameterError, match="n_seeds"):
        corresponding_seeds(x, y, lm, 10.0)
    with pytest.raises(SeedError):
        corresponding_seeds(x, y, np.array([[0, 10**6]]), 5)
    with pytest.raises(ParameterError, match="prior must be"):
        sx, sy = prepare_shape(x, 0), prepare_shape(y, 0)
        bx, by, _ = match_bases(sx, sy, "diffusion", 10, lm)
        F = np.ones((x.n_vertices, 2))
        build_problem(bx, by, F, F, prior=np.eye(3), w_prior=1.0)


def test_stretch_deform_keeps_ids_and_is_not_isometric():
    """Same faces and vertex count (ground truth = identity), deterministic, identity at
    strength 0; at strength 1 the limb scaling alone stretches edges near its centre by up to
    1 + 0.6 = 1.6, so some edge grows by more than 1.5x."""
    x = bumpy_blob(3)
    y = stretch_deform(x, seed=3, strength=1.0)
    np.testing.assert_array_equal(y.faces, x.faces)
    np.testing.assert_array_equal(stretch_deform(x, seed=3, strength=1.0).vertices, y.vertices)
    np.testing.assert_allclose(stretch_deform(x, seed=3, strength=0.0).vertices, x.vertices, atol=0)
    ratio = y.edge_lengths / x.edge_lengths
    assert ratio.max() > 1.5
    with pytest.raises(ParameterError, match="strength"):
        stretch_deform(x, strength=-1.0)


def test_replace_seeds_moves_near_seeds_to_the_map_and_keeps_far_ones(permuted_pair):
    """With the exact map, a seed misplaced by one edge goes back to its true image; one
    misplaced by more than the covering radius sqrt(1/S) stays put; landmarks never move."""
    from torchfmap.seeds import replace_seeds

    x, y, perm, lm = permuted_pair
    inverse = np.argsort(perm)
    sx, sy = prepare_shape(x, 0), prepare_shape(y, 0)
    seeds = corresponding_seeds(x, y, lm, 12, distances=(sx.distances, sy.distances))
    true_y = inverse[seeds[:, 0]]
    np.testing.assert_array_equal(seeds[:, 1], true_y)
    radius = np.sqrt(1.0 / len(seeds))
    near_i, far_i = len(lm), len(lm) + 1
    ring = y.edges[(y.edges == true_y[near_i]).any(axis=1)].ravel()
    near = int(next(v for v in ring if v != true_y[near_i] and v not in set(seeds[:, 1])))
    d_far = sy.distances(true_y[far_i])
    far = int(np.argmax(np.where(np.isin(np.arange(y.n_vertices), seeds[:, 1]), -1, d_far)))
    assert d_far[far] > radius
    moved = seeds.copy()
    moved[near_i, 1], moved[far_i, 1] = near, far
    out = replace_seeds(sx.distances, sy.distances, moved, perm, len(lm))
    np.testing.assert_array_equal(out[: len(lm)], seeds[: len(lm)])
    assert out[near_i, 1] == true_y[near_i]
    assert out[far_i, 1] == far
    assert len(set(out[:, 1].tolist())) == len(out)


def test_distance_rows_are_cached_and_in_sqrt_area_units():
    """Rows are geodesic distances divided by sqrt(area) (so a scaled copy gives the same
    rows), computed once per source."""
    from torchfmap.operators import DistanceRows

    x = bumpy_blob(3)
    rows, scaled = DistanceRows(x, normalized=True), DistanceRows(x.scaled(7.0), normalized=True)
    solved = []
    inner = rows.solver.distances
    rows.solver.distances = lambda sources: solved.extend(sources) or inner(sources)
    a = rows(5)
    np.testing.assert_array_equal(rows(5), a)
    assert solved == [5] and a[5] == 0 and (a >= 0).all()
    np.testing.assert_allclose(scaled.rows([5, 9]), rows.rows([5, 9]), rtol=1e-6, atol=1e-9)
    assert solved == [5, 9]


def test_distance_rows_budget_keeps_the_first_rows_and_equals_the_solver():
    """Unnormalised rows equal the solver's bit for bit; with a budget of two rows the third
    is solved on every request and the first two never again; a negative budget is refused."""
    from torchfmap import ParameterError
    from torchfmap.operators import DistanceRows, GeodesicSolver

    x = bumpy_blob(2)
    solver = GeodesicSolver(x)
    rows = DistanceRows(x, solver, max_bytes=2 * 8 * x.n_vertices)
    solved = []
    inner = solver.distances
    solver.distances = lambda sources: solved.extend(sources) or inner(sources)
    first = rows.distances([3, 7, 11])
    assert solved == [3, 7, 11]
    np.testing.assert_array_equal(first, inner([3, 7, 11]))
    np.testing.assert_array_equal(rows.distances([11, 7, 3]), first[[2, 1, 0]])
    assert solved == [3, 7, 11, 11]
    with pytest.raises(ParameterError, match="max_bytes"):
        DistanceRows(x, max_bytes=-1)


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
