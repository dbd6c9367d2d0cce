"""Match results (``torchfmap.matching.results``): ``refine_result`` refines an unrefined result with a
refiner, and with landmarks keeps a refinement only if it does not raise the geodesic distortion
(``keeps_refinement``, the one guard)."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, match
from torchfmap.bases import prepare_shape
from torchfmap.evaluate.scores import landmarks_from_gt
from torchfmap.fmap import Refined
from torchfmap.kinds import KINDS
from torchfmap.matching.quality import DISTORTION_RESOLUTION, geodesic_distortion
from torchfmap.matching.results import keeps_refinement, refine_result


def test_the_distortion_guard():
    assert keeps_refinement(None, None)  # no landmarks: no score, always kept
    assert keeps_refinement(0.2, 0.2) and keeps_refinement(0.2, 0.1)
    assert keeps_refinement(0.2, 0.2 * (1 + DISTORTION_RESOLUTION))  # a rise within the resolution
    assert not keeps_refinement(0.2, 0.2 * (1 + DISTORTION_RESOLUTION) + 1e-12)


def test_refine_result_is_matchs_refinement_and_drops_a_worse_map(bent_pair):
    """``refine_result(match(..., refine=None), kind.refiner(...), *shapes)`` is
    ``match(..., refine=...)``; a refiner that scatters the map is dropped (``refined=False``,
    the start kept); a refined result is not refined again."""
    x, y, gt = bent_pair
    lm = landmarks_from_gt(x, gt, 8)
    shapes = (prepare_shape(x, 40), prepare_shape(y, 40))
    start = match(x, y, landmarks=lm, basis="laplacian", k=20, shapes=shapes)
    refiner = KINDS["laplacian"].refiner("zoomout", k_final=40, landmarks=lm)
    refined = refine_result(start, refiner, *shapes)
    direct = match(x, y, landmarks=lm, basis="laplacian", k=20, refine="zoomout", k_final=40, shapes=shapes)
    np.testing.assert_array_equal(refined.p2p_yx, direct.p2p_yx)
    assert refined.refined and direct.refined and "refine" in refined.timings
    assert refined.distortion == pytest.approx(geodesic_distortion(*shapes, refined.p2p_yx))

    def scattering(C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds=None):
        bad = np.random.default_rng(0).integers(0, x.n_vertices, y.n_vertices)
        return Refined(C_xy, bad, basis_x, basis_y, seeds)

    dropped = refine_result(start, scattering, *shapes)
    assert not dropped.refined and dropped.distortion == start.distortion
    np.testing.assert_array_equal(dropped.p2p_yx, start.p2p_yx)
    unguarded = refine_result(match(x, y, basis="laplacian", k=20, shapes=shapes), scattering, *shapes)
    assert unguarded.refined  # without landmarks there is no score: the refinement is kept
    with pytest.raises(ParameterError, match="unrefined result"):
        refine_result(refined, refiner, *shapes)
