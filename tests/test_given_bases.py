"""match(bases=...) with bases built as a pair: solved as the kind they are (corresponding
columns), refined like it, and refused in swapped order."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import Basis, ParameterError
from torchfmap.bases.prepared import prepare_shape
from torchfmap.eval import evaluate_map, landmarks_from_gt
from torchfmap.pipeline import match, match_bases


@pytest.fixture(scope="module")
def saved(bent_pair, tmp_path_factory):
    x, y, gt = bent_pair
    lm = landmarks_from_gt(x, gt, 8)
    bx, by, _ = match_bases(prepare_shape(x, 0), prepare_shape(y, 0), "diffusion", 30, lm)
    folder = tmp_path_factory.mktemp("bases")
    bx.save(folder / "a.npz")
    by.save(folder / "b.npz")
    return lm, Basis.load(folder / "a.npz"), Basis.load(folder / "b.npz")


def test_pair_bases_from_files_match_like_the_landmark_call(bent_pair, saved):
    x, y, gt = bent_pair
    lm, bx, by = saved
    direct = match(x, y, landmarks=lm, basis="diffusion", k=30)
    given = match(x, y, bases=(bx, by))
    assert given.kind == "diffusion"  # the files' kind, not 'stack'
    e_direct = evaluate_map(x, y, direct.p2p_yx, gt, max_points=300)[0].mean_error
    e_given = evaluate_map(x, y, given.p2p_yx, gt, max_points=300)[0].mean_error
    # the same bases and the same pull to C = I; the descriptors differ (no landmark kernels)
    assert e_given <= 1.5 * e_direct + 0.01, (e_given, e_direct)
    refined = match(x, y, bases=(bx, by), refine="zoomout")  # the kind's own refinement
    assert refined.seeds is not None and refined.p2p_yx.shape == (y.n_vertices,)


def test_swapped_bases_are_refused(bent_pair, saved):
    x, y, _ = bent_pair
    _, bx, by = saved
    with pytest.raises(ParameterError, match="fit the meshes in the other order"):
        match(x, y, bases=(by, bx))
    np.testing.assert_array_equal(bx.pair_landmarks, by.pair_landmarks)
