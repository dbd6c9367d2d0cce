"""Match results (``torchfmap.results``): refining an unrefined result is the same step as
``match(refine=...)``, and a result is refined once."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import match
from torchfmap.errors import ParameterError
from torchfmap.results import refine_result


def test_refine_result_is_the_refinement_of_match_and_runs_once(bent_pair):
    x, y, _ = bent_pair
    start = match(x, y, k=12)
    refined = refine_result(start, "icp")
    np.testing.assert_array_equal(refined.p2p_yx, match(x, y, k=12, refine="icp").p2p_yx)
    assert refined.refined and not start.refined
    with pytest.raises(ParameterError, match="unrefined"):
        refine_result(refined, "icp")
