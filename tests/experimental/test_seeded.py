"""The classical self-seeded second stage (``torchfmap.experimental.seeded``): stage 1 is the
ZoomOut map, stage 2 the match at the seeds where it agrees both ways; the core ``match`` and
the CLI no longer offer it."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, match
from torchfmap.bases.prepared import prepare_shape
from torchfmap.cli import build_parser
from torchfmap.evaluate.scores import evaluate_map, landmarks_from_gt
from torchfmap.experimental.seeded import SEEDED_SEEDS, map_seeds, seeded_match


def test_seeded_match_solves_again_at_the_seeds_its_map_agrees_on(bent_pair):
    """Stage 1 is ``match(refine='zoomout')``; stage 2 is the eigenbasis match with the
    consistent seeds of stage 1 as landmarks (its ``seeds``), refined by ZoomOut; a second solve
    at agreeing seeds stays a good map."""
    x, y, gt = bent_pair
    result, first = seeded_match(x, y, k=20)
    np.testing.assert_array_equal(first.p2p_yx, match(x, y, k=20, refine="zoomout").p2p_yx)
    shape_x = prepare_shape(x, 40)
    C = first.C_xy
    seeds = map_seeds(shape_x, C, C.T, first.basis_x.values, first.basis_y.values, SEEDED_SEEDS)
    np.testing.assert_array_equal(result.seeds, seeds)
    again = match(x, y, k=20, landmarks=seeds, basis="laplacian", refine="zoomout")
    np.testing.assert_array_equal(result.p2p_yx, again.p2p_yx)
    assert result.distortion is not None and result.kind == "laplacian" and result.candidates == {}
    assert any(key.startswith("stage1:") for key in result.timings)
    errors = [evaluate_map(x, y, r.p2p_yx, gt, max_points=300)[0].mean_error for r in (first, result)]
    assert errors[1] <= 2.0 * errors[0] + 0.01


def test_seeded_match_refuses_what_would_change_its_stages_and_match_does_not_offer_it(bent_pair, capsys):
    x, y, gt = bent_pair
    for bad in (dict(landmarks=landmarks_from_gt(x, gt, 4)), dict(refine="icp"), dict(basis="hybrid")):
        with pytest.raises(ParameterError, match="seeded_match seeds a second solve"):
            seeded_match(x, y, k=20, **bad)
    with pytest.raises(ParameterError, match="got refine='seeded'"):
        match(x, y, k=20, refine="seeded")
    with pytest.raises(SystemExit):
        build_parser().parse_args(["match", "a.off", "b.off", "--out", "m.txt", "--refine", "seeded"])
    assert "invalid choice: 'seeded'" in capsys.readouterr().err
