"""Checks of match's arguments (``torchfmap.match_checks``): given bases of meshes of different
sizes, as ``torchfmap basis SRC TGT --landmarks`` writes them for any real pair."""

from __future__ import annotations

import numpy as np

from torchfmap import match, prepare_shape
from torchfmap.pipeline import match_bases
from torchfmap.seeds import farthest_point_sampling

from .conftest import bumpy_blob


def test_given_bases_of_meshes_of_different_sizes_solve_and_refine():
    """The pair (642 and 162 vertices) built together at corresponding landmarks, given back to
    match: solved in them (no comparison of per-vertex arrays of different lengths)."""
    x, y = bumpy_blob(3), bumpy_blob(2)  # one shape at two resolutions: vertex i of y is vertex i of x
    lm_y = farthest_point_sampling(y, 6)
    landmarks = np.stack([lm_y, lm_y], axis=1)
    sx, sy = prepare_shape(x, 0), prepare_shape(y, 0)
    bx, by, _ = match_bases(sx, sy, "diffusion", 12, landmarks)
    result = match(x, y, bases=(bx, by), refine="icp")
    assert result.p2p_yx.shape == (y.n_vertices,) and result.kind == "diffusion"
    assert result.p2p_yx.max() < x.n_vertices
