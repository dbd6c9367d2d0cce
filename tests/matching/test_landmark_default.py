"""The landmark default (``torchfmap.matching.landmark_default``): the landmarks' cross-validation, its
scores, and the rule by which it overrides the distortion's choice."""

from __future__ import annotations

import numpy as np
import pytest

import torchfmap.matching.landmark_default as landmark_default
from torchfmap import ParameterError, match, prepare_shape
from torchfmap.evaluate.scores import landmarks_from_gt
from torchfmap.matching.landmark_default import AUTO_KINDS, CV_RATIO, landmark_scores


def test_held_out_landmark_errors_are_distances_to_the_true_matches(bent_pair):
    """Each kind's score is the mean geodesic distance (units of sqrt(area)) between where its
    fold maps send held-out landmarks and their true matches: finite, >= 0, below the shape's
    diameter; on this near-isometric pair the eigenbasis sends them within a few edges."""
    x, y, gt = bent_pair
    pairs = landmarks_from_gt(x, gt, 6)
    sx, sy = prepare_shape(x, 30), prepare_shape(y, 30)
    scores = landmark_scores(sx, sy, pairs, AUTO_KINDS, 12)
    assert set(scores) == set(AUTO_KINDS)
    diameter = sx.distances.distances(pairs[:1, 0]).max()
    assert all(0 <= v < diameter for v in scores.values())
    edge = x.mean_edge_length / np.sqrt(x.area)
    assert scores["laplacian"] < 5 * edge
    with pytest.raises(ParameterError, match="3 or more are needed, got 2"):
        landmark_scores(sx, sy, pairs[:2], AUTO_KINDS, 12)


def test_landmark_descriptors_are_solved_once_per_landmark(bent_pair, monkeypatch):
    """The cross-validation's folds use subsets of the same landmarks: their descriptor columns
    are the whole set's columns, solved once per landmark and shape."""
    import torchfmap.matching.solve as solve

    x, y, gt = bent_pair
    pairs = landmarks_from_gt(x, gt, 6)
    sx, sy = prepare_shape(x, 30), prepare_shape(y, 30)
    whole = solve.match_descriptors(sx, sy, pairs)
    solved = []
    real = solve.landmark_descriptors
    monkeypatch.setattr(
        solve, "landmark_descriptors", lambda lm, **kw: solved.append(list(lm)) or real(lm, **kw)
    )
    fold = solve.match_descriptors(sx, sy, pairs[1::2])
    assert solved == []  # every landmark's columns were kept
    n_wks, per = whole[0].shape[1] - 2 * len(pairs), 2  # two heat kernels per landmark
    lm_cols = np.concatenate([np.arange(n_wks + per * i, n_wks + per * (i + 1)) for i in range(1, 6, 2)])
    for w, f in zip(whole, fold, strict=True):
        np.testing.assert_array_equal(f[:, :n_wks], w[:, :n_wks])
        np.testing.assert_allclose(f[:, n_wks:], w[:, lm_cols], rtol=1e-12, atol=0)


def test_a_clear_cross_validation_verdict_overrides_the_distortion_and_a_close_one_does_not(
    bent_pair, monkeypatch
):
    x, y, gt = bent_pair
    pairs = landmarks_from_gt(x, gt, 6)
    plain = match(x, y, landmarks=pairs, k=12)
    chosen = plain.kind
    assert plain.fold_scores and set(plain.fold_scores) == set(AUTO_KINDS)
    assert "held-out landmarks" in plain.scores()
    verdicts = {
        "clear": {chosen: 1.0, next(n for n in AUTO_KINDS if n != chosen): 0.9 * CV_RATIO},
        "close": {chosen: 1.0, next(n for n in AUTO_KINDS if n != chosen): 1.1 * CV_RATIO},
    }
    pref = landmark_default.AUTO_KINDS[0]
    for name, scores in verdicts.items():
        monkeypatch.setattr(landmark_default, "landmark_scores", lambda *a, s=scores, **kw: dict(s))
        result = match(x, y, landmarks=pairs, k=12, refine="icp")
        other = next(n for n in scores if n != chosen)
        if name == "close":
            assert result.kind == chosen
        else:  # the verdict's kind, refined, unless its map is more distorted than the eigenbasis's
            d = {n: c.distortion for n, c in result.candidates.items()}
            assert result.kind == (other if d[other] <= d[pref] else pref), d
        assert result.distortion <= result.candidates[pref].distortion  # never more distorted
        assert result.fold_scores == scores
    # too few landmarks to hold some out: no cross-validation, the distortion decides
    assert match(x, y, landmarks=pairs[:2], k=12).fold_scores == {}
