"""Evaluation (``torchfmap.evaluate.scores``): metrics against hand values, bijectivity error, shape
differences, reports, ground-truth formats and pair discovery (never a silent identity), invalid
maps refused."""

from __future__ import annotations

import numpy as np
import pytest

import torchfmap.evaluate.scores as eval_module
from torchfmap import ParameterError, load_mesh, save_mesh
from torchfmap.cli import main
from torchfmap.data import icosphere
from torchfmap.evaluate.scores import (
    Correspondence,
    MapReport,
    auc,
    bijectivity_error,
    coverage,
    discover_pairs,
    error_floor,
    evaluate_map,
    evaluated_rows,
    geodesic_errors,
    gt_from_map,
    gt_from_vts,
    gt_identity,
    pck_curve,
    retrieval_accuracy,
    select_pairs,
    shape_difference,
    shape_distance,
    smoothness,
)
from torchfmap.io import read_map, read_vts

from ..conftest import bend, bumpy_blob, data_path, make_bent_pair


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


def test_vts_ground_truth_reads_a_corres_folder(tmp_path):
    """The one reader of a data set's ``corres/``: plain or gzip-compressed 1-based files, and
    a missing one named with the fix."""
    import gzip

    from torchfmap.evaluate.ground_truth import vts_ground_truth

    (tmp_path / "a.vts").write_text("3\n1\n2\n")
    with gzip.open(tmp_path / "b.vts.gz", "wt") as f:
        f.write("4\n5\n6\n")
    gt = vts_ground_truth(tmp_path, "a", "b")
    assert gt.idx_x.tolist() == [2, 0, 1] and gt.idx_y.tolist() == [3, 4, 5]
    with pytest.raises(ParameterError, match=r"no ground truth .*c\.vts.*Fix"):
        vts_ground_truth(tmp_path, "a", "c")


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
    assert shape_distance(np.eye(6), W, W, form="conformal") == pytest.approx(0.0, abs=1e-12)
    D = np.array([[0, 1, 5, 5], [1, 0, 5, 5], [5, 5, 0, 2], [5, 5, 2, 0.0]])
    assert retrieval_accuracy(D, ["a", "a", "b", "b"]) == 1.0
    assert retrieval_accuracy(D, ["a", "b", "a", "b"]) == 0.0


def test_bijectivity_error_zero_for_bijection(sphere3):
    perm = np.random.default_rng(2).permutation(sphere3.n_vertices)
    assert bijectivity_error(sphere3, perm, np.argsort(perm)) == 0.0


@pytest.mark.parametrize("subdivisions", [2, 3])
def test_bijectivity_error_by_hand(subdivisions):
    """On the unit sphere the geodesic distance is arccos(p·q). A back map sending everything to
    vertex 0 gives mean_v arccos(v·v_0)/sqrt(|M|); one sending v to its antipode gives
    π/sqrt(|M|). The heat method (t = h²) is first-order accurate: relative error ≤ h_max."""
    y = icosphere(subdivisions)
    v, n = y.vertices, y.n_vertices
    ident = np.arange(n)
    h = y.edge_lengths.max()
    const = np.zeros(n, dtype=np.int64)
    hand = np.arccos(np.clip(v @ v[0], -1, 1)).mean() / np.sqrt(y.area)
    assert bijectivity_error(y, ident, const, max_points=None) == pytest.approx(hand, rel=h)
    antipode = np.argmin(v @ v.T, axis=1)
    np.testing.assert_allclose(v[antipode], -v, atol=1e-12)  # icospheres are centrally symmetric
    got = bijectivity_error(y, ident, antipode, max_points=None)
    assert got == pytest.approx(np.pi / np.sqrt(y.area), rel=h)


def test_shape_difference_closed_forms():
    """Area: CᵀC (identity for orthogonal C); conformal: W_x⁺ Cᵀ W_y C (identity when
    C W_x Cᵀ = W_y with invertible W)."""
    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.normal(size=(5, 5)))
    np.testing.assert_allclose(shape_difference(Q), np.eye(5), atol=1e-12)
    C = rng.normal(size=(4, 5))
    np.testing.assert_allclose(shape_difference(C, form="area"), C.T @ C, rtol=1e-12)
    W = np.diag(rng.uniform(1, 3, 5))
    np.testing.assert_allclose(shape_difference(Q, W, Q @ W @ Q.T, form="conformal"), np.eye(5), atol=1e-10)
    with pytest.raises(ParameterError, match="needs W_x and W_y"):
        shape_difference(Q, form="conformal")
    with pytest.raises(ParameterError, match="unknown shape difference"):
        shape_difference(Q, form="volume")


def test_map_report_row(sphere2):
    """evaluate_map on the identity: zero errors, AUC 1, full coverage, unit stretch."""
    n = sphere2.n_vertices
    report, errors = evaluate_map(sphere2, sphere2, np.arange(n), gt_from_map(np.arange(n)))
    assert isinstance(report, MapReport)
    assert errors.max() == 0 and report.mean_error == 0 and report.auc == pytest.approx(1.0)
    assert report.coverage == 1.0 and report.smoothness == pytest.approx(1.0, rel=1e-12)
    assert report.row().split() == ["0.0000", "0.0000", "1.000", "1.000", "1.00"]


def test_discover_pairs(tmp_path, sphere2):
    """Without corres/: consecutive meshes with the identity; with corres/ and test_pairs.txt:
    the listed pairs and .vts ground truth (1-based files -> 0-based indices)."""
    for name in ("a", "b", "c"):
        save_mesh(sphere2, tmp_path / f"{name}.off")
    pairs = list(discover_pairs(tmp_path))
    assert [(a, b) for a, b, *_ in pairs] == [("a", "b"), ("b", "c")]
    gt = pairs[0][4]
    np.testing.assert_array_equal(gt.idx_y, np.arange(sphere2.n_vertices))
    np.testing.assert_array_equal(gt.idx_x, gt.idx_y)
    (tmp_path / "corres").mkdir()
    np.savetxt(tmp_path / "corres" / "a.vts", [1, 5, 7], fmt="%d")
    np.savetxt(tmp_path / "corres" / "c.vts", [2, 3, 9], fmt="%d")
    (tmp_path / "test_pairs.txt").write_text("c a\n")
    (only,) = list(discover_pairs(tmp_path))
    assert only[:2] == ("c", "a")
    np.testing.assert_array_equal(only[4].idx_x, [1, 2, 8])  # source x = c
    np.testing.assert_array_equal(only[4].idx_y, [0, 4, 6])  # target y = a
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ParameterError, match="holds 0 meshes, at least two are needed"):
        list(discover_pairs(empty))


def test_pair_protocols_are_chosen_and_said(tmp_path, sphere2):
    for name in ("a", "b", "c"):
        save_mesh(sphere2, tmp_path / f"{name}.off")
    pairs, said = select_pairs(tmp_path)
    assert pairs == [("a", "b"), ("b", "c")] and said.startswith("2 consecutive pairs of 3 meshes")
    assert "of 6 ordered pairs: --pairs all" in said
    pairs, said = select_pairs(tmp_path, "all")
    assert len(pairs) == 6 == len(set(pairs)) and said == "all 6 ordered pairs of 3 meshes"
    assert [p[:2] for p in discover_pairs(tmp_path, pairs="all")] == pairs
    (tmp_path / "mine.txt").write_text("c b\na c\n")
    listed = ([("c", "b"), ("a", "c")], "the 2 pairs listed in mine.txt")
    assert select_pairs(tmp_path, tmp_path / "mine.txt") == listed
    (tmp_path / "bad.txt").write_text("a zebra\n")
    with pytest.raises(ParameterError, match=r"names \['zebra'\], which .* does not hold"):
        select_pairs(tmp_path, tmp_path / "bad.txt")
    with pytest.raises(ParameterError, match="neither a protocol nor an existing file"):
        select_pairs(tmp_path, "every")


def test_a_data_set_laid_out_as_shapes_test_beside_corres(tmp_path, sphere2):
    """DUO-FM / ULRSSM data sets: meshes in shapes_train/ and shapes_test/, one corres/ beside
    them. The data set's folder names the sub-folder to point to; the sub-folder reads the
    corres/ beside it."""
    for split, names in (("shapes_train", ("a", "b")), ("shapes_test", ("c", "d"))):
        (tmp_path / split).mkdir()
        for name in names:
            save_mesh(sphere2, tmp_path / split / f"{name}.off")
    (tmp_path / "corres").mkdir()
    for name, rows in (("c", [1, 5, 7]), ("d", [2, 3, 9])):
        np.savetxt(tmp_path / "corres" / f"{name}.vts", rows, fmt="%d")
    with pytest.raises(ParameterError, match=r"meshes are in shapes_test, shapes_train: point to one"):
        select_pairs(tmp_path)
    (only,) = list(discover_pairs(tmp_path / "shapes_test"))
    assert only[:2] == ("c", "d")
    np.testing.assert_array_equal(only[4].idx_x, [0, 4, 6])
    np.testing.assert_array_equal(only[4].idx_y, [1, 2, 8])


@pytest.fixture
def shuffled_folder(tmp_path):
    """Two meshes of equal vertex count whose vertex orders differ (the second is shuffled)."""
    x, y, _ = make_bent_pair(0.2, seed=0, subdivisions=2)
    save_mesh(x, tmp_path / "a.off")
    save_mesh(y, tmp_path / "b.off")
    return tmp_path


def test_identity_only_for_one_template_unless_asked(shuffled_folder, tmp_path, capsys):
    with pytest.raises(ParameterError, match="face lists differ.*--gt identity"):
        list(discover_pairs(shuffled_folder))
    ((_, _, _, _, gt),) = list(discover_pairs(shuffled_folder, identity=True))
    np.testing.assert_array_equal(gt.idx_x, gt.idx_y)
    assert main(["eval", str(shuffled_folder), "--k", "8", "--quiet"]) == 2
    assert "--gt identity" in capsys.readouterr().err
    # meshes of different vertex counts have no identity map: the fix does not offer it
    sizes = tmp_path / "sizes"
    sizes.mkdir()
    save_mesh(icosphere(1), sizes / "a.off")
    save_mesh(icosphere(2), sizes / "b.off")
    with pytest.raises(ParameterError, match="vertex counts differ") as err:
        list(discover_pairs(sizes))
    assert "identity" not in str(err.value)
    # the same template (same faces): identity is the convention, and --gt files refuses it
    same = tmp_path / "same"
    same.mkdir()
    x = bumpy_blob(2)
    for i, s in enumerate((0.1, 0.3)):
        save_mesh(x.copy(bend(x.vertices, s)), same / f"m{i}.off")
    assert len(list(discover_pairs(same))) == 1
    with pytest.raises(ParameterError, match="no ground truth"):
        list(discover_pairs(same, identity=False))
    assert main(["eval", str(same), "--k", "8", "--quiet", "--gt", "files"]) == 2


def test_gt_from_vts_names_paths_given_for_arrays(tmp_path):
    from torchfmap.evaluate.scores import gt_from_vts

    with pytest.raises(ParameterError, match=r"not their paths.*read_vts"):
        gt_from_vts(str(tmp_path / "a.vts"), tmp_path / "b.vts")


def test_evaluation_refuses_invalid_maps(sphere2):
    """-1 used to wrap to the last vertex, a map in the wrong direction was scored, floats and
    out-of-range entries gave bare IndexErrors, max_points=0 gave NaN."""
    from torchfmap.evaluate.scores import evaluate_map, geodesic_errors, gt_identity

    small = icosphere(1)
    n = sphere2.n_vertices
    gt = gt_identity(small.n_vertices)
    good = np.arange(small.n_vertices)
    cases = {
        "outside": good - 1,  # holds -1
        "outside ": good + 1,  # holds n
        "integer": good.astype(float),
    }
    for match_text, p2p in cases.items():
        with pytest.raises(ParameterError, match=match_text.strip()):
            geodesic_errors(small, p2p, gt)
    with pytest.raises(ParameterError, match="looks like a map x -> y"):
        evaluate_map(small, sphere2, good, gt)
    with pytest.raises(ParameterError, match="max_points"):
        geodesic_errors(small, good, gt, max_points=0)
    assert n > small.n_vertices


def test_error_floor_is_the_best_shared_image_of_rows_that_share_a_target_vertex():
    """Rows sharing a target vertex must share its image: each group's floor is the least mean
    error over sending the vertex to one of the group's source vertices, computed here by trying
    every candidate with geodesic_errors; a target vertex with one source vertex has floor 0."""
    sphere = icosphere(3)
    rng = np.random.default_rng(0)
    idx_y = np.repeat(np.arange(30), [1, 2, 3] * 10)  # groups of 1, 2 and 3 rows
    idx_x = rng.choice(sphere.n_vertices, len(idx_y), replace=False)
    gt = Correspondence(idx_x, idx_y)
    floor = error_floor(sphere, gt)
    assert floor.shape == idx_x.shape and np.all(floor >= 0)
    for y in range(30):
        rows = np.flatnonzero(idx_y == y)
        tried = []
        for c in idx_x[rows]:
            p2p = np.zeros(30, dtype=np.int64)
            p2p[y] = c
            tried.append(geodesic_errors(sphere, p2p, gt)[rows])
        best = min(np.mean(t) for t in tried)  # ties (a group of two) may pick either source
        np.testing.assert_allclose(floor[rows].mean(), best, rtol=1e-12, atol=1e-12)
        assert any(np.allclose(floor[rows], t, rtol=1e-12, atol=1e-12) for t in tried)
        assert (len(rows) == 1) == (floor[rows].max() == 0.0)
    np.testing.assert_array_equal(error_floor(sphere, gt_identity(sphere.n_vertices)), 0.0)
    with pytest.raises(ParameterError, match="outside mesh_x"):
        error_floor(sphere, Correspondence(np.array([sphere.n_vertices]), np.array([0])))


def _noisy_map(mesh, share: float, seed: int = 0) -> np.ndarray:
    """The identity with ``share`` of the vertices sent to random vertices: heavy-tailed errors."""
    rng = np.random.default_rng(seed)
    p2p = np.arange(mesh.n_vertices)
    moved = rng.random(mesh.n_vertices) < share
    p2p[moved] = rng.integers(0, mesh.n_vertices, int(moved.sum()))
    return p2p


def test_a_sample_estimates_the_mean_error_within_its_standard_error(sphere3):
    """n of P points drawn without replacement: the sampled mean is within 4 standard errors
    (sd / sqrt(n) · sqrt(1 - n / P), from the full errors) of the mean over every point, and the
    report's own standard error (from the sample) estimates it."""
    gt, p2p = gt_identity(sphere3.n_vertices), _noisy_map(sphere3, 0.3)
    full_report, full = evaluate_map(sphere3, sphere3, p2p, gt, max_points=None)
    assert len(full) == full_report.n_points == full_report.n_total == sphere3.n_vertices
    assert full_report.mean_error_se == 0.0 and full_report.sampling() == f"all {len(full)} points"
    n, total = 100, len(full)
    true_se = full.std(ddof=1) / np.sqrt(n) * np.sqrt(1 - n / total)
    for seed in range(3):
        report, errors = evaluate_map(sphere3, sphere3, p2p, gt, max_points=n, seed=seed)
        assert len(errors) == report.n_points == n and report.n_total == total
        assert abs(report.mean_error - full.mean()) < 4 * true_se
        # the sample's standard deviation estimates the population's (heavy tails: a loose factor)
        assert 0.5 * true_se < report.mean_error_se < 1.5 * true_se
        assert f"{n} of {total} points" in report.sampling()
    rows = evaluated_rows(total, total, n, seed=0)
    np.testing.assert_array_equal(full[rows], geodesic_errors(sphere3, p2p, gt, max_points=n, seed=0))


def test_auto_samples_above_the_size_and_says_so(sphere3, monkeypatch):
    """max_points='auto' (the default) scores every point on source meshes of at most
    FULL_EVAL_VERTICES vertices and SAMPLED_EVAL_POINTS of them above; None scores all."""
    gt, p2p = gt_identity(sphere3.n_vertices), _noisy_map(sphere3, 0.2)
    report, errors = evaluate_map(sphere3, sphere3, p2p, gt)
    assert sphere3.n_vertices <= eval_module.FULL_EVAL_VERTICES and len(errors) == sphere3.n_vertices
    monkeypatch.setattr(eval_module, "FULL_EVAL_VERTICES", sphere3.n_vertices - 1)
    monkeypatch.setattr(eval_module, "SAMPLED_EVAL_POINTS", 50)
    report, errors = evaluate_map(sphere3, sphere3, p2p, gt)
    assert (report.n_points, report.n_total, len(errors)) == (50, sphere3.n_vertices, 50)
    assert report.mean_error_se > 0 and report.sampling().startswith(f"50 of {sphere3.n_vertices} points")
    report, errors = evaluate_map(sphere3, sphere3, p2p, gt, max_points=None)  # asked for: every point
    assert report.n_points == report.n_total == len(errors) == sphere3.n_vertices
    assert evaluated_rows(10, 10**6, "auto") is None  # fewer rows than the sample: all of them
    rows = evaluated_rows(1000, 10**6, 7, seed=3)
    assert len(np.unique(rows)) == 7 and np.all(np.diff(rows) > 0)
    np.testing.assert_array_equal(rows, evaluated_rows(1000, 10**6, 7, seed=3))  # seeded
    for bad in (0, -3, True, "all", 2.5):
        with pytest.raises(ParameterError, match="max_points must be 'auto', None"):
            evaluated_rows(10, 10, bad)


def test_eval_command_states_the_sampling(tmp_path, sphere2, monkeypatch, capsys):
    """The eval table gives a sampled pair's mean with its standard error and a footer saying how
    many points were scored; --max-points all scores every point."""
    for name in ("a", "b"):
        save_mesh(sphere2, tmp_path / f"{name}.off")
    monkeypatch.setattr(eval_module, "FULL_EVAL_VERTICES", 10)
    monkeypatch.setattr(eval_module, "SAMPLED_EVAL_POINTS", 40)
    assert main(["eval", str(tmp_path), "--k", "20", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert " ± " in out and f"40 of {sphere2.n_vertices} points" in out and "--max-points all" in out
    assert main(["eval", str(tmp_path), "--k", "20", "--quiet", "--max-points", "all"]) == 0
    out = capsys.readouterr().out
    assert " ± " not in out and "Points:" not in out
