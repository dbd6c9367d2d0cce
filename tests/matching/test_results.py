"""Match results (``torchfmap.matching.results``): ``refine_result`` refines an unrefined result with a
refiner under the one guard (``keeps_refinement``): cross-validated by held-out landmarks with
three or more, else judged by the geodesic distortion with landmarks."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, match
from torchfmap.bases import prepare_shape
from torchfmap.evaluate.scores import landmarks_from_gt
from torchfmap.fmap import Refined
from torchfmap.kinds import KINDS
from torchfmap.matching.landmark_default import (
    CV_REFINE_MIN_LANDMARKS,
    landmark_scores,
    refine_guarded,
    refinement_scores,
)
from torchfmap.matching.quality import DISTORTION_RESOLUTION, geodesic_distortion
from torchfmap.matching.results import RefineCheck, keeps_refinement, refine_result


def test_the_guard():
    assert keeps_refinement(0.2, 0.2) and keeps_refinement(0.2, 0.1)
    assert keeps_refinement(0.2, 0.2 * (1 + DISTORTION_RESOLUTION))  # a rise within the resolution
    assert not keeps_refinement(0.2, 0.2 * (1 + DISTORTION_RESOLUTION) + 1e-12)
    text = str(RefineCheck(0.05, 0.04, True, (0.03, 0.04)))
    assert (
        "kept" in text
        and "distortion 0.0500 -> 0.0400" in text
        and "held-out landmark error 0.0300 -> 0.0400" in text
    )
    assert RefineCheck(0.05, 0.04, True, (0.03, 0.04)).held_out_worse
    assert not RefineCheck(0.05, 0.04, True, (0.04, 0.03)).held_out_worse
    assert not RefineCheck(0.05, 0.04, True).held_out_worse


def test_refine_result_is_matchs_refinement_and_drops_a_worse_map(bent_pair):
    """``refine_result(match(..., refine=None), kind.refiner(...), *shapes)`` is
    ``match(..., refine=...)``; a refiner that scatters the map is dropped (``refined=False``,
    the start kept); a refined result is not refined again."""
    x, y, gt = bent_pair
    lm = landmarks_from_gt(x, gt, CV_REFINE_MIN_LANDMARKS - 1)  # too few to hold out: the distortion judges
    shapes = (prepare_shape(x, 40), prepare_shape(y, 40))
    start = match(x, y, landmarks=lm, basis="laplacian", k=20, shapes=shapes)
    refiner = KINDS["laplacian"].refiner("zoomout", k_final=40, landmarks=lm)
    refined = refine_result(start, refiner, *shapes)
    direct = match(x, y, landmarks=lm, basis="laplacian", k=20, refine="zoomout", k_final=40, shapes=shapes)
    np.testing.assert_array_equal(refined.p2p_yx, direct.p2p_yx)
    assert refined.refined and direct.refined and "refine" in refined.timings
    assert refined.distortion == pytest.approx(geodesic_distortion(*shapes, refined.p2p_yx))
    assert direct.refine_check.kept and direct.refine_check.held_out is None

    def scattering(C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds=None):
        bad = np.random.default_rng(0).integers(0, x.n_vertices, y.n_vertices)
        return Refined(C_xy, bad, basis_x, basis_y, seeds)

    dropped = refine_result(start, scattering, *shapes)
    assert not dropped.refined and dropped.distortion == start.distortion
    assert not dropped.refine_check.kept
    np.testing.assert_array_equal(dropped.p2p_yx, start.p2p_yx)
    # without landmarks the distortion judges too (computed for the start and the refined map)
    plain = match(x, y, basis="laplacian", k=20, shapes=shapes)
    dropped = refine_result(plain, scattering, *shapes)
    assert not dropped.refined and dropped.distortion is None  # None: the match had no landmarks
    check = dropped.refine_check
    assert not check.kept
    assert (
        check.before == pytest.approx(geodesic_distortion(*shapes, plain.p2p_yx))
        and check.after > check.before
    )
    kept = refine_result(plain, KINDS["laplacian"].refiner("zoomout", k_final=40), *shapes)
    assert kept.refined and kept.refine_check.kept and kept.distortion is None
    with pytest.raises(ParameterError, match="unrefined result"):
        refine_result(refined, refiner, *shapes)


def test_held_out_landmarks_are_reported_and_warned_of_not_a_veto(bent_pair):
    """With enough landmarks the refinement is cross-validated: each fold's map (solved as
    ``landmark_scores`` solves it: the same raw held-out error) refined without its held-out
    landmarks. The figures are reported; the distortion decides (a scattering refiner is dropped
    by it), and a kept refinement whose folds moved the landmarks away is warned of."""
    import warnings

    from torchfmap.errors import MapWarning

    x, y, gt = bent_pair
    lm = landmarks_from_gt(x, gt, 8)
    shapes = (prepare_shape(x, 40), prepare_shape(y, 40))
    kind = KINDS["laplacian"]
    calls = []

    def make_scattering(fold_pairs, bar=False):
        def scattering(C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds=None):
            calls.append(len(fold_pairs))
            bad = np.random.default_rng(len(calls)).integers(0, x.n_vertices, y.n_vertices)
            return Refined(C_xy, bad, basis_x, basis_y, seeds)

        return scattering

    def make_identity(fold_pairs, bar=False):
        return lambda C, p2p, sx, sy, bx, by, seeds=None: Refined(C, p2p, bx, by, seeds)

    raw, worse = refinement_scores(*shapes, lm, kind, 20, make_scattering)
    assert len(calls) == 4 and set(calls) == {6}  # 4 folds of 8 landmarks, each refined with 6
    assert raw == pytest.approx(landmark_scores(*shapes, lm, ["laplacian"], 20)["laplacian"], rel=1e-12)
    assert worse > 2 * raw  # scattered maps land far from the held-out partners
    start = match(x, y, landmarks=lm, basis="laplacian", k=20, shapes=shapes)
    dropped = refine_guarded(start, kind, *shapes, lm, 20, make_scattering)
    assert not dropped.refined and not dropped.refine_check.kept  # by the distortion
    assert dropped.refine_check.held_out[1] > 2 * dropped.refine_check.held_out[0]
    np.testing.assert_array_equal(dropped.p2p_yx, start.p2p_yx)
    with warnings.catch_warnings():
        warnings.simplefilter("error", MapWarning)  # equal held-out errors: kept, no word
        kept = refine_guarded(start, kind, *shapes, lm, 20, make_identity)
    assert kept.refined and kept.refine_check.held_out[0] == kept.refine_check.held_out[1]
    # a kept refinement that moved held-out landmarks away: warned of, with its figures
    with pytest.warns(MapWarning, match=r"held-out landmarks away .* 0\.0100 -> 0\.0200 .*refine=None"):
        refine_result(start, make_identity(lm), *shapes, held_out=(0.01, 0.02))
    # too few landmarks, or given bases: no folds
    few = refine_guarded(start, kind, *shapes, lm[: CV_REFINE_MIN_LANDMARKS - 1], 20, make_identity)
    given = refine_guarded(start, kind, *shapes, lm, 20, make_identity, cross_validate=False)
    assert few.refine_check.held_out is None and given.refine_check.held_out is None
