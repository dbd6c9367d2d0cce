"""Seeds (``torchfmap.seeds``): curvature against closed forms, farthest-point sampling, features,
coverage growth, corresponding, replaced and consistent seeds."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import (
    ParameterError,
    SeedError,
    coverage_seeds,
    curvature,
    curvature_features,
    farthest_point_sampling,
    gaussian_curvature,
    heat_kernels,
    laplacian,
    mass_matrix,
    mean_curvature,
)
from torchfmap.bases.prepared import prepare_shape
from torchfmap.data import icosphere
from torchfmap.fmap import build_problem
from torchfmap.matching.solve import match_bases
from torchfmap.seeds import consistent_seeds, corresponding_seeds, heat_support_radius, max_curvature_vertex

from .conftest import bumpy_blob, random_rotation


@pytest.mark.parametrize("radius", [1.0, 2.5])
def test_sphere_curvatures(radius):
    s = icosphere(3, radius=radius)
    assert np.allclose(mean_curvature(s), 1 / radius, rtol=1e-3)
    assert np.allclose(gaussian_curvature(s), 1 / radius**2, rtol=1e-2)


def test_gauss_bonnet(blob):
    k = gaussian_curvature(blob)
    area = mass_matrix(blob, "voronoi").diagonal()
    assert k @ area == pytest.approx(4 * np.pi, rel=1e-10)  # 2 pi chi, chi = 2


@pytest.mark.parametrize("metric", ["euclidean", "geodesic"])
def test_fps_deterministic_prefix_and_spread(blob, metric):
    a = farthest_point_sampling(blob, 15, metric=metric)
    b = farthest_point_sampling(blob, 15, metric=metric)
    assert np.array_equal(a, b) and len(np.unique(a)) == 15
    assert np.array_equal(farthest_point_sampling(blob, 6, metric=metric), a[:6])  # greedy prefix
    _, r6 = farthest_point_sampling(blob, 6, metric=metric, return_radius=True)
    _, r15 = farthest_point_sampling(blob, 15, metric=metric, return_radius=True)
    assert r15 < r6


def test_fps_start_and_landmarks(blob):
    seeds = farthest_point_sampling(blob, 5, start=17, metric="euclidean")
    assert seeds[0] == 17
    seeds = farthest_point_sampling(blob, 8, landmarks=[3, 99, 42], metric="euclidean")
    assert seeds[:3].tolist() == [3, 99, 42] and len(set(seeds)) == 8
    d = np.linalg.norm(blob.vertices[seeds[3]] - blob.vertices[[3, 99, 42]], axis=1).min()
    dists = np.min(np.linalg.norm(blob.vertices[:, None] - blob.vertices[[3, 99, 42]][None], axis=2), axis=1)
    assert d == pytest.approx(dists.max())  # the first FPS seed is the farthest from the landmarks


def test_curvature_start_is_pose_and_order_invariant(blob, rng):
    seeds = farthest_point_sampling(blob, 6, metric="euclidean")
    moved = blob.copy(blob.vertices @ random_rotation(rng).T + 1.0)
    assert np.array_equal(farthest_point_sampling(moved, 6, metric="euclidean"), seeds)
    perm = rng.permutation(blob.n_vertices)
    permuted = farthest_point_sampling(blob.permuted(perm), 6, metric="euclidean")
    assert np.array_equal(perm[permuted], seeds)


def test_curvature_features_find_the_bumps(blob):
    from torchfmap.data.synthetic import _BUMPS

    feats = curvature_features(blob, 6)
    assert 1 <= len(feats) <= 6 and len(set(feats)) == len(feats)
    # the strongest features sit on the bump tips (directions of the Gaussian bumps)
    unit = blob.vertices / np.linalg.norm(blob.vertices, axis=1, keepdims=True)
    tips = np.array([np.argmax(unit @ (np.asarray(d) / np.linalg.norm(d))) for d, _, _ in _BUMPS])
    dist = np.linalg.norm(blob.vertices[feats[0]] - blob.vertices[tips], axis=1).min()
    assert dist < 0.5 * np.sqrt(blob.area / 6)
    assert np.array_equal(curvature_features(blob, 6), feats)  # deterministic


def test_coverage_growth_covers_and_needs_more_seeds_for_smaller_t(blob):
    ops = laplacian(blob)
    counts = []
    for t in (1e-2, 2e-3):
        seeds = coverage_seeds(blob, t, eps=1e-3, operators=ops)
        K = heat_kernels(ops, seeds, [t * blob.area])[0]
        covered = (np.abs(K) > 1e-3 * np.abs(K).max(axis=0)).any(axis=1)
        assert covered.all()
        counts.append(len(seeds))
    assert counts[1] > counts[0]
    assert heat_support_radius(1.0, np.exp(-1)) == pytest.approx(2.0)


def test_seed_errors(blob):
    with pytest.raises(ParameterError, match=r"k must be in \[1, 642\]"):
        farthest_point_sampling(blob, 700)
    with pytest.raises(SeedError, match="duplicates"):
        farthest_point_sampling(blob, 5, landmarks=[1, 1])
    with pytest.raises(SeedError, match="out of range"):
        farthest_point_sampling(blob, 5, start=642)
    with pytest.raises(ParameterError, match="metric"):
        farthest_point_sampling(blob, 5, metric="manhattan")
    with pytest.raises(ParameterError, match="t=0"):
        coverage_seeds(blob, 0.0)
    with pytest.raises(ParameterError, match="curvature measure"):
        curvature_features(blob, 3, measure="principal")


def test_curvature_names_its_kinds():
    mesh = bumpy_blob(2)
    np.testing.assert_array_equal(curvature(mesh, "mean"), mean_curvature(mesh))
    np.testing.assert_array_equal(curvature(mesh, "abs_mean"), np.abs(mean_curvature(mesh)))
    np.testing.assert_array_equal(curvature(mesh, "gaussian"), gaussian_curvature(mesh))
    with pytest.raises(ParameterError, match="unknown curvature measure"):
        curvature(mesh, "max")


def test_max_curvature_vertex_finds_a_spike():
    """A sphere with one vertex pulled out by 40%: the largest |mean curvature| (after 1-ring
    smoothing) is at the spike or in its 1-ring."""
    mesh = icosphere(3)
    spike = 77
    v = mesh.vertices.copy()
    v[spike] *= 1.4
    spiky = mesh.copy(v)
    ring = np.unique(mesh.faces[np.any(mesh.faces == spike, axis=1)])
    assert max_curvature_vertex(spiky) in ring
    assert max_curvature_vertex(spiky, smooth_steps=0) == spike
    # and on the asymmetric blob it is a vertex index, stable under rigid motion
    blob = bumpy_blob(2)
    assert max_curvature_vertex(blob) == max_curvature_vertex(blob.copy(blob.vertices + 5.0))


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


def test_replace_seeds_never_moves_a_seed_beyond_the_radius(permuted_pair):
    """A seed whose vertex another seed took stayed where the map put it, however far (it could
    not stay): here seed A's map points at seed B's vertex one edge away, and B's own map points
    beyond the covering radius. Now no seed moves onto another's vertex, so every seed ends
    within the radius sqrt(1/S) of where it was, and the seeds stay distinct."""
    from torchfmap.seeds import replace_seeds

    x, y, perm, lm = permuted_pair
    inverse = np.argsort(perm)
    sx, sy = prepare_shape(x, 0), prepare_shape(y, 0)
    seeds = corresponding_seeds(x, y, lm, 12, distances=(sx.distances, sy.distances))
    radius = np.sqrt(1.0 / len(seeds))
    a, b = len(lm), len(lm) + 1
    (a_x, b_x), b_old = seeds[[a, b], 0], int(seeds[b, 1])
    ring = y.edges[(y.edges == b_old).any(axis=1)].ravel()
    a_old = int(next(v for v in ring if v != b_old and v not in set(seeds[:, 1])))
    moved = seeds.copy()
    moved[a, 1] = a_old  # A one edge from B
    far_x = int(np.argmax(sx.distances(b_x)))
    p2p = perm.copy()
    near_b = sy.distances(b_old) < 1.2 * radius  # B's neighbourhood is mapped far from B
    p2p[near_b] = far_x
    p2p[inverse[a_x]] = far_x
    p2p[b_old] = a_x  # ... and B's vertex to A's seed: A's best image
    assert sx.distances(b_x)[far_x] > 1.2 * radius
    out = replace_seeds(sx.distances, sy.distances, moved, p2p, len(lm))
    np.testing.assert_array_equal(out[: len(lm)], moved[: len(lm)])
    shift = [sy.distances(int(old))[int(new)] for old, new in zip(moved[:, 1], out[:, 1], strict=True)]
    assert max(shift) < radius, shift
    assert len(set(out[:, 1].tolist())) == len(out)


def test_consistent_seeds_keep_round_trips_and_drop_the_rest():
    x = bumpy_blob(2)
    shape = prepare_shape(x, 0)
    s = farthest_point_sampling(x, 12)
    ident = consistent_seeds(shape.distances, s, s, s)  # a map and its inverse that agree
    np.testing.assert_array_equal(ident, np.stack([s, s], axis=1))
    back = s.copy()
    back[3] = s[7]  # the round trip of seed 3 lands on another seed: far from it
    images = s.copy()
    images[5] = s[4]  # two seeds sent to one vertex: the second is dropped
    kept = consistent_seeds(shape.distances, s, images, back)
    assert 3 not in [list(s).index(v) for v in kept[:, 0]] and len(kept) == 10
    assert len(np.unique(kept[:, 1])) == len(kept)
    with pytest.raises(ParameterError, match="one length"):
        consistent_seeds(shape.distances, s, s[:3], s)


@pytest.mark.parametrize("t", [0.0, -1.0, float("nan"), float("inf")])
def test_coverage_seeds_bad_time(sphere2, t):
    with pytest.raises(ParameterError, match="diffusion time must be finite and > 0"):
        coverage_seeds(sphere2, t)
