"""Point maps and functional maps (``torchfmap.fmap.convert``): nearest neighbours, conversions
both ways, their checks."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, SeedError
from torchfmap.fmap import (
    check_landmark_pairs,
    check_p2p,
    fmap_to_p2p,
    fmap_to_p2p_bijective,
    icp_refine,
    nearest_neighbor,
    p2p_to_fmap,
    zoomout,
)
from torchfmap.fmap.convert import Neighbors, nearest_neighbor_distance


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


def test_p2p_fmap_round_trip(permuted_bases):
    x, y, perm, bx, by = permuted_bases
    C = p2p_to_fmap(perm, bx, by)
    # a vertex permutation is an exact isometry: C is orthogonal (diagonal +-1 up to degenerate blocks)
    assert np.abs(C.T @ C - np.eye(40)).max() < 1e-8
    for mode in ("pullback", "orthogonal"):
        assert np.array_equal(fmap_to_p2p(C, bx, by, mode=mode), perm)
    assert np.array_equal(fmap_to_p2p_bijective(C, C.T, bx, by), perm)
    # truncation to a smaller map still recovers the permutation
    assert np.array_equal(fmap_to_p2p(p2p_to_fmap(perm, bx, by, 20, 20), bx, by), perm)


def test_the_map_at_some_rows_is_the_whole_map_there(permuted_bases, rng):
    """``rows`` converts only those target vertices, and gives what the whole map gives there."""
    x, y, perm, bx, by = permuted_bases
    C = p2p_to_fmap(perm, bx, by) + 0.05 * rng.normal(size=(40, 40))  # not an exact permutation
    rows = rng.choice(len(perm), 17, replace=False)
    for mode in ("pullback", "orthogonal"):
        whole = fmap_to_p2p(C, bx, by, mode=mode, precision="double")
        part = fmap_to_p2p(C, bx, by, mode=mode, precision="double", rows=rows)
        assert part.shape == (17,) and np.array_equal(part, whole[rows])


def test_conversion_errors(permuted_bases):
    x, y, perm, bx, by = permuted_bases
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


def test_check_p2p_and_landmark_pairs():
    np.testing.assert_array_equal(check_p2p(np.array([2, 0, 1], dtype=np.int32), 3, 3), [2, 0, 1])
    with pytest.raises(ParameterError, match="one entry per vertex \\(4\\)"):
        check_p2p(np.zeros(3, dtype=int), 4, 3)
    with pytest.raises(ParameterError, match="integer vertex indices"):
        check_p2p(np.zeros(3), 3, 3)
    with pytest.raises(ParameterError, match=r"outside \[0, 3\)"):
        check_p2p(np.array([0, 3, 1]), 3, 3)
    pairs = check_landmark_pairs([[0, 4], [2, 1]], 3, 5)
    assert pairs.dtype == np.int64 and pairs.tolist() == [[0, 4], [2, 1]]
    with pytest.raises(ParameterError, match=r"must be \(L, 2\) pairs"):
        check_landmark_pairs([0, 1], 3, 5)
    with pytest.raises(SeedError, match="source landmarks"):
        check_landmark_pairs([[7, 0]], 3, 5)
    with pytest.raises(SeedError, match="swap the columns"):  # fits only as (y vertex, x vertex)
        check_landmark_pairs([[4, 0], [3, 2]], 3, 5)
