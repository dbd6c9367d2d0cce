"""Seeds: curvature against closed forms, farthest-point sampling, features, coverage growth."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import (
    ParameterError,
    SeedError,
    coverage_seeds,
    curvature_features,
    farthest_point_sampling,
    gaussian_curvature,
    heat_kernels,
    laplacian,
    mass_matrix,
    mean_curvature,
)
from torchfmap.data import icosphere
from torchfmap.seeds import heat_support_radius

from .conftest import random_rotation


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
    with pytest.raises(ParameterError, match="curvature kind"):
        curvature_features(blob, 3, kind="principal")
