"""Match results (``torchfmap.results``): ``refine_map``, the deprecated alias of a kind's
refinement."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import match
from torchfmap.bases import KINDS


def test_refine_map_is_a_deprecated_alias_and_the_fmap_layer_points_to_the_kinds(bent_pair):
    import torchfmap.fmap
    from torchfmap.pipeline import refine_map

    x, y, _ = bent_pair
    r = match(x, y, k=12)
    ctx = r._context
    args = (r.C_xy, r.p2p_yx, ctx.shape_x, ctx.shape_y, r.basis_x, r.basis_y, "icp")
    with pytest.warns(DeprecationWarning, match="refine"):
        old = refine_map(*args, kind="laplacian", k_final=12, mode="orthogonal")
    new = KINDS["laplacian"].refine(*args, k_final=12, mode="orthogonal")
    np.testing.assert_array_equal(old.p2p_yx, new.p2p_yx)
    with pytest.raises(AttributeError, match="get_kind"):
        torchfmap.fmap.refine_map  # noqa: B018
