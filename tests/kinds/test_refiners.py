"""Refiners (``torchfmap.kinds.refiners``): the anchors of eigenbasis ZoomOut, from landmarks
and from per-vertex features, each block weighing alike."""

from __future__ import annotations

import numpy as np

from torchfmap.bases import prepare_shape
from torchfmap.evaluate.scores import geodesic_errors, gt_from_map
from torchfmap.fmap import p2p_to_fmap
from torchfmap.kinds.refiners import ZoomOut, stacked_anchors


def test_stacked_anchors_weigh_every_block_alike_whatever_its_units():
    """Each block is divided by its mean row norm on ``y``: a block given in other units (x 1000)
    stacks to the same arrays; a single block is passed on as given, none gives None."""
    rng = np.random.default_rng(0)
    a = (rng.normal(size=(30, 4)), rng.normal(size=(20, 4)))
    b = (rng.normal(size=(30, 2)), rng.normal(size=(20, 2)))
    ax, ay = stacked_anchors(a, None, b)
    assert ax.shape == (30, 6) and ay.shape == (20, 6)
    for cols, (bx, by) in ((slice(0, 4), a), (slice(4, 6), b)):
        # one block's rows on y: mean norm 1, and x scaled by the same number
        np.testing.assert_allclose(np.linalg.norm(ay[:, cols], axis=1).mean(), 1.0, rtol=1e-12)
        np.testing.assert_allclose(ax[:, cols] * np.linalg.norm(by, axis=1).mean(), bx, rtol=1e-12)
    big = stacked_anchors(a, (1000 * b[0], 1000 * b[1]))
    np.testing.assert_allclose(big[0], ax, rtol=1e-12)
    np.testing.assert_allclose(big[1], ay, rtol=1e-12)
    assert stacked_anchors(None, a) is a and stacked_anchors(None, None) is None


def test_zoomout_with_features_that_correspond_carries_a_map_from_no_information(permuted_bases):
    """Features that correspond exactly (coordinates; on a permuted copy the same rows permuted):
    from a random start, where eigenbasis ZoomOut alone stays at chance, the features bring the
    map well below chance, and the true map is a fixed point."""
    x, y, perm, _, _ = permuted_bases
    shapes = (prepare_shape(x, 40), prepare_shape(y, 40))
    bx, by = (s.eigenbasis.truncated(15) for s in shapes)
    feats = (x.vertices, x.vertices[perm])
    start = np.random.default_rng(0).integers(0, x.n_vertices, y.n_vertices)
    gt = gt_from_map(perm)
    C = p2p_to_fmap(start, bx, by)
    chance = geodesic_errors(x, ZoomOut(40)(C, start, *shapes, bx, by).p2p_yx, gt).mean()
    guided = ZoomOut(40, features=feats)(C, start, *shapes, bx, by)
    assert geodesic_errors(x, guided.p2p_yx, gt).mean() < 0.5 * chance
    assert guided.basis_x.k == 40 and guided.C_xy.shape == (40, 40)
    kept = ZoomOut(40, features=feats)(p2p_to_fmap(perm, bx, by), perm, *shapes, bx, by)
    np.testing.assert_array_equal(kept.p2p_yx, perm)


def test_dense_pairs_match_and_refine_on_samples_as_well_as_exhaustively(permuted_pair, monkeypatch):
    """Past ``LOCAL_SEARCH_PAIRS`` (lowered here so a small pair crosses it) the raw point map
    and ZoomOut run on surface samples and search locally; on a vertex-permuted copy they find
    the true map as well as the exhaustive paths do, and the samplings are kept in the shapes."""
    import torchfmap as tf
    import torchfmap.kinds.refiners as refiners

    x, y, perm, _ = permuted_pair
    exact = tf.match(x, y, k=20, refine="zoomout")
    monkeypatch.setattr(refiners, "LOCAL_SEARCH_PAIRS", 1)
    monkeypatch.setattr(refiners, "SURFACE_SAMPLES", 200)
    shapes = tuple(tf.prepare_shape(m, 40) for m in (x, y))
    dense = tf.match(x, y, k=20, refine="zoomout", shapes=shapes)
    assert refiners.is_dense(*shapes)
    assert all(("surface_sampling", 200) in s.derived for s in shapes)
    for attr in ("p2p_yx_initial", "p2p_yx"):
        assert np.mean(getattr(dense, attr) == perm) >= np.mean(getattr(exact, attr) == perm) - 0.02
    assert np.mean(dense.p2p_yx == perm) > 0.95


def test_shape_samplings_do_not_depend_on_the_meshs_units(permuted_pair):
    """A prepared shape's operators live in its unit-area frame and its vertices in the file's
    units: the surface sampling of a mesh in millimetres is the one in metres (same samples)."""
    import torchfmap as tf
    from torchfmap.kinds.refiners import shape_sampling

    x = permuted_pair[0]
    base = shape_sampling(tf.prepare_shape(x, 10), 200).index
    for scale in (0.02, 100.0):
        scaled = tf.Mesh(x.vertices * scale, x.faces)
        np.testing.assert_array_equal(shape_sampling(tf.prepare_shape(scaled, 10), 200).index, base)


def test_icp_on_a_dense_pair_searches_locally_and_keeps_the_true_map(permuted_bases, monkeypatch):
    """ICP past ``LOCAL_SEARCH_PAIRS`` (lowered here) converts every point map locally: the true
    map of a permuted copy stays a fixed point."""
    import torchfmap as tf
    import torchfmap.kinds.refiners as refiners

    x, y, perm, _, _ = permuted_bases
    monkeypatch.setattr(refiners, "LOCAL_SEARCH_PAIRS", 1)
    monkeypatch.setattr(refiners, "SURFACE_SAMPLES", 150)
    shapes = tuple(tf.prepare_shape(m, 20) for m in (x, y))
    bx, by = (s.eigenbasis.truncated(20) for s in shapes)
    C = tf.fmap.p2p_to_fmap(perm, bx, by)
    refined = refiners.ICP()(C, perm, *shapes, bx, by)
    assert np.mean(refined.p2p_yx == perm) > 0.99
