"""Refinement (``torchfmap.fmap.refine``): ICP, ZoomOut (subsampled, guarded by its energy) and
ZoomOut over basis sequences."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, basis_stack, farthest_point_sampling
from torchfmap.evaluate.scores import geodesic_errors, gt_from_map
from torchfmap.fmap import fmap_to_p2p, icp_refine, p2p_to_fmap, zoomout, zoomout_sequence

from ..conftest import bumpy_blob


@pytest.mark.parametrize("mode", ["pullback", "orthogonal"])
def test_refinement_recovers_from_noise(permuted_bases, mode):
    x, y, perm, bx, by = permuted_bases
    C = p2p_to_fmap(perm, bx, by, 15, 15)
    noisy = C + 0.15 * np.random.default_rng(0).normal(size=C.shape)
    before = np.mean(fmap_to_p2p(noisy, bx, by, mode=mode) == perm)
    C_icp, p_icp = icp_refine(noisy, bx, by, mode=mode)
    C_zo, p_zo = zoomout(noisy, bx, by, 40, step=5, mode=mode)
    assert C_zo.shape == (40, 40)
    assert np.mean(p_icp == perm) >= before and np.mean(p_zo == perm) > max(before, 0.9)


def test_subsampled_zoomout(permuted_bases):
    x, y, perm, bx, by = permuted_bases
    C = p2p_to_fmap(perm, bx, by, 15, 15)
    noisy = C + 0.15 * np.random.default_rng(0).normal(size=C.shape)
    before = np.mean(fmap_to_p2p(noisy, bx, by, mode="orthogonal") == perm)
    # samples of y and their true partners on x: the sampled problem keeps the answer
    sy = np.random.default_rng(1).choice(y.n_vertices, 300, replace=False)
    sx = np.sort(perm[sy])
    C_zo, p_zo = zoomout(noisy, bx, by, 40, step=5, mode="orthogonal", subsample=(sx, sy))
    assert C_zo.shape == (40, 40)
    assert np.mean(p_zo == perm) > max(before, 0.9)
    # with every vertex as a sample it is plain ZoomOut up to the least-squares vs projection step
    full = (np.arange(x.n_vertices), np.arange(y.n_vertices))
    _, p_all = zoomout(noisy, bx, by, 40, step=5, mode="orthogonal", subsample=full)
    assert np.mean(p_all == perm) > 0.9
    for bad in ((sx, sy + 10**6), (sx[:0], sy), "nope", (sx.astype(float), sy)):
        with pytest.raises(ParameterError, match="subsample"):
            zoomout(noisy, bx, by, 40, step=5, subsample=bad)


def test_zoomout_never_returns_a_map_worse_than_its_start_by_its_own_energy(permuted_bases):
    """From bad starts (random maps), the guarded ZoomOut's result has at most the start's
    energy (Σ_k ‖C_kᵀC_k - I‖²/k over its sizes), and it is the unguarded result whenever that
    one is no worse; from the exact map it stays exact."""
    from torchfmap.fmap import fmap_to_p2p
    from torchfmap.fmap.refine import zoomout_energy

    x, y, perm, bx, by = permuted_bases
    sizes = list(range(10, 40, 5)) + [40]
    for seed in range(4):
        C0 = np.random.default_rng(seed).normal(size=(10, 10))
        start = fmap_to_p2p(C0, bx, by, mode="orthogonal")
        e_start = zoomout_energy(start, bx, by, sizes)
        C, p2p = zoomout(C0, bx, by, 40, step=5, mode="orthogonal")
        _, free = zoomout(C0, bx, by, 40, step=5, mode="orthogonal", guard=False)
        assert zoomout_energy(p2p, bx, by, sizes) <= e_start + 1e-12
        assert C.shape == (40, 40)
        if zoomout_energy(free, bx, by, sizes) <= e_start:
            assert zoomout_energy(p2p, bx, by, sizes) <= zoomout_energy(free, bx, by, sizes)
    exact = p2p_to_fmap(perm, bx, by, 10, 10)
    np.testing.assert_array_equal(zoomout(exact, bx, by, 40, step=5, mode="orthogonal")[1], perm)


@pytest.fixture(scope="module")
def nested_bases_pair():
    """The blob, a vertex-permuted copy (truth p2p_yx = perm) and nested stack bases built from
    the SAME corresponding seeds (seed prefixes of 6, 12, 24: nested harmonic + diffusion spans)."""
    x = bumpy_blob(2)
    rng = np.random.default_rng(0)
    perm = rng.permutation(x.n_vertices)
    y = x.permuted(perm)
    inv = np.argsort(perm)  # vertex v of x is vertex inv[v] of y
    seeds = farthest_point_sampling(x, 24, metric="euclidean")
    bx = [basis_stack(x, seeds[:n], times=[0.05]) for n in (6, 12, 24)]
    by = [basis_stack(y, inv[seeds[:n]], times=[0.05]) for n in (6, 12, 24)]
    return x, y, perm, bx, by


@pytest.mark.parametrize("mode", ["pullback", "orthogonal"])
def test_zoomout_sequence_recovers_permutation(nested_bases_pair, mode):
    """From a map with 30% random entries the error drops (both modes); in 'orthogonal' mode
    the true permutation comes back exactly: the bases of y are those of x relabelled, so the
    projected map is the identity plus the perturbation's low-frequency part and the nearest
    neighbours of identical embeddings are exact. ('pullback' may keep a few neighbours.)"""
    x, y, perm, bx, by = nested_bases_pair
    rng = np.random.default_rng(1)
    start = perm.copy()
    bad = rng.choice(len(start), len(start) * 3 // 10, replace=False)
    start[bad] = rng.integers(0, x.n_vertices, len(bad))
    err0 = geodesic_errors(x, start, gt_from_map(perm)).mean()
    C, p2p = zoomout_sequence(start, bx, by, mode=mode)
    assert C.shape == (by[-1].k, bx[-1].k)
    assert p2p.shape == (y.n_vertices,) and p2p.dtype.kind == "i"
    assert p2p.min() >= 0 and p2p.max() < x.n_vertices
    err = geodesic_errors(x, p2p, gt_from_map(perm)).mean()
    assert err < err0
    assert np.count_nonzero(p2p != perm) < np.count_nonzero(start != perm)
    if mode == "orthogonal":
        np.testing.assert_array_equal(p2p, perm)


def test_zoomout_sequence_fixed_point(nested_bases_pair):
    """The true map is a fixed point and its C is the identity: Φ_y = Φ_x[perm] (bases computed
    separately, equal up to round-off ~1e-12·cond), so Φ_yᵀ B_y Φ_x[perm] = I to 1e-8."""
    x, y, perm, bx, by = nested_bases_pair
    C, p2p = zoomout_sequence(perm, bx, by)
    np.testing.assert_allclose(C, np.eye(len(C)), atol=1e-8)
    np.testing.assert_array_equal(p2p, perm)


def test_zoomout_sequence_on_samples_keeps_the_true_map_and_improves_a_noisy_one(nested_bases_pair):
    """With samples that correspond exactly (x's samples and their copies on y) the true map is
    a fixed point of the sampled iteration (least squares on exact rows gives C = I); from a
    perturbed start the error drops, and the final point map covers every vertex of y."""
    x, y, perm, bx, by = nested_bases_pair
    inv = np.argsort(perm)
    sx = farthest_point_sampling(x, 120, metric="euclidean")  # > K = 48 columns
    samples = (sx, inv[sx])
    C, p2p = zoomout_sequence(perm, bx, by, subsample=samples)
    np.testing.assert_allclose(C, np.eye(len(C)), atol=1e-8)
    np.testing.assert_array_equal(p2p, perm)
    rng = np.random.default_rng(2)
    start = perm.copy()
    bad = rng.choice(len(start), len(start) * 3 // 10, replace=False)
    start[bad] = rng.integers(0, x.n_vertices, len(bad))
    # independent samples on y (not copies of x's): still an improvement on the start
    own = (sx, farthest_point_sampling(y, 120, metric="euclidean"))
    _, p2p = zoomout_sequence(start, bx, by, mode="orthogonal", subsample=own)
    assert p2p.shape == (y.n_vertices,)
    err0 = geodesic_errors(x, start, gt_from_map(perm)).mean()
    assert geodesic_errors(x, p2p, gt_from_map(perm)).mean() < err0
    with pytest.raises(ParameterError, match="subsample of y"):
        zoomout_sequence(perm, bx, by, subsample=(sx, np.array([y.n_vertices])))


def test_zoomout_sequence_errors(nested_bases_pair):
    x, y, perm, bx, by = nested_bases_pair
    with pytest.raises(ParameterError, match="same length"):
        zoomout_sequence(perm, bx, by[:2])
    with pytest.raises(ParameterError, match="non-empty"):
        zoomout_sequence(perm, [], [])
    with pytest.raises(ParameterError, match="p2p_yx must have one entry per vertex"):
        zoomout_sequence(perm[:-1], bx, by)


def test_zoomout_refuses_to_shrink(sphere2):
    from torchfmap import laplacian_eigenbasis
    from torchfmap.fmap import zoomout

    b = laplacian_eigenbasis(sphere2, 12)
    with pytest.raises(ParameterError, match="k_final=4 is below"):
        zoomout(np.eye(8), b, b, 4)


def test_energy_guard_keeps_the_first_lowest_energy_map(permuted_bases):
    """ZoomOut's one guard: offered maps are scored by ``zoomout_energy`` over the sizes, the
    first of the lowest kept; ``replaces`` says whether it is another than the last one; a
    disabled guard keeps nothing."""
    from torchfmap.fmap import EnergyGuard, zoomout_energy

    _, _, perm, bx, by = permuted_bases
    sizes = [10, 20]
    scrambled = np.random.default_rng(0).integers(0, bx.n_vertices, by.n_vertices)
    guard = EnergyGuard(bx, by, sizes)
    guard.offer(perm)
    guard.offer(scrambled)
    assert guard.p2p_yx is perm and guard.replaces(scrambled) and not guard.replaces(perm)
    assert guard.energy == zoomout_energy(perm, bx, by, sizes) < zoomout_energy(scrambled, bx, by, sizes)
    guard.offer(perm.copy())  # equal energy: the first is kept
    assert guard.p2p_yx is perm
    off = EnergyGuard(bx, by, sizes, enabled=False)
    off.offer(perm)
    assert off.p2p_yx is None and not off.replaces(scrambled)


def test_zoomout_anchors_keep_the_true_map_and_carry_a_map_from_no_information(permuted_bases):
    """Anchors that correspond exactly (geodesic distances to 6 landmark pairs; on a permuted
    copy they are the same rows, permuted): the true map is a fixed point (both parts of the
    embedding agree there, distance 0), and from a random start, where ZoomOut alone stays at
    chance, the anchors bring the map well below chance."""
    from torchfmap import GeodesicSolver

    x, y, perm, bx, by = permuted_bases
    ax = GeodesicSolver(x).distances(np.arange(0, 600, 100)).T  # (V, 6)
    anchors = (ax, ax[perm])
    _, kept = zoomout(p2p_to_fmap(perm, bx, by, 15, 15), bx, by, 40, step=5, anchors=anchors)
    np.testing.assert_array_equal(kept, perm)
    start = np.random.default_rng(0).integers(0, x.n_vertices, y.n_vertices)
    C = p2p_to_fmap(start, bx, by, 15, 15)
    gt = gt_from_map(perm)
    chance = geodesic_errors(x, zoomout(C, bx, by, 40, step=5)[1], gt).mean()
    anchored = geodesic_errors(x, zoomout(C, bx, by, 40, step=5, anchors=anchors)[1], gt).mean()
    assert anchored < 0.5 * chance
    samples = (np.arange(0, x.n_vertices, 2), np.sort(perm[np.arange(0, y.n_vertices, 2)]))
    _, on_samples = zoomout(C, bx, by, 40, step=5, anchors=anchors, subsample=samples)
    assert geodesic_errors(x, on_samples, gt).mean() < 0.5 * chance
    for bad in ((ax, ax[:10]), (ax, ax[:, :3]), (ax[:, :0], ax[:, :0]), (ax, np.full_like(ax, np.nan)), "no"):
        with pytest.raises(ParameterError, match="anchors"):
            zoomout(C, bx, by, 40, step=5, anchors=bad)


def test_zoomout_on_surface_samples_recovers_the_map_and_keeps_the_true_one(permuted_bases):
    """ZoomOut on surface samples (fits weighted by the cells' areas, each sample matched among
    every vertex near its match, the final map searched locally, :class:`Samples.of_surfaces`):
    the true map of a permuted copy is a fixed point, and a noisy start is carried to the
    exhaustive ZoomOut's answer, with no step comparing every vertex with every vertex."""
    from torchfmap.fmap.nearest import surface_sampling
    from torchfmap.fmap.refine import Samples
    from torchfmap.operators import laplacian

    x, y, perm, bx, by = permuted_bases
    samples = Samples.of_surfaces(
        *(surface_sampling(m.vertices, laplacian(m)[1].diagonal(), 150) for m in (x, y))
    )
    C = p2p_to_fmap(perm, bx, by, 15, 15)
    _, fixed = zoomout(C, bx, by, 40, step=5, subsample=samples, p2p_yx=perm)
    np.testing.assert_array_equal(fixed, perm)
    noisy = C + 0.15 * np.random.default_rng(0).normal(size=C.shape)
    start = fmap_to_p2p(noisy, bx, by, mode="orthogonal")
    _, exact = zoomout(noisy, bx, by, 40, step=5)
    _, sampled = zoomout(noisy, bx, by, 40, step=5, subsample=samples, p2p_yx=start)
    assert np.mean(sampled == perm) >= np.mean(exact == perm) - 0.02 and np.mean(sampled == perm) > 0.9


def test_every_zoomout_variant_runs_the_one_loop(permuted_bases, monkeypatch):
    """Plain, partial and hybrid ZoomOut and the fixed-size iterations all step through
    :func:`~torchfmap.fmap.refine.zoomout_iterations` (one implementation of the loop)."""
    import torchfmap.fmap.refine as refine
    import torchfmap.kinds.hybrid as hybrid
    import torchfmap.kinds.refiners as refiners
    import torchfmap.matching.partial as partial

    calls = []
    real = refine.zoomout_iterations

    def spy(step, sizes, **kw):
        calls.append(type(step).__name__)
        return real(step, sizes, **kw)

    for module in (refine, hybrid, refiners, partial):
        monkeypatch.setattr(module, "zoomout_iterations", spy, raising=False)
    x, y, perm, bx, by = permuted_bases
    zoomout(p2p_to_fmap(perm, bx, by, 10, 10), bx, by, 20)
    zoomout_sequence(perm, [bx, bx], [by, by])
    partial.partial_zoomout(perm, bx, by, 10, 20)
    assert calls == ["SpectralStep", "SequenceStep", "SpectralStep"]


def test_zoomout_iterations_start_from_exactly_one_map(permuted_bases):
    """The one loop refuses both starts or neither, and a point-map start with no size; from the
    true map it stays at the true map (a fixed point of the projection and its conversion)."""
    from torchfmap.fmap import zoomout_iterations
    from torchfmap.fmap.refine import SpectralStep

    x, y, perm, bx, by = permuted_bases
    step = SpectralStep(bx, by)
    C = p2p_to_fmap(perm, bx, by, 10, 10)
    for bad in ({"C_xy": C, "p2p_yx": perm}, {}, {"p2p_yx": perm}):
        sizes = [] if bad == {"p2p_yx": perm} else [12]
        with pytest.raises(ParameterError, match="exactly one"):
            zoomout_iterations(step, sizes, **bad)
    C_out, p2p = zoomout_iterations(step, [15, 20], p2p_yx=perm)
    assert C_out.shape == (20, 20)
    np.testing.assert_array_equal(p2p, perm)
