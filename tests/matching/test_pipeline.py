"""Matching (``torchfmap.matching.pipeline``): every basis and refinement end to end, the steps one by one,
the landmark default's choice by geodesic distortion, given bases, feature-aware bases at
corresponding seeds, scale invariance, settings that would change nothing, bad input and
warnings."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from torchfmap import Basis, MapWarning, Mesh, ParameterError, SeedError, save_mesh
from torchfmap.bases.prepared import prepare_shape
from torchfmap.cli import build_parser, main
from torchfmap.data import icosphere
from torchfmap.evaluate.scores import evaluate_map, gt_identity, landmarks_from_gt
from torchfmap.kinds import KINDS
from torchfmap.matching.landmark_default import AUTO_KINDS, AUTO_MARGIN
from torchfmap.matching.pipeline import match
from torchfmap.matching.quality import geodesic_distortion
from torchfmap.matching.solve import match_bases

from ..conftest import SCALES, _agree, bend, bumpy_blob


@pytest.mark.parametrize(
    ("basis", "refine"),
    [
        ("laplacian", None),
        ("laplacian", "zoomout"),
        ("laplacian", "icp"),
        ("harmonic", "zoomout"),
        ("diffusion", None),
        ("stack", "zoomout"),
        ("stack", "icp"),
        ("eigen_diffusion", None),
        ("eigen_diffusion", "zoomout"),
    ],
)
def test_every_basis_gives_a_good_map(bent_pair, basis, refine):
    x, y, gt = bent_pair
    landmarks = landmarks_from_gt(x, gt, 10) if KINDS[basis].needs_landmarks else None
    result = match(x, y, landmarks=landmarks, basis=basis, k=30, refine=refine)
    assert result.kind == basis
    assert result.p2p_yx.shape == (y.n_vertices,)
    assert result.C_xy.shape[0] == result.C_xy.shape[1] or refine == "zoomout"
    report, _ = evaluate_map(x, y, result.p2p_yx, gt, max_points=300)
    assert report.mean_error < 0.12, report
    if refine is not None:
        initial, _ = evaluate_map(x, y, result.p2p_yx_initial, gt, max_points=300)
        assert report.mean_error <= initial.mean_error * 1.1


def test_subsampled_zoomout_and_p2p_modes(bent_pair):
    x, y, gt = bent_pair
    errors = {}
    for mode in ("orthogonal", "pullback"):
        result = match(x, y, k=20, refine="zoomout", zoomout_samples=300, p2p_mode=mode)
        assert result.C_xy.shape == (40, 40)
        errors[mode] = evaluate_map(x, y, result.p2p_yx, gt, max_points=300)[0].mean_error
    assert max(errors.values()) < 0.12, errors


def test_match_bad_input(bent_pair):
    x, y, gt = bent_pair
    with pytest.raises(ParameterError, match="corresponding landmarks"):
        match(x, y, basis="harmonic")
    with pytest.raises(SeedError, match="out of range"):
        match(x, y, landmarks=[[0, 10**6]], basis="stack")
    with pytest.raises(ParameterError, match=r"\(L, 2\) pairs"):
        match(x, y, landmarks=[1, 2, 3], basis="stack")
    for bad_k in (0, -5, 20.0, x.n_vertices):
        with pytest.raises(ParameterError, match=r"k \(basis size\) must be an integer"):
            match(x, y, k=bad_k)
    with pytest.raises(ParameterError, match="k_final=10 is below k=20"):
        match(x, y, k=20, refine="zoomout", k_final=10)


def test_identity_gt_on_self_match():
    x = bumpy_blob(2)
    result = match(x, x, k=20)
    report, _ = evaluate_map(x, x, result.p2p_yx, gt_identity(x.n_vertices))
    assert report.mean_error < 0.02


def test_match_steps_one_by_one_equal_match(bent_pair):
    """match() is the composition of its public steps: running them by hand gives the same map."""
    from torchfmap import MatchResult
    from torchfmap.bases.prepared import prepare_shape
    from torchfmap.fmap import Refined, fmap_to_p2p, solve_fmap
    from torchfmap.fmap.defaults import W_DCOMM, W_ORIENT
    from torchfmap.kinds import get_kind
    from torchfmap.matching.solve import match_bases, match_descriptors

    x, y, gt = bent_pair
    lm = landmarks_from_gt(x, gt, 6)
    result = match(x, y, landmarks=lm, basis="laplacian", k=20, refine="icp", k_descriptors=40)
    assert isinstance(result, MatchResult)
    sx, sy = prepare_shape(x, 40), prepare_shape(y, 40)
    bx, by, seeds = match_bases(sx, sy, "laplacian", 20, lm)
    assert seeds is None
    assert bx.k == by.k == 20 and bx.stiffness is not None
    dx, dy = match_descriptors(sx, sy, lm, k_descriptors=40)
    C = solve_fmap(
        bx,
        by,
        dx,
        dy,
        w_lap=KINDS["laplacian"].w_lap,
        w_orient=W_ORIENT,
        w_dcomm=W_DCOMM,
        meshes=(x, y),
        landmarks=lm,
        w_lmk=1.0,
    )
    p2p = fmap_to_p2p(C, bx, by, mode="orthogonal")
    np.testing.assert_array_equal(p2p, result.p2p_yx_initial)
    kind = get_kind("laplacian")
    refined = kind.refiner("icp")(C, p2p, sx, sy, bx, by, seeds)
    assert isinstance(refined, Refined) and refined.seeds is None
    C, p2p = refined.C_xy, refined.p2p_yx
    np.testing.assert_array_equal(p2p, result.p2p_yx)
    np.testing.assert_array_equal(C, result.C_xy)


@pytest.fixture(scope="module")
def chosen(bent_pair):
    x, y, gt = bent_pair
    lm = landmarks_from_gt(x, gt, 8)
    shapes = (prepare_shape(x, 60), prepare_shape(y, 60))
    return lm, shapes, match(x, y, landmarks=lm, k=24, refine="zoomout", shapes=shapes)


def test_default_solves_every_kind_and_keeps_the_least_distorted(bent_pair, chosen):
    x, y, gt = bent_pair
    lm, shapes, result = chosen
    assert set(result.candidates) == set(AUTO_KINDS) and not result.skipped
    assert result.kind in AUTO_KINDS
    g = {name: c.distortion for name, c in result.candidates.items()}
    best = min(g, key=g.get)
    expected = best if g[best] <= (1 - AUTO_MARGIN) * g["laplacian"] else "laplacian"
    assert result.kind == expected
    # the reported distortion is the returned map's
    assert result.distortion == pytest.approx(geodesic_distortion(*shapes, result.p2p_yx))
    assert "*" in result.scores() and result.kind in result.scores()
    report, _ = evaluate_map(x, y, result.p2p_yx, gt, max_points=300)
    assert report.mean_error < 0.12


def test_candidates_are_the_forced_kinds(bent_pair, chosen):
    """Each candidate is what basis=<kind> gives on the same prepared shapes: the eigenbasis
    refined as asked, the feature-aware kinds unrefined unless chosen."""
    x, y, _ = bent_pair
    lm, shapes, result = chosen
    for name, cand in result.candidates.items():
        refine = "zoomout" if name == "laplacian" or name == result.kind else None
        forced = match(x, y, landmarks=lm, k=24, basis=name, refine=refine, shapes=shapes)
        np.testing.assert_array_equal(cand.p2p_yx, forced.p2p_yx)
        assert cand.distortion == pytest.approx(forced.distortion)


def test_forced_basis_and_no_landmarks_do_not_choose(bent_pair):
    x, y, gt = bent_pair
    assert match(x, y, k=20).kind == "laplacian"
    assert match(x, y, k=20).candidates == {} and match(x, y, k=20).distortion is None
    forced = match(x, y, landmarks=landmarks_from_gt(x, gt, 6), k=20, basis="diffusion")
    assert forced.kind == "diffusion" and forced.candidates == {} and forced.distortion > 0
    with pytest.raises(ParameterError, match="basis='auto' chooses among bases built at landmarks"):
        match(x, y, k=20, basis="auto")


def test_a_refinement_that_raises_the_distortion_is_dropped(bent_pair, monkeypatch):
    x, y, gt = bent_pair
    lm = landmarks_from_gt(x, gt, 8)
    eigen = type(KINDS["laplacian"])  # the kind returns its refiner
    real = eigen.zoomout_refiner

    def scrambling(self, **settings):  # a refiner that returns a scattered map
        refiner = real(self, **settings)

        def scattered(*args):
            bad = np.random.default_rng(0).integers(0, x.n_vertices, y.n_vertices)
            return refiner(*args)._replace(p2p_yx=bad)

        return scattered

    monkeypatch.setattr(eigen, "zoomout_refiner", scrambling)
    result = match(x, y, landmarks=lm, k=20, basis="laplacian", refine="zoomout")
    assert not result.refined
    np.testing.assert_array_equal(result.p2p_yx, result.p2p_yx_initial)
    monkeypatch.setattr(eigen, "zoomout_refiner", real)
    kept = match(x, y, landmarks=lm, k=20, basis="laplacian", refine="zoomout")
    assert kept.refined and kept.distortion <= result.distortion


def test_skipped_kinds_are_reported_not_fatal(bent_pair):
    """A feature-aware kind that cannot be built (more columns than corresponding seeds allow)
    is skipped with its reason; the eigenbasis still answers."""
    x, y, gt = bent_pair
    small_x, small_y = (m.copy() for m in (x, y))
    lm = landmarks_from_gt(x, gt, 4)
    result = match(small_x, small_y, landmarks=lm, k=1, refine=None)
    assert "hybrid" in result.skipped and "k >= 2" in result.skipped["hybrid"]
    assert result.kind in result.candidates


def test_match_never_calls_itself(bent_pair, monkeypatch):
    """``match`` dispatches to one solve (``solve_pair``) or to the landmark default, which
    solves each candidate with ``solve_pair`` on shapes prepared once: no call of ``match``
    reaches ``match`` again, and the default prepares each shape once."""
    import torchfmap.matching.pipeline as pipeline
    import torchfmap.matching.solve as solve

    x, y, gt = bent_pair
    calls, prepared = [], []
    real_match, real_prepare = pipeline.match, solve.prepare_shape

    def counted(*args, **kwargs):
        calls.append(1)
        return real_match(*args, **kwargs)

    def counted_prepare(mesh, n_eigen, **kwargs):
        prepared.append(mesh)
        return real_prepare(mesh, n_eigen, **kwargs)

    monkeypatch.setattr(pipeline, "match", counted)
    monkeypatch.setattr(solve, "prepare_shape", counted_prepare)
    result = pipeline.match(x, y, landmarks=landmarks_from_gt(x, gt, 6), k=16, refine="zoomout")
    assert calls == [1] and set(result.candidates) == set(AUTO_KINDS)
    assert len(prepared) == 2 and prepared[0] is x and prepared[1] is y
    pipeline.match(x, y, k=16, refine="icp")
    assert calls == [1, 1]


def test_zoomout_of_given_eigenbases_grows_within_them(bent_pair):
    """Eigenbases given as files (here of the robust Laplacian, as `torchfmap basis --laplacian
    robust` saves them) are solved in their first k columns and ZoomOut grows the map within
    *their* eigenfunctions: the refined map's bases are the given ones and its C is the given
    bases' map of the point map (earlier, ZoomOut ran in the prepared cotan eigenbases: solved
    in one basis, refined in another). Bases with fewer columns than k_final are refused."""
    from torchfmap.bases import laplacian_eigenbasis
    from torchfmap.fmap import zoomout
    from torchfmap.operators import laplacian

    x, y, gt = bent_pair
    bx, by = (laplacian_eigenbasis(m, 40, operators=laplacian(m, scheme="robust")) for m in (x, y))
    result = match(x, y, bases=(bx, by), k=20, refine="zoomout")
    assert result.refined and result.C_xy.shape == (40, 40)
    for given, used in ((bx, result.basis_x), (by, result.basis_y)):
        np.testing.assert_array_equal(used.values, given.values)
    raw = match(x, y, bases=(bx.truncated(20), by.truncated(20)))
    np.testing.assert_array_equal(result.p2p_yx_initial, raw.p2p_yx)  # solved in the first k columns
    C, p2p = zoomout(raw.C_xy, bx, by, 40)  # ZoomOut of that map in the given eigenbases
    np.testing.assert_array_equal(result.p2p_yx, p2p)
    np.testing.assert_array_equal(result.C_xy, C)
    assert evaluate_map(x, y, result.p2p_yx, gt, max_points=300)[0].mean_error < 0.12
    with pytest.raises(ParameterError, match="holds? 40.*Fix: save bases with at least 60"):
        match(x, y, bases=(bx, by), k=30, refine="zoomout")
    with pytest.raises(ParameterError, match="the given bases hold 40"):
        match(x, y, bases=(bx, by), refine="zoomout")  # k = 50 by default: 100 eigenfunctions


@pytest.fixture(scope="module")
def saved(bent_pair, tmp_path_factory):
    x, y, gt = bent_pair
    lm = landmarks_from_gt(x, gt, 8)
    bx, by, _ = match_bases(prepare_shape(x, 0), prepare_shape(y, 0), "diffusion", 30, lm)
    folder = tmp_path_factory.mktemp("bases")
    bx.save(folder / "a.npz")
    by.save(folder / "b.npz")
    return lm, Basis.load(folder / "a.npz"), Basis.load(folder / "b.npz")


def test_pair_bases_from_files_match_like_the_landmark_call(bent_pair, saved):
    x, y, gt = bent_pair
    lm, bx, by = saved
    direct = match(x, y, landmarks=lm, basis="diffusion", k=30)
    given = match(x, y, bases=(bx, by))
    assert given.kind == "diffusion"  # the files' kind, not 'stack'
    e_direct = evaluate_map(x, y, direct.p2p_yx, gt, max_points=300)[0].mean_error
    e_given = evaluate_map(x, y, given.p2p_yx, gt, max_points=300)[0].mean_error
    # the same bases and the same pull to C = I; the descriptors differ (no landmark kernels)
    assert e_given <= 1.5 * e_direct + 0.01, (e_given, e_direct)
    refined = match(x, y, bases=(bx, by), refine="zoomout")  # the kind's own refinement
    assert refined.seeds is not None and refined.p2p_yx.shape == (y.n_vertices,)


def test_swapped_bases_are_refused(bent_pair, saved):
    x, y, _ = bent_pair
    _, bx, by = saved
    with pytest.raises(ParameterError, match="fit the meshes in the other order"):
        match(x, y, bases=(by, bx))
    np.testing.assert_array_equal(bx.pair_landmarks, by.pair_landmarks)


def test_a_basis_of_another_mesh_with_as_many_vertices_is_named(bent_pair, saved):
    """Vertex areas fingerprint the mesh a basis was built on: a basis of another pose of the same
    connectivity draws a warning naming it; bases of this mesh built with any mass scheme
    torchfmap has, or of the mesh written with 6 digits and read back (its areas moved by
    rounding), draw none."""
    from torchfmap import laplacian
    from torchfmap.matching.checks import MASS_FIT_TOL, mass_mismatch

    x, y, _ = bent_pair
    _, bx, by = saved
    other = x.copy(bend(x.vertices, 0.6))  # as many vertices, the same faces, another pose
    assert mass_mismatch(by, other) > 10 * MASS_FIT_TOL
    with pytest.warns(MapWarning, match="basis_y's vertex areas are not mesh_y's.*torchfmap basis"):
        match(x, other, bases=(bx, by))
    rounded = Mesh(np.array([[float(f"{c:.6g}") for c in v] for v in y.vertices]), y.faces)
    own = [prepare_shape(y, 20, operators=laplacian(y, mass=m)).eigenbasis for m in ("barycentric", "fem")]
    own.append(prepare_shape(y, 20, laplacian="robust").eigenbasis)
    ex = prepare_shape(x, 20).eigenbasis
    for mesh, basis in [(rounded, by)] + [(y, b) for b in own]:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            match(x, mesh, bases=(ex if basis is not by else bx, basis))
        assert not [w for w in caught if "vertex areas" in str(w.message)], mesh


@pytest.mark.parametrize("kind", ["diffusion", "harmonic", "stack"])
def test_feature_bases_have_exactly_k_orthonormal_corresponding_columns(kind):
    """Every feature-aware basis honours k: k B-orthonormal columns on both shapes, column i
    built at seed pair i (landmarks first)."""
    x = bumpy_blob(3)
    y = x.copy(bend(x.vertices, 0.3))
    lm = np.array([[5, 5], [300, 300], [500, 500]])
    sx, sy = prepare_shape(x, 0), prepare_shape(y, 0)
    bx, by, seeds = match_bases(sx, sy, kind, 25, lm)
    assert bx.k == by.k == 25
    # modified Gram-Schmidt with re-orthogonalisation: orthogonality to a few eps per column
    tol = 100 * 25 * np.finfo(float).eps
    np.testing.assert_allclose(bx.gram(), np.eye(25), atol=tol)
    np.testing.assert_allclose(by.gram(), np.eye(25), atol=tol)
    np.testing.assert_array_equal(seeds[: len(lm)], lm)
    seed_of = {int(a): int(b) for a, b in seeds}
    for cx, cy in zip(bx.columns, by.columns, strict=True):
        assert cx.family == cy.family and cx.time == cy.time and seed_of[cx.seed] == cy.seed


def test_exact_seeds_on_a_permuted_copy_give_the_identity_map(permuted_pair):
    """With an exact copy, trilateration places every seed exactly, the bases correspond
    exactly, C = I and the point map is the permutation, raw and refined."""
    x, y, perm, lm = permuted_pair
    result = match(x, y, landmarks=lm, basis="diffusion", k=30, refine="zoomout")
    inverse = np.argsort(perm)
    np.testing.assert_array_equal(result.seeds[:, 1], inverse[result.seeds[:, 0]])
    np.testing.assert_array_equal(result.p2p_yx_initial, perm)
    np.testing.assert_array_equal(result.p2p_yx, perm)


@pytest.mark.parametrize("refine", [None, "zoomout"])
@pytest.mark.parametrize("name", list(KINDS))
def test_match_of_a_scaled_target_is_the_same_map(small_bent_pair, name, refine):
    """``match(x, c y) == match(x, y)``. The frames of ``c y`` and ``y`` differ by round-off
    (a relative 1e-16), which moves the bases by far less than the gap between a vertex's
    nearest and second-nearest match except at exact near-ties: the point maps agree on (at
    least) 99 % of the vertices and the functional maps to 1e-8 of their size; at ``c = 2``
    (exact in floating point) they are identical."""
    x, y, lm = small_bent_pair
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


def test_unused_settings_are_refused(bent_pair, tmp_path, capsys):
    x, y, gt = bent_pair
    lm = landmarks_from_gt(x, gt, 6)
    with pytest.raises(ParameterError, match="k_final=40 is the size ZoomOut grows"):
        match(x, y, k=20, k_final=40)
    with pytest.raises(ParameterError, match="k_final=40 is the size ZoomOut grows"):
        match(x, y, k=20, k_final=40, landmarks=lm, refine="icp")
    with pytest.raises(ParameterError, match="the laplacian basis has none"):
        match(x, y, k=20, times=[0.01], landmarks=lm, basis="laplacian")
    with pytest.raises(ParameterError, match="the laplacian basis has none"):
        match(x, y, k=20, times=[0.01])
    # the default with landmarks passes times to its feature-aware candidate only
    assert match(x, y, k=20, times=[0.01], landmarks=lm).candidates
    save_mesh(x, tmp_path / "x.off")
    save_mesh(y, tmp_path / "y.off")
    args = ["match", str(tmp_path / "x.off"), str(tmp_path / "y.off"), "--out", str(tmp_path / "m.txt")]
    assert main([*args, "--k", "20", "--k-final", "40"]) == 2
    err = capsys.readouterr().err
    assert "--k-final 40 is the size ZoomOut grows" in err and "--refine zoomout" in err
    assert main([*args, "--k", "20", "--times", "0.01"]) == 2
    assert "--times are the heat times" in capsys.readouterr().err


def test_match_on_a_small_mesh_names_the_real_limit():
    """A 42-vertex mesh with k=10 used to be told 'got k=100' (the hidden descriptor count)."""
    from torchfmap import match

    s = icosphere(1)
    result = match(s, s, k=10)
    assert result.p2p_yx.shape == (42,)
    with pytest.raises(ParameterError, match=r"k \(basis size\) must be an integer in \[1, 41\]"):
        match(s, s, k=60)


def test_one_based_landmarks_are_flagged():
    """Landmarks read 1-based were accepted (0.022 -> 0.444 on the demo pair): when the
    pairs shifted by -1 fit the shapes' geodesic distances far better, match warns."""
    import warnings

    from torchfmap import match
    from torchfmap.data import demo_pair
    from torchfmap.evaluate.scores import gt_from_map, landmarks_from_gt

    a, b, gt_ba = demo_pair()
    lm = landmarks_from_gt(a, gt_from_map(gt_ba), 8)
    with pytest.warns(UserWarning, match="read 1-based"):
        match(a, b, landmarks=lm + 1, k=20)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*1-based.*")
        match(a, b, landmarks=lm, k=20)


def test_misread_landmark_files_are_flagged_on_real_pairs():
    """FAUST_r 070 -> 071 with 7 ground-truth landmarks: read 1-based or with swapped columns,
    match warns and names the reading that fits; as given, it does not warn."""
    import warnings

    from torchfmap import load_mesh, match
    from torchfmap.evaluate.scores import gt_from_vts, landmarks_from_gt
    from torchfmap.io import read_vts

    from ..conftest import data_path

    folder = data_path("faust_r_train")
    x, y = (load_mesh(folder / f"tr_reg_{n}.off") for n in ("070", "071"))
    gt = gt_from_vts(*(read_vts(folder / "corres" / f"tr_reg_{n}.vts") for n in ("070", "071")))
    lm = landmarks_from_gt(x, gt, 7)
    with pytest.warns(UserWarning, match="read 1-based"):
        match(x, y, landmarks=lm + 1, k=20, basis="laplacian")
    with pytest.warns(UserWarning, match="columns swapped"):
        match(x, y, landmarks=lm[:, ::-1].copy(), k=20, basis="laplacian")
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*fit the shapes.*")
        match(x, y, landmarks=lm, k=20, basis="laplacian")


def test_a_collapsed_map_warns():
    x = bumpy_blob(2)
    y = x.copy(bend(x.vertices, 0.3))
    with pytest.warns(MapWarning, match="has collapsed"):
        match(x, y, k=20, w_lap=1e12)
    with warnings.catch_warnings():
        warnings.simplefilter("error", MapWarning)
        match(x, y, k=20)  # a healthy map: no warning


def test_empty_times_are_refused(capsys):
    x = bumpy_blob(1)
    with pytest.raises(ParameterError, match="diffusion times must be finite"):
        match(x, x, landmarks=[[0, 0], [5, 5], [9, 9]], basis="diffusion", times=[], k=10)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["match", "a.off", "b.off", "--out", "m.txt", "--times", ""])
    assert "times must not be empty" in capsys.readouterr().err
    for flag in ("--lr", "--minutes"):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["train", "f", "--out", "m.ckpt", flag, "nan"])


def test_a_k_too_large_for_the_memory_is_refused_before_any_work(monkeypatch, tmp_path, capsys):
    """--k 2000 on a 2.5K mesh passed the range check, ran for minutes and died in a 59.6 GiB
    MemoryError: the solve's estimate is checked first, by every path of match and by the CLI
    (one line: the estimate, the memory available and the fix)."""
    import torchfmap.matching.landmark_default
    import torchfmap.matching.pipeline
    from torchfmap import MemoryEstimateError
    from torchfmap.data import demo_pair
    from torchfmap.fmap.solver import solve_bytes

    a, b, _ = demo_pair()
    needed = solve_bytes(2000, 2000)  # the estimate, and half of it available
    monkeypatch.setattr("torchfmap._util.checks.available_memory", lambda: needed // 2)
    gib = f"{needed / 2**30:.1f} GiB of memory (its row systems grow as k^3), and {needed / 2**31:.1f} GiB"
    for module in (torchfmap.matching.pipeline, torchfmap.matching.landmark_default):
        monkeypatch.setattr(module, "prepare_shapes", lambda *a, **k: pytest.fail("the work started"))
    for landmarks in (None, [[0, 0], [100, 100], [900, 900]]):
        with pytest.raises(MemoryEstimateError) as info:
            match(a, b, k=2000, landmarks=landmarks)
        assert f"k = 2000 needs an estimated {gib} is available. Fix: a smaller k" in str(info.value)
    paths = [str(save_mesh(m, tmp_path / f"{n}.off")) for n, m in (("a", a), ("b", b))]
    assert main(["match", *paths, "--k", "2000", "--out", str(tmp_path / "m.txt"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and gib in err and "Fix: a smaller k (--k" in err


def test_progress_names_each_step_on_stderr(capsys):
    """progress=True: a status line on stderr names the steps as they start (the kinds' steps
    and the landmark default's cross-validation); progress=False (the default) prints nothing."""
    x = bumpy_blob(2)
    y = x.copy(bend(x.vertices, 0.3))
    match(x, y, k=15, k_descriptors=30, progress=True, refine="icp")
    err = capsys.readouterr().err
    steps = (
        "operators",
        "laplacian: eigenpairs",
        "laplacian: functional map",
        "laplacian: point map",
        "laplacian: refinement",
    )
    for step in steps:
        assert f"match: {step}" in err, step
    lm = landmarks_from_gt(x, gt_identity(x.n_vertices), 4)
    match(x, y, k=15, k_descriptors=30, landmarks=lm, progress=True)
    err = capsys.readouterr().err
    assert "match: hybrid: basis" in err and "match: cross-validation: laplacian, fold 1 of 4" in err
    assert "match: refinement check: laplacian, fold 1 of 4" not in err  # refine=None: nothing to check
    lm5 = landmarks_from_gt(x, gt_identity(x.n_vertices), 5)  # enough to cross-validate a refinement
    match(x, y, k=15, k_descriptors=30, landmarks=lm5, progress=True, refine="icp")
    assert "match: refinement check: laplacian, fold 4 of 4" in capsys.readouterr().err
    match(x, y, k=15, k_descriptors=30)
    assert capsys.readouterr().err == ""


def test_match_is_quiet_unless_asked_and_zoomout_shows_its_sizes_when_asked(permuted_pair, capsys):
    """``progress=False`` (the default) writes nothing to stderr, with or without landmarks
    (the landmark default refines every candidate); ``progress=True`` names the steps and shows
    ZoomOut's bar over its sizes."""
    from torchfmap import match

    x, y, _, lm = permuted_pair
    match(x, y, k=10, refine="zoomout")
    match(x, y, k=10, refine="zoomout", landmarks=lm)
    assert capsys.readouterr().err == ""
    match(x, y, k=10, refine="zoomout", progress=True)
    err = capsys.readouterr().err
    assert "ZoomOut" in err and "refinement" in err


def test_empty_or_bad_times_are_refused_before_any_work(monkeypatch):
    """``times=[]`` with landmarks used to be accepted: the feature-aware candidate was skipped
    and the eigenbasis returned without a word. Refused for every kind, before the operators."""
    import torchfmap.matching.pipeline as pipeline

    x = bumpy_blob(2)
    lm = np.array([[0, 0], [50, 50], [100, 100]])
    monkeypatch.setattr(pipeline, "prepare_shapes", lambda *a, **k: pytest.fail("work began"))
    for times in ([], [0.0], [float("nan")]):
        for basis in (None, "hybrid", "diffusion"):
            with pytest.raises(ParameterError, match="times must be finite and > 0"):
                match(x, x, landmarks=lm, times=times, basis=basis)
