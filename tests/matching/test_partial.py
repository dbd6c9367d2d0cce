"""Partial-to-full matching (torchfmap.matching.partial, match(partial=True)) and the cuts that make
partial data (torchfmap.data.cuts)."""

import warnings

import numpy as np
import pytest

from torchfmap import match, prepare_shape
from torchfmap.data import demo_pair
from torchfmap.data.cuts import cut_holes, cut_plane
from torchfmap.data.synthetic import icosphere
from torchfmap.descriptors import shot
from torchfmap.errors import MapWarning, ParameterError, SeedError
from torchfmap.evaluate.partial import discover_partial_pairs, overlap_iou
from torchfmap.evaluate.scores import geodesic_errors, gt_from_map, landmarks_from_gt
from torchfmap.fmap import p2p_to_fmap
from torchfmap.io import save_mesh
from torchfmap.matching.partial import (
    common_frame,
    match_partial,
    overlap_indicator,
    partial_rank,
    partial_zoomout,
    reseeded_map,
)  # fmt: skip
from torchfmap.mesh import Mesh


@pytest.fixture(scope="module")
def blob_cut():
    a, b, gt = demo_pair()
    cut = cut_plane(b, 0.6, seed=1)
    return a, cut, gt[cut.vertices]  # part vertex -> vertex of a


def test_cut_plane_keeps_positions_and_reaches_the_area_ratio():
    sphere = icosphere(4)
    cut = cut_plane(sphere, 0.5, normal=(0, 0, 1))
    np.testing.assert_array_equal(cut.mesh.vertices, sphere.vertices[cut.vertices])
    # bisection on face centroids: the kept area misses the asked one by at most the faces the
    # plane crosses, a band one face wide around the equator (perimeter x edge length)
    band = 2 * np.pi * sphere.mean_edge_length / sphere.area
    assert abs(cut.mesh.area / sphere.area - 0.5) <= band
    assert cut.mesh.boundary_vertices.size > 0 and cut.mesh.n_components == 1


def test_cut_holes_removes_about_the_asked_area():
    sphere = icosphere(4)
    cut = cut_holes(sphere, 0.7, n_holes=3, seed=0)
    np.testing.assert_array_equal(cut.mesh.vertices, sphere.vertices[cut.vertices])
    largest_face = sphere.face_areas.max() / sphere.area
    assert 0.7 - largest_face <= cut.mesh.area / sphere.area <= 0.7 + 3 * largest_face
    assert len(cut.mesh.boundary_edges) > 0


@pytest.mark.parametrize("ratio", [0.0, 1.0, float("nan")])
def test_cuts_refuse_bad_ratios(ratio):
    with pytest.raises(ParameterError, match="area_ratio"):
        cut_plane(icosphere(2), ratio)


def test_hemisphere_spectrum_in_the_whole_frame():
    """A hemisphere's Neumann eigenvalues are the sphere's l(l+1) with multiplicity l + 1 (the
    harmonics even about the cut plane); in the whole sphere's unit-area frame they must sit on
    the sphere's own eigenvalues: 4π l(l+1)."""
    sphere = icosphere(4)
    cut = cut_plane(sphere, 0.5, normal=(0, 0, 1))
    whole, part = prepare_shape(sphere, 30), prepare_shape(cut.mesh, 20)
    a = cut.mesh.area / sphere.area
    lam = common_frame(part.eigenbasis, a).eigenvalues
    exact = np.concatenate([[4 * np.pi * n * (n + 1)] * (n + 1) for n in range(6)])[:20]
    # the tolerance: the whole sphere's own discretisation error on the same eigenvalues, plus
    # the jagged cut (faces kept by centroid), which moves the boundary by up to one edge length
    # h: a relative change O(h / radius) of a Neumann eigenvalue (a wrong frame is off by 1 / a = 2)
    sphere_exact = np.concatenate([[4 * np.pi * n * (n + 1)] * (2 * n + 1) for n in range(6)])[1:30]
    sphere_err = np.max(np.abs(whole.eigenbasis.eigenvalues[1:30] / sphere_exact - 1))
    np.testing.assert_allclose(lam[1:], exact[1:], rtol=sphere_err + sphere.mean_edge_length)
    mid = 4 * np.pi * (12 + 20) / 2  # between l = 3 and l = 4
    assert np.sum(lam < mid) == 1 + 2 + 3 + 4
    assert np.sum(whole.eigenbasis.eigenvalues < mid) == 16
    # B-orthonormal in the whole's frame
    b = common_frame(part.eigenbasis, a)
    np.testing.assert_allclose(b.gram(), np.eye(b.k), atol=1e-8)


def test_partial_rank_counts_eigenvalues_below_the_whole():
    lam_x = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    lam_y = np.array([0.0, 2.0, 4.0, 6.0, 8.0])
    assert partial_rank(lam_x, lam_y, 5) == 3  # 0, 2, 4 <= 4
    assert partial_rank(lam_x, lam_y, 1) == 1  # never below one
    assert partial_rank(lam_x, lam_x, 5) == 5  # a whole "part": full rank


def test_overlap_of_the_true_map_marks_the_part():
    """Extension by zero of the part's constant function: with the true map's C the overlap is
    the band-limited indicator of the part (a step function's projection: near 1 inside, near 0
    outside, Gibbs overshoot only near the cut)."""
    sphere = icosphere(4)
    cut = cut_plane(sphere, 0.5, normal=(0, 0, 1))
    whole, part = prepare_shape(sphere, 60), prepare_shape(cut.mesh, 60)
    a = cut.mesh.area / sphere.area
    full, pb = whole.eigenbasis, common_frame(part.eigenbasis, a)
    r = partial_rank(full.eigenvalues, pb.eigenvalues, 49)
    C = p2p_to_fmap(cut.vertices, full, pb, 49, r)
    np.testing.assert_allclose(C[0, 0], np.sqrt(a), rtol=1e-6)  # constants: 1 -> sqrt(a) φ_0
    v = overlap_indicator(C, full, pb)
    inside = np.zeros(sphere.n_vertices, bool)
    inside[cut.vertices] = True
    far = np.abs(sphere.vertices[:, 2]) > 0.3  # away from the cut, where the projection converged
    assert v[inside & far].mean() > 0.9 and v[~inside & far].mean() < 0.1


def test_partial_match_with_landmarks_beats_the_full_shape_map(blob_cut):
    """Same landmarks, same k: the partial map (one frame, rank-limited) against the full-shape
    map, which assumes the part whole and stretches it to the whole's size."""
    a, cut, gt_part = blob_cut
    lm = landmarks_from_gt(a, gt_from_map(gt_part), 5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MapWarning)
        whole = match(a, cut.mesh, k=30, landmarks=lm, basis="laplacian", refine="zoomout")
    part = match(a, cut.mesh, k=30, landmarks=lm, refine="zoomout", partial=True)
    err = [geodesic_errors(a, r.p2p_yx, gt_from_map(gt_part)).mean() for r in (whole, part)]
    assert err[1] < err[0]
    assert part.kind == "partial" and part.overlap.shape == (a.n_vertices,)
    assert part.C_xy.shape == (part.partial_rank, 60) and part.partial_rank < 60
    assert 0.0 <= part.overlap.min() and part.overlap.max() <= 1.0


def test_partial_input_warns_once_naming_the_flag(blob_cut):
    a, cut, _ = blob_cut
    with pytest.warns(MapWarning, match="partial=True") as record:
        match(a, cut.mesh, k=10)
    assert len([w for w in record if issubclass(w.category, MapWarning)]) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error", MapWarning)
        match(a, cut.mesh, k=10, partial=True)  # asked for: no warning


def test_partial_refuses_what_it_would_not_use(blob_cut):
    a, cut, _ = blob_cut
    with pytest.raises(ParameterError, match="n_descriptors"):
        match(a, cut.mesh, k=10, partial=True, n_descriptors=10)
    with pytest.raises(ParameterError, match="basis"):
        match(a, cut.mesh, k=10, partial=True, basis="diffusion")
    with pytest.raises(ParameterError, match="icp"):
        match(a, cut.mesh, k=10, partial=True, refine="icp")
    with pytest.raises(ParameterError, match="whole shape first"):
        match(cut.mesh, a, k=10, partial=True)  # swapped


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_partial_in_other_units_is_refused_naming_the_units(blob_cut, scale):
    """A whole in metres and a part in millimetres (or the reverse) puts the area ratio 1e6 away
    from any real part's: refused, naming the units, never a map of rank 1."""
    a, cut, _ = blob_cut
    with pytest.raises(ParameterError, match="units") as err:
        match(a, cut.mesh.scaled(scale), k=10, partial=True)
    assert "whole shape first" not in str(err.value)  # the order was right


@pytest.mark.slow
def test_cli_partial(blob_cut, tmp_path, capsys):
    from torchfmap.cli import main

    a, cut, gt_part = blob_cut
    save_mesh(a, tmp_path / "whole.off")
    save_mesh(cut.mesh, tmp_path / "part.off")
    run = ["match", str(tmp_path / "whole.off"), str(tmp_path / "part.off")]
    assert main([*run, "--partial", "--k", "20", "--out", str(tmp_path / "m.txt")]) == 0
    assert "partial basis, rank" in capsys.readouterr().out
    assert len(np.loadtxt(tmp_path / "m.txt", dtype=np.int64)) == cut.n_vertices
    assert main([*run, "--k", "20", "--out", str(tmp_path / "m.txt")]) == 0
    assert "--partial" in capsys.readouterr().err
    learned = [*run, "--partial", "--checkpoint", "faust_r", "--out", str(tmp_path / "m.txt")]
    assert main([*learned, "--adapt", "2"]) != 0  # adaptation's loss is the whole-shape loss
    err = capsys.readouterr().err
    assert "--adapt" in err and "--partial" in err and "Traceback" not in err
    assert main([*learned, "--refine", "zoomout"]) == 0
    assert "faust_r" in (out := capsys.readouterr().out) and "partial: rank" in out
    assert len(np.loadtxt(tmp_path / "m.txt", dtype=np.int64)) == cut.n_vertices


def _collection(tmp_path, blob_cut, base=0):
    a, cut, gt_part = blob_cut
    for sub in ("full", "partial", "corres"):
        (tmp_path / sub).mkdir(parents=True, exist_ok=True)
    save_mesh(a, tmp_path / "full" / "blob.off")
    save_mesh(cut.mesh, tmp_path / "partial" / "blob_cut60.off")
    known = gt_part.copy()
    known[:10] = -1  # ten vertices without ground truth (written as 0 when 1-based)
    np.savetxt(tmp_path / "corres" / "blob_cut60.map", known + base, fmt="%d")
    return tmp_path


def test_partial_collection_is_read(tmp_path, blob_cut):
    a, cut, gt_part = blob_cut
    folder = _collection(tmp_path, blob_cut)
    [(whole, part, pw, pp, gt)] = list(discover_partial_pairs(folder))
    assert (whole, part) == ("blob", "blob_cut60")
    np.testing.assert_array_equal(gt.idx_y, np.arange(10, cut.n_vertices))
    np.testing.assert_array_equal(gt.idx_x, gt_part[10:])
    one = _collection(tmp_path / "one", blob_cut, base=1)  # 1-based: 0 marks no ground truth
    [(*_, gt1)] = list(discover_partial_pairs(one, map_base=1))
    np.testing.assert_array_equal(gt1.idx_x, gt.idx_x)


def _field_layouts(tmp_path, blob_cut) -> dict:
    """The same part in the field's layouts: ``shapes/`` + ``maps/<part>_<whole>.map`` (0-based,
    -1 for none), SHREC'16 as distributed (``null/``, ``cuts/`` with ``.baryc_gt``: a 1-based
    triangle and barycentric weights, the part's vertex its corner of largest weight) and as the
    field converts it (``null/off``, ``cuts/off``, ``cuts/corres/*.vts``, 1-based)."""
    a, cut, gt_part = blob_cut
    known = gt_part.copy()
    known[:10] = -1
    pfarm = tmp_path / "pfarm"
    (pfarm / "shapes").mkdir(parents=True)
    (pfarm / "maps").mkdir()
    save_mesh(a, pfarm / "shapes" / "blob_a.off")  # underscores in names: the map's name still splits once
    save_mesh(cut.mesh, pfarm / "shapes" / "blob_a_cut.off")
    np.savetxt(pfarm / "maps" / "blob_a_cut_blob_a.map", known, fmt="%d")
    shrec = tmp_path / "shrec"
    for sub in ("null", "cuts"):
        (shrec / sub).mkdir(parents=True)
    save_mesh(a, shrec / "null" / "blob.off")
    save_mesh(cut.mesh, shrec / "cuts" / "cuts_blob_shape_1.off")
    face_of = np.zeros(a.n_vertices, dtype=np.int64)
    face_of[a.faces[:, 0]] = np.arange(len(a.faces))  # a face with the vertex as its first corner...
    corner = np.zeros(a.n_vertices, dtype=np.int64)
    for c in (1, 2):  # ... or another corner, for vertices that are never first
        missing = ~np.isin(np.arange(a.n_vertices), a.faces[:, :c].ravel())
        face_of[a.faces[:, c][missing[a.faces[:, c]]]] = np.flatnonzero(missing[a.faces[:, c]])
        corner[a.faces[:, c][missing[a.faces[:, c]]]] = c
    weights = np.full((cut.n_vertices, 3), 0.15)
    weights[np.arange(cut.n_vertices), corner[gt_part]] = 0.7
    table = np.column_stack([face_of[gt_part] + 1, weights])
    table[:10, 0] = len(a.faces) + 1  # rows naming no triangle of the whole: left out
    np.savetxt(shrec / "cuts" / "cuts_blob_shape_1.baryc_gt", table, fmt=["%d", "%.6f", "%.6f", "%.6f"])
    converted = tmp_path / "shrec_converted"
    for sub in ("null/off", "cuts/off", "cuts/corres"):
        (converted / sub).mkdir(parents=True)
    save_mesh(a, converted / "null" / "off" / "blob.off")
    save_mesh(cut.mesh, converted / "cuts" / "off" / "cuts_blob_shape_1.off")
    np.savetxt(converted / "cuts" / "corres" / "cuts_blob_shape_1.vts", gt_part + 1, fmt="%d")
    return {"pfarm": pfarm, "shrec": shrec, "converted": converted}


def test_the_fields_partial_layouts_are_read_as_they_are(tmp_path, blob_cut):
    a, cut, gt_part = blob_cut
    layouts = _field_layouts(tmp_path, blob_cut)
    [(whole, part, pw, pp, gt)] = list(discover_partial_pairs(layouts["pfarm"]))
    assert (whole, part) == ("blob_a", "blob_a_cut") and pp.name == "blob_a_cut.off"
    np.testing.assert_array_equal(gt.idx_y, np.arange(10, cut.n_vertices))
    np.testing.assert_array_equal(gt.idx_x, gt_part[10:])
    for name in ("shrec", "converted"):
        [(whole, part, pw, pp, gt)] = list(discover_partial_pairs(layouts[name]))
        assert (whole, part) == ("blob", "cuts_blob_shape_1")
        rows = np.arange(10 if name == "shrec" else 0, cut.n_vertices)
        np.testing.assert_array_equal(gt.idx_y, rows)
        np.testing.assert_array_equal(gt.idx_x, gt_part[rows])


def test_partial_collection_refuses_bad_layouts(tmp_path, blob_cut):
    with pytest.raises(
        ParameterError, match=r"not a partial collection.*torchfmap: .*shapes\+maps: .*SHREC'16: "
    ):
        list(discover_partial_pairs(tmp_path))
    layouts = _field_layouts(tmp_path / "field", blob_cut)
    (layouts["pfarm"] / "maps" / "blob_a_cut_blob_a.map").rename(
        layouts["pfarm"] / "maps" / "blob_cut_lion.map"
    )
    with pytest.raises(ParameterError, match="names no <part>_<whole> pair"):
        list(discover_partial_pairs(layouts["pfarm"]))
    (layouts["shrec"] / "cuts" / "cuts_blob_shape_1.baryc_gt").unlink()
    with pytest.raises(ParameterError, match="no ground truth .*baryc_gt"):
        list(discover_partial_pairs(layouts["shrec"]))
    folder = _collection(tmp_path, blob_cut)
    np.savetxt(folder / "corres" / "blob_cut60.map", np.arange(5), fmt="%d")  # too short
    with pytest.raises(ParameterError, match="one line per part vertex"):
        list(discover_partial_pairs(folder))


def test_overlap_iou_exact_cases():
    mass = np.array([1.0, 2.0, 3.0, 4.0])
    assert overlap_iou(np.array([1.0, 1.0, 0.0, 0.0]), [0, 1], mass) == 1.0
    assert overlap_iou(np.array([0.0, 0.0, 1.0, 1.0]), [0, 1], mass) == 0.0
    # estimated {1, 2}, true {0, 1}: intersection area 2, union 1 + 2 + 3
    assert overlap_iou(np.array([0.2, 0.9, 0.7, 0.0]), [0, 1], mass) == pytest.approx(2 / 6)


@pytest.mark.slow
def test_cli_eval_partial(tmp_path, blob_cut, capsys):
    from torchfmap.cli import main

    folder = _collection(tmp_path, blob_cut)
    cmd = ["eval", str(folder), "--partial", "--gt-landmarks", "5", "--k", "20"]
    assert main([*cmd, "--quiet"]) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert "IoU |" in out and "| blob | blob_cut60 |" in out and "maps 0-based" in out
    layouts = _field_layouts(tmp_path / "field", blob_cut)  # the field's layouts, as they are
    for name in ("pfarm", "shrec"):
        assert main(["eval", str(layouts[name]), "--partial", "--k", "20", "--quiet"]) == 0
        assert "IoU |" in capsys.readouterr().out
    assert main([*cmd, "--pairs", "all"]) != 0
    err = capsys.readouterr().err
    assert "--pairs" in err and "Traceback" not in err
    # a trained network's features in the partial solve: the same table, IoU included
    assert main(["eval", str(folder), "--partial", "--checkpoint", "faust_r", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "IoU |" in out and "| blob | blob_cut60 |" in out and "faust_r" in out and "partial" in out


def test_given_descriptors_that_agree_recover_the_restriction():
    """A part cut from the whole itself, with the vertex positions as descriptors (equal on the
    part and on the whole where it lies): the solve must find the restriction, up to the
    resolution of k eigenfunctions (a few edge lengths)."""
    a, _, _ = demo_pair()
    cut = cut_plane(a, 0.6, seed=3)
    whole, part = prepare_shape(a, 60), prepare_shape(cut.mesh, 60)
    xyz = (a.vertices, cut.mesh.vertices)
    r = match_partial(whole, part, k=30, refine="zoomout", descriptors=xyz)
    err = geodesic_errors(a, r.p2p_yx, gt_from_map(cut.vertices))
    assert np.mean(err) < 3 * a.mean_edge_length / np.sqrt(a.area)


def test_shot_is_local_and_rigid_invariant():
    """SHOT reads only the surface within its radius in a frame of its own: a rigid motion
    leaves it unchanged, and a cut changes it only within the radius of the cut (plus the ring
    whose vertex areas and normals the cut changes)."""
    a, _, _ = demo_pair()
    radius = 0.15 * np.sqrt(a.area)
    F = shot(a, radius)
    np.testing.assert_allclose(np.linalg.norm(F, axis=1), 1.0)
    R = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))  # proper rotation
    moved = a.copy(vertices=a.vertices @ R.T + 3.0)
    # exact except where round-off decides: an axis sign voted by a tie of neighbours, or a
    # neighbour on a grid cell's or the ball's border (on a regular icosphere-like mesh, a few
    # vertices in a hundred share such symmetric neighbourhoods)
    same = np.abs(shot(moved, radius) - F).max(axis=1) < 1e-8
    assert same.mean() > 0.98
    cut = cut_plane(a, 0.6, seed=3)
    Fp = shot(cut.mesh, radius)
    rim = cut.mesh.vertices[cut.mesh.boundary_vertices]
    near_cut = np.linalg.norm(cut.mesh.vertices[:, None] - rim[None], axis=2).min(axis=1)
    # away from the cut (beyond the radius plus one ring, whose normals the cut changes)
    far = near_cut > radius + 2 * a.mean_edge_length
    assert far.sum() > 100
    np.testing.assert_allclose(Fp[far], F[cut.vertices][far], atol=1e-8)
    with pytest.raises(ParameterError, match="radius"):
        shot(a, 0.0)


def test_partial_zoomout_keeps_the_landmark_distances_in_the_wholes_units():
    """With landmarks, partial ZoomOut also matches the vertices' geodesic distances to them;
    the part's distance rows (units of its own sqrt(area)) times sqrt(area ratio) are the
    whole's, away from the cut, so both sides are in one unit (a part cut from the whole
    itself: the median relative difference is the heat method's discretisation error)."""
    from torchfmap.kinds.refiners import landmark_coordinates
    from torchfmap.matching.partial import area_ratio

    whole = demo_pair()[0]
    cut = cut_plane(whole, 0.6, seed=1)
    shapes = (prepare_shape(whole, 100), prepare_shape(cut.mesh, 100))
    idx = np.linspace(0, cut.n_vertices - 1, 5).astype(int)
    lm = np.stack([cut.vertices[idx], idx], axis=1)
    ax, ay = landmark_coordinates(*shapes, lm)
    a = area_ratio(whole, cut.mesh)
    on_whole = ax[cut.vertices]
    far = on_whole > 0.1  # relative differences away from the landmarks themselves
    rel = np.abs(ay * np.sqrt(a) - on_whole)[far] / on_whole[far]
    assert np.median(rel) < 0.05
    # against the ground truth of a part cut from the whole (not a replay of the steps): the
    # refined map is no worse than the raw one and within half an edge of the truth on average
    # (a map off by one vertex everywhere is about one edge off), and the true map is nearly a
    # fixed point of anchored partial ZoomOut (its mean error well under half an edge)
    gt, edge = gt_from_map(cut.vertices), whole.mean_edge_length / np.sqrt(whole.area)
    r = match(whole, cut.mesh, landmarks=lm, k=30, refine="zoomout", partial=True, shapes=shapes)
    start = match(whole, cut.mesh, landmarks=lm, k=30, partial=True, shapes=shapes)
    raw, refined = (geodesic_errors(whole, m.p2p_yx, gt).mean() for m in (start, r))
    assert refined <= raw and refined < 0.5 * edge
    full, part = shapes[0].eigenbasis, common_frame(shapes[1].eigenbasis, a)
    _, kept = partial_zoomout(cut.vertices, full, part, 30, 60, anchors=(ax, ay * np.sqrt(a)))
    assert geodesic_errors(whole, kept, gt).mean() < 0.5 * edge
    with pytest.raises(ParameterError, match="anchors"):  # the check of fmap.zoomout's anchors
        partial_zoomout(start.p2p_yx, full, part, 30, 60, anchors=(ax, ay[:10]))


@pytest.mark.parametrize("how", ["plane", "holes"])
def test_reseeded_map_keeps_the_true_map_of_a_part_cut_from_the_whole(how):
    """A part cut from the whole itself: the seeds' images by the true map are exact, and every
    seed's function exp(-d²/σ²) is the whole's away from the cut, so the true map is a fixed
    point up to the vertices where the cut lengthens paths. A map off by one vertex everywhere
    would have a mean error of about one edge length: the mean must stay well under it."""
    whole = demo_pair()[0]
    cut = cut_plane(whole, 0.6, seed=1) if how == "plane" else cut_holes(whole, 0.6, 3, seed=1)
    shapes = prepare_shape(whole, 10), prepare_shape(cut.mesh, 10)
    lm = np.stack([cut.vertices[[0, 50, 100]], [0, 50, 100]], axis=1)
    p2p = reseeded_map(*shapes, cut.vertices, lm)
    assert p2p.shape == (cut.n_vertices,) and p2p.dtype == np.int64
    err = geodesic_errors(whole, p2p, gt_from_map(cut.vertices))
    assert err.mean() < 0.5 * whole.mean_edge_length / np.sqrt(whole.area)
    # intrinsic: a rigid motion of the part changes nothing (round-off may flip exact ties)
    rot = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    moved = Mesh(cut.mesh.vertices @ rot.T + 5.0, cut.mesh.faces)
    again = reseeded_map(shapes[0], prepare_shape(moved, 10), cut.vertices, lm)
    assert np.mean(again == p2p) > 0.99


def test_reseeded_map_bounds_its_seeds_and_checks_its_settings():
    sphere = icosphere(2)
    cut = cut_plane(sphere, 0.6, seed=0)
    shapes = prepare_shape(sphere, 10), prepare_shape(cut.mesh, 10)
    p2p = reseeded_map(*shapes, cut.vertices, n_seeds=10**6)  # more seeds than vertices: all of them
    assert p2p.shape == (cut.n_vertices,) and 0 <= p2p.min() and p2p.max() < sphere.n_vertices
    err = geodesic_errors(sphere, p2p, gt_from_map(cut.vertices))  # as in the test above
    assert err.mean() < 0.5 * sphere.mean_edge_length / np.sqrt(sphere.area)
    for bad in ({"n_seeds": 0}, {"width": 0.0}, {"width": float("nan")}):
        with pytest.raises(ParameterError, match="reseeded_map"):
            reseeded_map(*shapes, cut.vertices, **bad)
    with pytest.raises(ParameterError, match="p2p_yx"):  # a map of the wrong length
        reseeded_map(*shapes, cut.vertices[:-1])
    with pytest.raises(SeedError, match="source landmarks"):
        reseeded_map(*shapes, cut.vertices, np.array([[sphere.n_vertices, 0]]))
    with pytest.raises(SeedError, match="target landmarks"):
        reseeded_map(*shapes, cut.vertices, np.array([[0, 1], [2, 1]]))


def test_partial_match_on_a_dense_pair_searches_locally_as_well(blob_cut, monkeypatch):
    """Past ``LOCAL_SEARCH_PAIRS`` (lowered here so the demo pair crosses it) the partial map,
    its ZoomOut and the re-seeded passes search locally around surface samples: the refined
    map's error against the ground truth stays within a few percent of an edge of the
    exhaustive path's, and the re-seeded pass keeps the true map of a part cut from the whole."""
    import torchfmap.kinds.refiners as refiners

    a, cut, gt_part = blob_cut
    lm = landmarks_from_gt(a, gt_from_map(gt_part), 5)
    exact = match(a, cut.mesh, k=30, landmarks=lm, refine="zoomout", partial=True)
    monkeypatch.setattr(refiners, "LOCAL_SEARCH_PAIRS", 1)
    monkeypatch.setattr(refiners, "SURFACE_SAMPLES", 300)
    dense = match(a, cut.mesh, k=30, landmarks=lm, refine="zoomout", partial=True)
    err = [geodesic_errors(a, r.p2p_yx, gt_from_map(gt_part)).mean() for r in (exact, dense)]
    assert err[1] <= err[0] + 0.25 * a.mean_edge_length / np.sqrt(a.area)
    whole = demo_pair()[0]
    part = cut_plane(whole, 0.6, seed=1)
    shapes = prepare_shape(whole, 10), prepare_shape(part.mesh, 10)
    p2p = reseeded_map(*shapes, part.vertices, np.stack([part.vertices[[0, 50]], [0, 50]], axis=1))
    local = geodesic_errors(whole, p2p, gt_from_map(part.vertices))
    assert local.mean() < 0.5 * whole.mean_edge_length / np.sqrt(whole.area)


def test_overlap_iou_scores_the_region_whatever_the_parts_meshing():
    """A part meshed four times coarser than its whole (a hemisphere of a coarser sphere, ground
    truth the nearest whole vertex): the exact indicator of the hemisphere scores about 1 as a
    region (the images alone cover a quarter of the region's vertices); a radius needs points."""
    from torchfmap.evaluate.partial import part_radius
    from torchfmap.operators import laplacian

    whole, coarse = icosphere(4), icosphere(3)
    keep = np.flatnonzero(coarse.vertices[:, 2] > 0)
    faces = coarse.faces[np.isin(coarse.faces, keep).all(axis=1)]
    remap = np.full(coarse.n_vertices, -1)
    remap[keep] = np.arange(len(keep))
    part = Mesh(coarse.vertices[keep], remap[faces])
    images = np.argmin(np.linalg.norm(part.vertices[:, None] - whole.vertices[None], axis=2), axis=1)
    mass = laplacian(whole)[1]
    exact = (whole.vertices[:, 2] > 0).astype(float)
    vertex_only = overlap_iou(exact, images, mass)
    region = overlap_iou(
        exact, images, mass, points=whole.vertices, radius=part_radius(part.vertices, part.faces)
    )
    assert vertex_only < 0.4 and region > 0.9
    assert overlap_iou(1.0 - exact, images, mass, points=whole.vertices, radius=0.1) < 0.1
    with pytest.raises(ParameterError, match="points"):
        overlap_iou(exact, images, mass, radius=0.1)


def test_partial_refinement_refuses_a_k_final_below_k_as_match_does(blob_cut):
    """``match_partial(k=40, refine='zoomout', k_final=10)`` is refused by the one rule of
    ZoomOut's sizes, as ``match(partial=True)`` refuses it (it returned a 7 x 10 map marked
    refined)."""
    a, cut, _ = blob_cut
    shapes = prepare_shape(a, 80), prepare_shape(cut.mesh, 80)
    for call in (
        lambda: match_partial(*shapes, k=40, refine="zoomout", k_final=10),
        lambda: match(a, cut.mesh, k=40, refine="zoomout", k_final=10, partial=True),
    ):
        with pytest.raises(ParameterError, match="k_final=10 is below k=40"):
            call()


def test_reseeded_map_solves_each_seed_row_once(monkeypatch):
    """The re-seeded pass's farthest-point seeds on the part take their rows from the prepared
    shape's distance rows and keep them there, so the pass solves each seed's row once (it
    solved every row twice: once for the sampling, once for the functions)."""
    from torchfmap.operators.geodesic import GeodesicSolver

    whole = demo_pair()[0]
    cut = cut_plane(whole, 0.6, seed=1)
    shapes = prepare_shape(whole, 10), prepare_shape(cut.mesh, 10)
    solved = []
    real_many, real_one = GeodesicSolver.distances, GeodesicSolver.distance

    def many(self, sources):
        solved.extend(np.atleast_1d(sources).tolist())
        return real_many(self, sources)

    def one(self, source):
        solved.append(int(source))
        return real_one(self, source)

    monkeypatch.setattr(GeodesicSolver, "distances", many)
    monkeypatch.setattr(GeodesicSolver, "distance", one)
    reseeded_map(*shapes, cut.vertices, n_seeds=20)
    assert len(solved) == len(set(solved)) and len(solved) <= 2 * 20


def test_descriptor_families_weigh_alike_and_given_ones_are_checked():
    """``families``: every column has unit mass norm on ``x`` before weighting, then each family
    carries ``max D_i`` of squared norm (a 3- or 2-column family next to a 12-column one weighs as
    it), and ``y`` is divided by ``x``'s norms (the solve compares the two); one family keeps unit
    columns. ``match_partial`` checks given descriptors row by row."""
    from scipy import sparse

    from torchfmap.matching.partial import families

    rng = np.random.default_rng(0)
    n_x, n_y = 40, 25
    mass = sparse.diags(rng.uniform(0.5, 2.0, n_x))
    given = [(rng.normal(size=(n_x, d)), rng.normal(size=(n_y, d))) for d in (12, 3, 2)]
    dx, dy = families(given, mass)
    energy = np.einsum("vd,vd->d", dx, mass @ dx)
    np.testing.assert_allclose(energy[:12], 1.0, rtol=1e-12)
    np.testing.assert_allclose(energy[12:15], 12 / 3, rtol=1e-12)
    np.testing.assert_allclose(energy[15:], 12 / 2, rtol=1e-12)
    scale = dx / np.hstack([g[0] for g in given])
    np.testing.assert_allclose(dy, np.hstack([g[1] for g in given]) * scale[0], rtol=1e-12)
    one_x, one_y = families(given[:1], mass)  # one family: unit columns, as before families
    np.testing.assert_allclose(np.einsum("vd,vd->d", one_x, mass @ one_x), 1.0, rtol=1e-12)
    a, _, _ = demo_pair()
    cut = cut_plane(a, 0.6, seed=3)
    whole, part = prepare_shape(a, 60), prepare_shape(cut.mesh, 60)
    with pytest.raises(ParameterError, match=r"descriptors\[1\].*V="):
        match_partial(whole, part, k=10, descriptors=(a.vertices, a.vertices), with_shot=True)
    # descriptors that agree, next to SHOT (which agrees away from the cut): still the restriction
    xyz = (a.vertices, cut.mesh.vertices)
    r = match_partial(whole, part, k=30, refine="zoomout", descriptors=xyz, with_shot=True)
    err = geodesic_errors(a, r.p2p_yx, gt_from_map(cut.vertices))
    assert np.mean(err) < 3 * a.mean_edge_length / np.sqrt(a.area)
