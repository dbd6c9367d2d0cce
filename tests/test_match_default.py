"""The landmark default of match: it chooses a basis kind by geodesic distortion, reports why,
and never keeps a refinement that raises the distortion."""

from __future__ import annotations

import numpy as np
import pytest

import torchfmap.results
from torchfmap import ParameterError
from torchfmap.bases.prepared import prepare_shape
from torchfmap.eval import evaluate_map, landmarks_from_gt
from torchfmap.pipeline import AUTO_KINDS, AUTO_MARGIN, match
from torchfmap.quality import geodesic_distortion


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
    eigen = type(torchfmap.KINDS["laplacian"])  # the kind owns its refinement
    real = eigen.refine

    def scrambling(*args, **kwargs):  # a refinement that returns a scattered map
        out = real(*args, **kwargs)
        bad = np.random.default_rng(0).integers(0, x.n_vertices, y.n_vertices)
        return out._replace(p2p_yx=bad)

    monkeypatch.setattr(eigen, "refine", scrambling)
    result = match(x, y, landmarks=lm, k=20, basis="laplacian", refine="zoomout")
    assert not result.refined
    np.testing.assert_array_equal(result.p2p_yx, result.p2p_yx_initial)
    monkeypatch.setattr(eigen, "refine", real)
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


def test_cli_line_names_the_choice(tmp_path, bent_pair, capsys):
    from torchfmap import save_mesh
    from torchfmap.cli import main

    x, y, gt = bent_pair
    save_mesh(x, tmp_path / "x.off")
    save_mesh(y, tmp_path / "y.off")
    np.savetxt(tmp_path / "lm.txt", landmarks_from_gt(x, gt, 8), fmt="%d")
    files = [str(tmp_path / "x.off"), str(tmp_path / "y.off")]
    args = ["match", *files, "--landmarks", str(tmp_path / "lm.txt")]
    assert main([*args, "--k", "20", "--out", str(tmp_path / "m.txt")]) == 0
    out = capsys.readouterr().out
    assert "chosen by geodesic distortion (laplacian" in out and "hybrid" in out


def test_seeded_refinement_solves_again_at_the_seeds_its_map_agrees_on(bent_pair, capsys, tmp_path):
    """``refine='seeded'``: stage 1 is the ZoomOut map; stage 2 is the match with the consistent
    seeds of stage 1 as landmarks (its ``seeds`` start with them), refined; both are kept in
    ``candidates``; landmarks are refused (the stage seeds itself); the CLI runs it."""
    x, y, gt = bent_pair
    result = match(x, y, k=20, refine="seeded")
    first = result.first_stage
    assert first is not None and first.first_stage is None and result.candidates == {}
    np.testing.assert_array_equal(first.p2p_yx, match(x, y, k=20, refine="zoomout").p2p_yx)
    assert result.distortion is not None and result.kind == "laplacian"  # solved with landmarks
    errors = [evaluate_map(x, y, r.p2p_yx, gt, max_points=300)[0].mean_error for r in (first, result)]
    assert errors[1] <= 2.0 * errors[0] + 0.01  # a second solve at agreeing seeds stays a good map
    with pytest.raises(ParameterError, match="refine='seeded' seeds a second solve"):
        match(x, y, k=20, refine="seeded", landmarks=landmarks_from_gt(x, gt, 4))
    from torchfmap import save_mesh
    from torchfmap.cli import main

    a, b = save_mesh(x, tmp_path / "x.off"), save_mesh(y, tmp_path / "y.off")
    assert (
        main(["match", str(a), str(b), "--k", "20", "--refine", "seeded", "--out", str(tmp_path / "m.txt")])
        == 0
    )
