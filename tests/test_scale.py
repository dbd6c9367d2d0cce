"""Scale invariance: every shape is prepared in its unit-area frame, so a match does not depend
on the units of either mesh (every basis kind, raw and refined; the learned path's ZoomOut)."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap.bases import KINDS, prepare_shape
from torchfmap.eval import Correspondence, landmarks_from_gt
from torchfmap.pipeline import match

from .conftest import bend, bumpy_blob

#: Scales of the target: not powers of two (so the unit-area frames differ by round-off), and 2
#: (a power of two: exactly the same frame).
SCALES = (1e-3, 2.0, 1e3)


@pytest.fixture(scope="module")
def pair():
    x = bumpy_blob(2)
    perm = np.random.default_rng(5).permutation(x.n_vertices)
    y = x.copy(bend(x.vertices, 0.3)).permuted(perm)
    gt = Correspondence(idx_x=perm, idx_y=np.arange(y.n_vertices))
    return x, y, landmarks_from_gt(x, gt, 6)


def _agree(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean(a == b))


@pytest.mark.parametrize("refine", [None, "zoomout"])
@pytest.mark.parametrize("name", list(KINDS))
def test_match_of_a_scaled_target_is_the_same_map(pair, name, refine):
    """``match(x, c y) == match(x, y)``. The frames of ``c y`` and ``y`` differ by round-off
    (a relative 1e-16), which moves the bases by far less than the gap between a vertex's
    nearest and second-nearest match except at exact near-ties: the point maps agree on (at
    least) 99 % of the vertices and the functional maps to 1e-8 of their size; at ``c = 2``
    (exact in floating point) they are identical."""
    x, y, lm = pair
    landmarks = lm if KINDS[name].needs_landmarks else None
    ref = match(x, y, landmarks=landmarks, basis=name, k=20, refine=refine)
    for c in SCALES:
        out = match(x, y.scaled(c), landmarks=landmarks, basis=name, k=20, refine=refine)
        if c == 2.0:
            np.testing.assert_array_equal(out.p2p_yx, ref.p2p_yx)
        assert _agree(out.p2p_yx, ref.p2p_yx) >= 0.99, c
        assert _agree(out.p2p_yx_initial, ref.p2p_yx_initial) >= 0.99, c
        np.testing.assert_allclose(out.C_xy, ref.C_xy, atol=1e-8 * np.abs(ref.C_xy).max())
    # both shapes scaled differently: still the same map
    both = match(x.scaled(1e-3), y.scaled(1e3), landmarks=landmarks, basis=name, k=20, refine=refine)
    assert _agree(both.p2p_yx, ref.p2p_yx) >= 0.99


def test_prepared_shapes_live_in_the_unit_area_frame(pair):
    x, _, _ = pair
    for c in SCALES:
        shape = prepare_shape(x.scaled(c), 10)
        assert shape.area == pytest.approx(1.0, rel=1e-12)
        assert shape.operators[1].sum() == pytest.approx(1.0, rel=1e-12)
        lam, ref = shape.eigenbasis.eigenvalues, prepare_shape(x, 10).eigenbasis.eigenvalues
        # the first eigenvalue is 0 up to the solver's round-off relative to the spectrum
        np.testing.assert_allclose(lam, ref, rtol=1e-8, atol=1e-10 * ref.max())
    L, B = prepare_shape(x, 0).operators
    given = prepare_shape(x.scaled(3.0), 0, operators=(L, 9.0 * B))
    assert given.scale == 1.0 and given.area == pytest.approx(9.0)  # the given mass's total


def test_learned_path_zoomout_of_a_scaled_target_is_the_same_map(pair):
    from torchfmap.nn.inference import refine_p2p

    x, y, _ = pair
    start = np.random.default_rng(0).integers(0, x.n_vertices, y.n_vertices)
    ref = refine_p2p(x, y, start, k0=10, k_final=30)
    assert _agree(refine_p2p(x, y.scaled(1e3), start, k0=10, k_final=30), ref) >= 0.99
