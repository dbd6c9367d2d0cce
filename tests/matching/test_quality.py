"""Map scores without ground truth (torchfmap.matching.quality): geodesic distortion, orientation
agreement."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import Mesh, ParameterError, load_mesh
from torchfmap.bases.prepared import prepare_shape
from torchfmap.data import demo_pair
from torchfmap.matching.quality import distortion_anchors, geodesic_distortion, orientation_agreement

from ..conftest import bumpy_blob, data_path, random_rotation


@pytest.fixture(scope="module")
def shapes():
    x = bumpy_blob(3)
    perm = np.random.default_rng(5).permutation(x.n_vertices)
    y = x.permuted(perm)  # the same surface, vertices shuffled: y's vertex v is x's perm[v]
    return x, y, perm, prepare_shape(x, 0), prepare_shape(y, 0)


def test_true_map_of_an_isometry_has_no_distortion_and_others_do(shapes):
    x, y, perm, sx, sy = shapes
    assert geodesic_distortion(sx, sy, perm) == pytest.approx(0.0, abs=1e-12)
    scrambled = np.random.default_rng(0).integers(0, x.n_vertices, y.n_vertices)
    # a random map sends neighbours anywhere: its distortion is of the order of the distances
    # themselves (mean geodesic distance on a unit-area blob ~ 0.4)
    assert geodesic_distortion(sx, sy, scrambled) > 0.1
    # a map off by a fraction of the surface distorts by about that much, never more than 2x
    shifted = perm.copy()
    nbr = x.edges  # move every vertex to a neighbour: distortion <= 2 edge lengths
    step = dict(zip(nbr[:, 0].tolist(), nbr[:, 1].tolist(), strict=False))
    shifted = np.array([step.get(int(v), int(v)) for v in perm])
    edge = x.mean_edge_length / np.sqrt(x.area)
    assert 0 < geodesic_distortion(sx, sy, shifted) <= 2.5 * edge


def test_distortion_is_rigid_and_scale_invariant(shapes, rng):
    x, y, perm, sx, sy = shapes
    wrong = np.roll(perm, 7)
    base = geodesic_distortion(sx, sy, wrong)
    R = random_rotation(rng)
    y2 = y.copy(3.0 * y.vertices @ R.T + 1.0)
    anchors = distortion_anchors(sy)
    moved = geodesic_distortion(sx, prepare_shape(y2, 0), wrong, anchors)
    assert moved == pytest.approx(base, rel=1e-6)


def test_distortion_checks_the_map(shapes):
    x, y, perm, sx, sy = shapes
    with pytest.raises(ParameterError):
        geodesic_distortion(sx, sy, perm[:-1])
    with pytest.raises(ParameterError):
        geodesic_distortion(sx, sy, perm + x.n_vertices)


def test_orientation_agreement_tells_a_mirror_image(shapes):
    x, y, perm, sx, sy = shapes
    assert orientation_agreement(x, y, perm) == pytest.approx(1.0)
    # the mirror image of x, its faces reversed so that its normals point outwards again
    mirror = Mesh(x.vertices * np.array([-1.0, 1.0, 1.0]), x.faces[:, ::-1])
    assert orientation_agreement(x, mirror, np.arange(x.n_vertices)) == pytest.approx(-1.0)
    # a constant map has no image triangle at all
    assert orientation_agreement(x, y, np.zeros(y.n_vertices, dtype=np.int64)) == 0.0


def test_geodesic_distortion_of_a_part_reads_its_distances_in_the_wholes_units():
    """A part cut from the whole, with its exact map: in the whole's units (``area_ratio``) the
    distortion is only the cut's detours and the discretisation; read in the part's own unit-area
    frame, every distance is off by ``1 / sqrt(a) - 1`` of itself."""
    from torchfmap.data.cuts import cut_plane
    from torchfmap.matching.partial import area_ratio

    whole = demo_pair()[0]
    cut = cut_plane(whole, 0.6, seed=1)
    shapes = prepare_shape(whole, 0), prepare_shape(cut.mesh, 0)
    a = area_ratio(whole, cut.mesh)
    right = geodesic_distortion(*shapes, cut.vertices, area_ratio=a)
    wrong = geodesic_distortion(*shapes, cut.vertices)
    mean_distance = shapes[1].distances.distances(distortion_anchors(shapes[1])).mean() * np.sqrt(a)
    assert wrong > 0.5 * (1 / np.sqrt(a) - 1) * mean_distance
    assert right < 0.25 * wrong
    with pytest.raises(ParameterError, match="area_ratio"):
        geodesic_distortion(*shapes, cut.vertices, area_ratio=0.0)


def test_the_landmark_reading_check_judges_a_bounded_number_of_pairs(monkeypatch):
    """However many pairs a file holds, each reading is judged on at most MISREAD_MAX_LANDMARKS
    of them (two distance solves per pair judged), spread over the file, and a file read 1-based
    is still flagged; a 0 in any pair (judged or not) rules the shifted reading out."""
    from torchfmap.evaluate.scores import gt_from_map, landmarks_from_gt
    from torchfmap.matching import quality

    a, b, gt_ba = demo_pair()
    sa, sb = prepare_shape(a, 0), prepare_shape(b, 0)
    lm = landmarks_from_gt(a, gt_from_map(gt_ba), 40)
    judged = []
    real = quality.landmark_distortion

    def spy(x, y, pairs):
        judged.append(len(pairs))
        return real(x, y, pairs)

    monkeypatch.setattr(quality, "landmark_distortion", spy)
    with pytest.warns(UserWarning, match="read 1-based"):
        quality.warn_if_off_by_one(sa, sb, lm + 1)
    assert judged and max(judged) == quality.MISREAD_MAX_LANDMARKS
    judged.clear()
    zero = lm + 1
    zero[5, 0] = 0  # pair 5 is not among those judged (rows 0, 2, 4, 6, ...), and it says: 0-based
    assert 0 not in (lm[:, 0] + 1) and 5 not in np.linspace(0, 39, quality.MISREAD_MAX_LANDMARKS).round()
    quality.warn_if_off_by_one(sa, sb, zero)
    assert len(judged) <= 2  # the given reading and the swapped one: not the shifted one


def test_a_one_based_file_of_real_landmarks_is_caught():
    """pyFM's cat-lion pairs (a non-isometric pair, 20 landmarks at salient points) written
    1-based: shifted by one vertex they land near where they should, and as given they distort
    distances 1.25x more; judged on all 20 pairs the check says so. The file as it is passes."""
    import warnings

    from torchfmap.io import read_landmark_pairs
    from torchfmap.matching.quality import warn_if_off_by_one

    folder = data_path("pyfm_cat_lion")
    shapes = (
        prepare_shape(load_mesh(folder / "cat-00.off"), 0),
        prepare_shape(load_mesh(folder / "lion-00.off"), 0),
    )
    pairs = read_landmark_pairs(folder / "landmarks.txt")
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        warn_if_off_by_one(*shapes, pairs)
    with pytest.warns(UserWarning, match="shifted by -1"):
        warn_if_off_by_one(*shapes, pairs + 1)
