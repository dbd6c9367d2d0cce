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
from torchfmap.fmap.nearest import (
    Neighbors,
    SurfaceSampling,
    local_nearest,
    nearest_neighbor_distance,
    surface_sampling,
)


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


def _sampling(mesh, n):
    from torchfmap.operators import laplacian

    return surface_sampling(mesh.vertices, laplacian(mesh)[1].diagonal(), n)


def test_surface_sampling_partitions_the_vertices_into_cells_around_spread_samples(permuted_bases):
    """Every vertex is in exactly one cell, the nearest sample's (each sample in its own); the
    cells' weights add up to the total mass; each sample's neighbours start with itself; the
    ring of a sample is exactly the vertices of its neighbours' cells; the samples are distinct
    and no closer than a fraction of the covering radius a uniform spread allows."""
    x = permuted_bases[0]
    from torchfmap.operators import laplacian

    mass = laplacian(x)[1].diagonal()
    sm = surface_sampling(x.vertices, mass, 60)
    assert isinstance(sm, SurfaceSampling)
    n = len(sm.index)  # 60, and more where crowded cells were split
    assert len(np.unique(sm.index)) == n >= 60
    np.testing.assert_array_equal(sm.cell[sm.index], np.arange(n))
    dist = np.linalg.norm(x.vertices[:, None, :] - x.vertices[sm.index][None], axis=2)
    np.testing.assert_allclose(dist[np.arange(x.n_vertices), sm.cell], dist.min(axis=1), rtol=1e-12)
    np.testing.assert_allclose(sm.weight.sum(), mass.sum(), rtol=1e-12)
    np.testing.assert_array_equal(sm.neighbors[:, 0], np.arange(n))
    np.testing.assert_array_equal(np.sort(sm.order), np.arange(x.n_vertices))
    for s in (0, 17, n - 1):
        ring = sm.ring[sm.ring_start[s] : sm.ring_start[s + 1]]
        expected = np.flatnonzero(np.isin(sm.cell, sm.neighbors[s]))
        np.testing.assert_array_equal(np.sort(ring), expected)
    # farthest points: the closest two samples are at least half the covering radius apart
    gaps = np.linalg.norm(x.vertices[sm.index][:, None] - x.vertices[sm.index][None], axis=2)
    np.fill_diagonal(gaps, np.inf)
    assert gaps.min() >= 0.5 * dist.min(axis=1).max()
    everyone = surface_sampling(x.vertices, mass, 10**6)
    np.testing.assert_array_equal(everyone.index, np.arange(x.n_vertices))
    for bad in ((x.vertices[:, :2], mass, 5), (x.vertices, mass[:-1], 5), (x.vertices, mass, 0)):
        with pytest.raises(ParameterError):
            surface_sampling(*bad)


def test_local_nearest_equals_the_exhaustive_search_for_a_continuous_map(permuted_bases):
    """On a vertex-permuted copy, the rows of a smooth embedding (the first eigenfunctions,
    pulled through the true map) find the same nearest rows locally as exhaustively: the map is
    continuous, so every vertex's partner lies near its samples' partners; the samples' own
    search (``only_samples``) agrees on the samples and leaves the rest at -1."""
    x, y, perm, bx, by = permuted_bases
    C = p2p_to_fmap(perm, bx, by, 20, 20)
    query, reference = by.values[:, :20], bx.values[:, :20] @ C.T
    exact = nearest_neighbor(query, reference, precision="double")
    sx, sy = _sampling(x, 80), _sampling(y, 80)
    local = local_nearest(query, reference, sy, sx, precision="double")
    np.testing.assert_array_equal(local, exact)
    only = local_nearest(query, reference, sy, sx, precision="double", only_samples=True)
    np.testing.assert_array_equal(only[sy.index], exact[sy.index])
    assert (np.delete(only, sy.index) == -1).all()
    with pytest.raises(ParameterError, match="one row per vertex"):
        local_nearest(query[:-1], reference, sy, sx)
    with pytest.raises(ParameterError, match="coarse"):
        local_nearest(query, reference, sy, sx, coarse=np.zeros(3, dtype=np.int64))
    # fmap_to_p2p with the samplings is the same search
    np.testing.assert_array_equal(
        fmap_to_p2p(C, bx, by, mode="orthogonal", precision="double", samplings=(sx, sy)), exact
    )


def test_surface_sampling_of_repeated_points_gives_distinct_samples_and_no_empty_cell():
    """Points that are copies of each other (a mesh with duplicated vertices): at most as many
    samples as distinct points, every sample distinct and in its own non-empty cell, so every
    ring holds vertices; NaN rows are refused by the local search."""
    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(*[np.arange(4.0)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    points = np.repeat(grid, 15, axis=0)
    sm = surface_sampling(points, np.full(len(points), 25 / len(points)), 100)
    assert len(np.unique(sm.index)) == len(sm.index) <= len(grid)
    assert (np.diff(sm.start) > 0).all() and (np.diff(sm.ring_start) > 0).all()
    embed = rng.normal(size=(len(points), 5))
    bad = embed.copy()
    bad[3] = np.nan
    with pytest.raises(ParameterError, match="NaN"):
        local_nearest(bad, embed, sm, sm)


def test_spread_samples_are_chosen_by_position_only(permuted_bases):
    """A vertex-permuted copy gets the same points (ties broken by position, the first sample
    the farthest from the centroid), and a mesh in other units the same ones."""
    from torchfmap.fmap.nearest import spread_samples
    from torchfmap.operators import laplacian

    x, y, perm = permuted_bases[:3]
    mass_x, mass_y = laplacian(x)[1].diagonal(), laplacian(y)[1].diagonal()
    sx, sy = spread_samples(x.vertices, mass_x, 50), spread_samples(y.vertices, mass_y, 50)
    np.testing.assert_array_equal(np.sort(perm[sy]), sx)  # y vertex i is x vertex perm[i]
    np.testing.assert_array_equal(spread_samples(1e3 * x.vertices, 1e6 * mass_x, 50), sx)
