"""End-to-end matching: every basis, refinements, the CLI commands, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, SeedError
from torchfmap.bases import KINDS
from torchfmap.cli import main
from torchfmap.eval import Correspondence, evaluate_map, gt_identity, landmarks_from_gt
from torchfmap.pipeline import match

from .conftest import bend, bumpy_blob, data_path


@pytest.fixture(scope="module")
def pair():
    x = bumpy_blob(3)
    perm = np.random.default_rng(2).permutation(x.n_vertices)
    y = x.copy(bend(x.vertices, 0.3)).permuted(perm)
    gt = Correspondence(idx_x=perm, idx_y=np.arange(y.n_vertices))
    return x, y, gt


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
def test_every_basis_gives_a_good_map(pair, basis, refine):
    x, y, gt = pair
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


def test_subsampled_zoomout_and_p2p_modes(pair):
    x, y, gt = pair
    errors = {}
    for mode in ("orthogonal", "pullback"):
        result = match(x, y, k=20, refine="zoomout", zoomout_samples=300, p2p_mode=mode)
        assert result.C_xy.shape == (40, 40)
        errors[mode] = evaluate_map(x, y, result.p2p_yx, gt, max_points=300)[0].mean_error
    assert max(errors.values()) < 0.12, errors


def test_match_bad_input(pair):
    x, y, gt = pair
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


def test_cli_match_writes_target_to_source_map(tmp_path, pair, capsys):
    from torchfmap import save_mesh

    x, y, gt = pair
    px, py = save_mesh(x, tmp_path / "x.off"), save_mesh(y, tmp_path / "y.off")
    lm = tmp_path / "lm.txt"
    np.savetxt(lm, landmarks_from_gt(x, gt, 10), fmt="%d")
    out = tmp_path / "map.txt"
    png = tmp_path / "transfer.png"
    assert (
        main(
            [
                "match",
                str(px),
                str(py),
                "--landmarks",
                str(lm),
                "--k",
                "30",
                "--refine",
                "icp",
                "--out",
                str(out),
                "--png",
                str(png),
            ]
        )
        == 0
    )
    p2p = np.loadtxt(out, dtype=int)
    assert p2p.shape == (y.n_vertices,) and p2p.max() < x.n_vertices
    report, _ = evaluate_map(x, y, p2p, gt, max_points=200)
    assert report.mean_error < 0.12
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    bad = tmp_path / "bad.txt"
    bad.write_text("1\n")
    assert main(["match", str(px), str(py), "--landmarks", str(bad), "--out", str(out)]) == 2
    assert "expected 2 integer column" in capsys.readouterr().err


def test_cli_eval_on_identity_folder(tmp_path, capsys):
    folder = data_path("tosca_hires_wolf")
    png = tmp_path / "pck.png"
    args = ["eval", str(folder), "--k", "30", "--max-pairs", "1", "--max-points", "200", "--png", str(png)]
    assert main([*args, "--threads", "1", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "| wolf0 | wolf1 |" in out and png.exists()
    mean = float(out.split("| **all** | | ")[1].split(" ")[0])
    assert mean < 0.1


def test_identity_gt_on_self_match():
    x = bumpy_blob(2)
    result = match(x, x, k=20)
    report, _ = evaluate_map(x, x, result.p2p_yx, gt_identity(x.n_vertices))
    assert report.mean_error < 0.02


def test_match_steps_one_by_one_equal_match(pair):
    """match() is the composition of its public steps: running them by hand gives the same map."""
    from torchfmap import MatchResult
    from torchfmap.fmap import Refined, fmap_to_p2p, solve_fmap
    from torchfmap.fmap.defaults import W_DCOMM, W_LAP, W_ORIENT
    from torchfmap.kinds import get_kind
    from torchfmap.pipeline import match_bases, match_descriptors, prepare_shape

    x, y, gt = pair
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
        w_lap=W_LAP["laplacian"],
        w_orient=W_ORIENT,
        w_dcomm=W_DCOMM,
        meshes=(x, y),
        landmarks=lm,
        w_lmk=1.0,
    )
    p2p = fmap_to_p2p(C, bx, by, mode="orthogonal")
    np.testing.assert_array_equal(p2p, result.p2p_yx_initial)
    kind = get_kind("laplacian")
    refined = kind.refine(C, p2p, sx, sy, bx, by, "icp", k_final=20, mode="orthogonal")
    assert isinstance(refined, Refined) and refined.seeds is None
    C, p2p = refined.C_xy, refined.p2p_yx
    np.testing.assert_array_equal(p2p, result.p2p_yx)
    np.testing.assert_array_equal(C, result.C_xy)
