"""Partial-to-partial matching (torchfmap.matching.overlap, match(partial='both')) and the overlapping
cuts that make its test data (torchfmap.data.cuts.overlapping_cuts)."""

import numpy as np
import pytest

from torchfmap import match, prepare_shape
from torchfmap.data import demo_pair
from torchfmap.data.cuts import cut_plane, overlapping_cuts
from torchfmap.errors import ParameterError
from torchfmap.evaluate.partial import overlap_iou
from torchfmap.matching.overlap import PairMatchResult, consistent_core, match_partial_pair, trilaterate


@pytest.fixture(scope="module")
def blob_cuts():
    whole = demo_pair()[0]
    a, b = overlapping_cuts(whole, seed=0)
    return whole, a, b


def _mass(mesh):
    return prepare_shape(mesh, 0).operators[1].diagonal()


def test_overlapping_cuts_overlap_as_asked(blob_cuts):
    whole, a, b = blob_cuts
    area = _mass(whole)  # any scale: shares are ratios
    common = area[np.intersect1d(a.vertices, b.vertices)].sum()
    for part in (a, b):
        np.testing.assert_array_equal(part.mesh.vertices, whole.vertices[part.vertices])
        assert 0.3 <= common / area[part.vertices].sum() <= 0.7
    with pytest.raises(ParameterError, match="shares"):
        overlapping_cuts(whole, shares=(0.7, 0.3))
    with pytest.raises(ParameterError, match="no two plane cuts"):
        overlapping_cuts(whole, shares=(0.999, 1.0))


def test_a_part_matched_with_itself_is_the_identity_on_all_of_it(blob_cuts):
    """Every vertex is its own twin (zero residual at every seed): the identity, overlap 1."""
    part = blob_cuts[1].mesh
    r = match(part, part, k=20, partial="both")
    assert isinstance(r, PairMatchResult) and r.kind == "partial_pair"
    np.testing.assert_array_equal(r.p2p_yx, np.arange(part.n_vertices))
    mass = _mass(part)
    everything = np.arange(part.n_vertices)
    assert (
        overlap_iou(r.overlap, everything, mass) == 1.0 and overlap_iou(r.overlap_y, everything, mass) == 1.0
    )
    assert r.overlap.shape == r.overlap_y.shape == (part.n_vertices,)
    assert r.overlap.min() >= 0 and r.overlap.max() <= 1


@pytest.mark.parametrize("n_landmarks", [0, 5])
def test_two_cuts_of_the_blob(blob_cuts, n_landmarks):
    """Two plane cuts of the blob, without landmarks and with 5 on the overlap (the blob has few
    features: landmarks help it most). Bounds from the problem: marking all of a
    part gives IoU = its overlap share, so an estimate that locates the overlap beats that
    share; the map on the marked overlap is off by less than the overlap's own extent (a tenth
    of the whole's sqrt(area), against a region about 0.4 of it across), and far below a random
    map's mean error (about 0.4)."""
    whole, a, b = blob_cuts
    in_a, in_b = np.isin(a.vertices, b.vertices), np.isin(b.vertices, a.vertices)
    on_b = {v: j for j, v in enumerate(b.vertices)}
    common = np.flatnonzero(in_a)
    pick = common[np.linspace(0, len(common) - 1, max(n_landmarks, 1)).astype(int)]
    landmarks = np.array([[i, on_b[a.vertices[i]]] for i in pick]) if n_landmarks else None
    r = match(a.mesh, b.mesh, k=20, refine="zoomout", partial="both", landmarks=landmarks)
    mass_a, mass_b = _mass(a.mesh), _mass(b.mesh)
    share_a, share_b = mass_a[in_a].sum() / mass_a.sum(), mass_b[in_b].sum() / mass_b.sum()
    assert overlap_iou(r.overlap, np.flatnonzero(in_a), mass_a) > share_a
    assert overlap_iou(r.overlap_y, np.flatnonzero(in_b), mass_b) > share_b
    shape_w = prepare_shape(whole, 0)
    marked = np.flatnonzero(in_b & (r.overlap_y > 0.5))
    truth, images = b.vertices[marked], a.vertices[r.p2p_yx[marked]]
    err = [shape_w.distances.distances(np.array([t]))[0, i] for t, i in zip(truth, images, strict=True)]
    assert np.mean(err) < 0.1


def test_either_order_gives_the_same_overlaps(blob_cuts):
    """The larger part plays the whole either way: swapping the inputs swaps the overlaps."""
    _, a, b = blob_cuts
    shapes = (prepare_shape(a.mesh, 20), prepare_shape(b.mesh, 20))
    ab = match_partial_pair(*shapes, k=20)
    ba = match_partial_pair(*shapes[::-1], k=20)
    np.testing.assert_allclose(ab.overlap, ba.overlap_y)
    np.testing.assert_allclose(ab.overlap_y, ba.overlap)
    assert ab.p2p_yx.shape == (b.n_vertices,) and ba.p2p_yx.shape == (a.n_vertices,)


def test_trilateration_and_core_of_the_true_map(blob_cuts):
    """With true seeds on the overlap, every overlap vertex has an exact twin (residual 0);
    the core of the identity map of a part onto itself is all of it."""
    _, a, _ = blob_cuts
    shape = prepare_shape(a.mesh, 0)
    n = a.n_vertices
    assert consistent_core(shape, shape, np.arange(n)).all()
    seeds = np.stack([np.arange(0, n, n // 30)] * 2, axis=1)
    p2p, res, back, res_back = trilaterate(shape, shape, seeds)
    np.testing.assert_array_equal(p2p, np.arange(n))
    np.testing.assert_array_equal(back, np.arange(n))
    assert res.max() == 0 and res_back.max() == 0


def test_partial_both_refuses_bad_input(blob_cuts):
    _, a, b = blob_cuts
    for bad in ("yes", "Both", 2, None):
        with pytest.raises(ParameterError, match="False, True .* or 'both'"):
            match(a.mesh, b.mesh, k=10, partial=bad)
    with pytest.raises(ParameterError, match="partial='both'.*basis"):
        match(a.mesh, b.mesh, k=10, partial="both", basis="diffusion")
    with pytest.raises(ParameterError, match="partial='both'.*times"):
        match(a.mesh, b.mesh, k=10, partial="both", times=[0.1])
    with pytest.raises(ParameterError, match="refine='icp'"):
        match(a.mesh, b.mesh, k=10, partial="both", refine="icp")
    shapes = (prepare_shape(a.mesh, 10), prepare_shape(b.mesh, 10))
    with pytest.raises(ParameterError, match="rounds >= 1"):
        match_partial_pair(*shapes, k=10, rounds=0)
    tiny = cut_plane(a.mesh, 0.05, normal=(1, 0, 0))  # 1e-4 of the area in other units
    with pytest.raises(ParameterError, match="units"):
        match(a.mesh, tiny.mesh.scaled(0.01), k=10, partial="both")
