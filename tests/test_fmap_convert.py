"""p2p <-> functional map conversions, nearest neighbours, refinement."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, laplacian_eigenbasis
from torchfmap.fmap import (
    fmap_to_p2p,
    fmap_to_p2p_bijective,
    icp_refine,
    nearest_neighbor,
    p2p_to_fmap,
    zoomout,
)
from torchfmap.fmap.convert import Neighbors, nearest_neighbor_distance

from .conftest import bumpy_blob


@pytest.fixture(scope="module")
def bases(request):
    x = bumpy_blob(3)
    perm = np.random.default_rng(5).permutation(x.n_vertices)
    y = x.permuted(perm)  # y vertex i is x vertex perm[i]: p2p_yx = perm
    return x, y, perm, laplacian_eigenbasis(x, 40), laplacian_eigenbasis(y, 40)


@pytest.mark.parametrize(
    ("method", "precision"), [("brute", "double"), ("brute", "single"), ("kdtree", "double")]
)
def test_nearest_neighbor_equals_brute_force(rng, method, precision):
    q, r = rng.normal(size=(300, 5)), rng.normal(size=(200, 5))
    d2 = ((q[:, None] - r[None]) ** 2).sum(axis=2)
    expected = np.argmin(d2, axis=1)
    # (Gaussian data: every row's best and second-best distances differ far beyond float32 round-off)
    assert np.min(np.diff(np.sort(d2, axis=1)[:, :2], axis=1)) > 1e-5
    options = dict(search=method, precision=precision, block_bytes=8 * 200 * 7)
    found = nearest_neighbor_distance(q, r, **options)
    assert isinstance(found, Neighbors) and found.index.dtype == np.int64
    assert np.array_equal(found.index, expected)
    assert np.allclose(found.distance, np.linalg.norm(q - r[expected], axis=1))
    got = nearest_neighbor(q, r, **options)  # the index alone, whatever the search
    assert isinstance(got, np.ndarray) and np.array_equal(got, expected)


def test_nearest_neighbor_errors(rng):
    with pytest.raises(ParameterError, match="must be"):
        nearest_neighbor(rng.normal(size=(3, 4)), rng.normal(size=(3, 5)))
    bad = rng.normal(size=(3, 4))
    bad[0, 0] = np.nan
    with pytest.raises(ParameterError, match="NaN"):
        nearest_neighbor(bad, rng.normal(size=(3, 4)))
    with pytest.raises(ParameterError, match="precision"):
        nearest_neighbor(rng.normal(size=(3, 4)), rng.normal(size=(3, 4)), precision="half")


def test_p2p_fmap_round_trip(bases):
    x, y, perm, bx, by = bases
    C = p2p_to_fmap(perm, bx, by)
    # a vertex permutation is an exact isometry: C is orthogonal (diagonal +-1 up to degenerate blocks)
    assert np.abs(C.T @ C - np.eye(40)).max() < 1e-8
    for mode in ("pullback", "orthogonal"):
        assert np.array_equal(fmap_to_p2p(C, bx, by, mode=mode), perm)
    assert np.array_equal(fmap_to_p2p_bijective(C, C.T, bx, by), perm)
    # truncation to a smaller map still recovers the permutation
    assert np.array_equal(fmap_to_p2p(p2p_to_fmap(perm, bx, by, 20, 20), bx, by), perm)


@pytest.mark.parametrize("mode", ["pullback", "orthogonal"])
def test_refinement_recovers_from_noise(bases, mode):
    x, y, perm, bx, by = bases
    C = p2p_to_fmap(perm, bx, by, 15, 15)
    noisy = C + 0.15 * np.random.default_rng(0).normal(size=C.shape)
    before = np.mean(fmap_to_p2p(noisy, bx, by, mode=mode) == perm)
    C_icp, p_icp = icp_refine(noisy, bx, by, mode=mode)
    C_zo, p_zo = zoomout(noisy, bx, by, 40, step=5, mode=mode)
    assert C_zo.shape == (40, 40)
    assert np.mean(p_icp == perm) >= before and np.mean(p_zo == perm) > max(before, 0.9)


def test_subsampled_zoomout(bases):
    x, y, perm, bx, by = bases
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


def test_conversion_errors(bases):
    x, y, perm, bx, by = bases
    with pytest.raises(ParameterError, match=r"C_xy has shape \(50, 50\)"):
        fmap_to_p2p(np.eye(50), bx, by)
    with pytest.raises(ParameterError, match="one entry per vertex"):
        p2p_to_fmap(perm[:10], bx, by)
    with pytest.raises(ParameterError, match="outside"):
        p2p_to_fmap(perm + 1, bx, by)
    with pytest.raises(ParameterError, match="square"):
        icp_refine(np.ones((4, 5)), bx, by)
    with pytest.raises(ParameterError, match="k_final"):
        zoomout(np.eye(10), bx, by, 100)


def test_zoomout_never_returns_a_map_worse_than_its_start_by_its_own_energy(bases):
    """From bad starts (random maps), the guarded ZoomOut's result has at most the start's
    energy (Σ_k ‖C_kᵀC_k - I‖²/k over its sizes), and it is the unguarded result whenever that
    one is no worse; from the exact map it stays exact."""
    from torchfmap.fmap import fmap_to_p2p
    from torchfmap.fmap.refine import zoomout_energy

    x, y, perm, bx, by = bases
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
