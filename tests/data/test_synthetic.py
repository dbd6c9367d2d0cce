"""Synthetic meshes (``torchfmap.data.synthetic``): icosphere sizes, the shipped demo pair,
``stretch_deform``."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError
from torchfmap.data import demo_pair, icosphere, make_demo_pair, stretch_deform

from ..conftest import bumpy_blob


def test_shipped_demo_pair_is_consistent():
    a, b, gt = demo_pair()
    assert a.n_vertices == b.n_vertices == len(gt)
    assert np.array_equal(np.sort(gt), np.arange(a.n_vertices))
    # regenerating gives the same files (the generator is deterministic)
    a2, b2, gt2 = make_demo_pair()
    assert np.array_equal(gt, gt2)
    assert np.allclose(a.vertices, a2.vertices, atol=1e-7) and np.allclose(b.vertices, b2.vertices, atol=1e-7)
    # the bend is near-isometric: areas agree to 1 %
    assert abs(a.area - b.area) < 0.01 * a.area


def test_stretch_deform_keeps_ids_and_is_not_isometric():
    """Same faces and vertex count (ground truth = identity), deterministic, identity at
    strength 0; at strength 1 the limb scaling alone stretches edges near its centre by up to
    1 + 0.6 = 1.6, so some edge grows by more than 1.5x."""
    x = bumpy_blob(3)
    y = stretch_deform(x, seed=3, strength=1.0)
    np.testing.assert_array_equal(y.faces, x.faces)
    np.testing.assert_array_equal(stretch_deform(x, seed=3, strength=1.0).vertices, y.vertices)
    np.testing.assert_allclose(stretch_deform(x, seed=3, strength=0.0).vertices, x.vertices, atol=0)
    ratio = y.edge_lengths / x.edge_lengths
    assert ratio.max() > 1.5
    with pytest.raises(ParameterError, match="strength"):
        stretch_deform(x, strength=-1.0)


def test_icosphere_sizes():
    for s in range(4):
        assert icosphere(s).n_vertices == 10 * 4**s + 2
