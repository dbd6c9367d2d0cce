"""Evaluation metrics against hand values; ground-truth formats; shape distances, retrieval."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, load_mesh
from torchfmap.data import icosphere
from torchfmap.eval import (
    auc,
    coverage,
    evaluate_map,
    geodesic_errors,
    gt_from_map,
    gt_from_vts,
    gt_identity,
    pck_curve,
    retrieval_accuracy,
    shape_distance,
    smoothness,
)
from torchfmap.io import read_map, read_vts

from .conftest import bend, bumpy_blob, data_path


def test_geodesic_error_hand_value():
    """On the unit sphere, mapping every vertex to its antipode has error pi / sqrt(4 pi)."""
    s = icosphere(3)
    antipode = np.argmin(s.vertices @ s.vertices.T, axis=1)
    errors = geodesic_errors(s, antipode, gt_identity(s.n_vertices))
    assert np.allclose(errors, np.pi / np.sqrt(s.area), rtol=0.03)
    assert np.all(geodesic_errors(s, np.arange(s.n_vertices), gt_identity(s.n_vertices)) == 0)
    # one neighbour off: the error is about an edge length (the heat method smooths near the source)
    e = s.edges[0]
    p2p = np.arange(s.n_vertices)
    p2p[e[0]] = e[1]
    err = geodesic_errors(s, p2p, gt_identity(s.n_vertices), normalize=False)
    assert err[e[0]] == pytest.approx(np.linalg.norm(s.vertices[e[0]] - s.vertices[e[1]]), rel=0.25)
    assert np.count_nonzero(err) == 1


def test_pck_auc_coverage_smoothness():
    errors = np.array([0.0, 0.05, 0.1, 0.3])
    thr, acc = pck_curve(errors, [0.0, 0.05, 0.2, 0.5])
    assert acc.tolist() == [0.25, 0.5, 0.75, 1.0]
    assert auc(np.zeros(5)) == pytest.approx(1.0) and auc(np.ones(5)) == 0.0
    assert coverage(np.array([0, 0, 1, 1]), 4) == 0.5
    s = icosphere(2)
    assert smoothness(s, s, np.arange(s.n_vertices)) == pytest.approx(1.0)


def test_gt_formats(tmp_path):
    (tmp_path / "m.txt").write_text("2\n0\n1\n")
    assert read_map(tmp_path / "m.txt").tolist() == [2, 0, 1]
    (tmp_path / "a.vts").write_text("3 7\n1 2\n")
    assert read_vts(tmp_path / "a.vts").tolist() == [2, 0]
    gt = gt_from_map([2, 0, 1])  # target v -> source gt_yx[v]
    assert gt.idx_x.tolist() == [2, 0, 1] and gt.idx_y.tolist() == [0, 1, 2]
    gt = gt_from_vts(np.array([5, 6]), np.array([1, 2]))
    assert gt.idx_x.tolist() == [5, 6] and gt.idx_y.tolist() == [1, 2]
    # a plain pair could be in either order: refused, with the fix
    with pytest.raises(ParameterError, match="Correspondence"):
        geodesic_errors(icosphere(1), np.arange(42), (np.arange(42), np.arange(42)))
    with pytest.raises(ParameterError, match="rows must correspond"):
        gt_from_vts(np.array([1]), np.array([1, 2]))


def test_gt_vts_on_real_pair():
    folder = data_path("tosca5k_dev")
    x, y = load_mesh(folder / "cat0.off"), load_mesh(folder / "cat1.off")
    gt = gt_from_vts(read_vts(folder / "corres" / "cat0.vts"), read_vts(folder / "corres" / "cat1.vts"))
    perfect = np.zeros(y.n_vertices, dtype=np.int64)
    perfect[gt.idx_y] = gt.idx_x
    report, errors = evaluate_map(x, y, perfect, gt, max_points=300)
    assert report.mean_error < 0.02  # .vts rows are not unique everywhere: a few repeated targets


def test_shape_distance_and_retrieval():
    Q = np.linalg.qr(np.random.default_rng(0).normal(size=(6, 6)))[0]
    assert shape_distance(Q) == pytest.approx(0.0, abs=1e-12)
    assert shape_distance(2 * Q) > 1.0
    W = np.diag(np.arange(1.0, 7.0))
    assert shape_distance(np.eye(6), W, W, kind="conformal") == pytest.approx(0.0, abs=1e-12)
    D = np.array([[0, 1, 5, 5], [1, 0, 5, 5], [5, 5, 0, 2], [5, 5, 2, 0.0]])
    assert retrieval_accuracy(D, ["a", "a", "b", "b"]) == 1.0
    assert retrieval_accuracy(D, ["a", "b", "a", "b"]) == 0.0


def test_retrieval_on_two_synthetic_classes():
    """Bent blobs and ellipsoids: shape distances from maps separate the classes."""
    from torchfmap.collection import shape_distance_matrix

    blob = bumpy_blob(2)
    sphere = icosphere(2)
    shapes = [blob.copy(bend(blob.vertices, s)) for s in (0.1, 0.2, 0.4)]
    shapes += [sphere.copy(sphere.vertices * np.array([1.6, a, 0.5])) for a in (0.8, 0.9, 1.0)]
    D = shape_distance_matrix(shapes, k=10, k_descriptors=30)
    assert np.allclose(D, D.T) and np.all(np.diag(D) == 0)
    assert retrieval_accuracy(D, ["blob"] * 3 + ["sphere"] * 3) == 1.0
