"""The classical commands (``torchfmap.cli.commands``): ``demo``, ``info``, ``basis``, ``match`` and
``eval`` (also with a checkpoint), their files and clear errors."""

from __future__ import annotations

import re

import numpy as np
import pytest

from torchfmap import Mesh, MeshWarning, load_mesh, save_mesh
from torchfmap.cli import main
from torchfmap.data import demo_pair_paths, icosphere, make_demo_pair
from torchfmap.errors import ParameterError
from torchfmap.evaluate.scores import evaluate_map, landmarks_from_gt

from ..conftest import _err, _identity_folder, bend, bumpy_blob, data_path, requires_plotly, with_fin


@pytest.mark.slow
def test_demo_command(capsys):
    assert main(["demo"]) == 0
    out = capsys.readouterr().out
    assert "blob_a" in out and "blob_b" in out and "first eigenvalues" in out


def test_info_command_and_errors(capsys, tmp_path):
    path = demo_pair_paths()[0]
    assert main(["info", str(path)]) == 0
    assert f"{load_mesh(path).n_vertices} vertices" in capsys.readouterr().out
    bad = tmp_path / "bad.off"
    bad.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\nnan 1 0\n3 0 1 2\n")
    assert main(["info", str(bad)]) == 2
    assert "NaN or infinite" in capsys.readouterr().err


def test_two_components_refused_by_basis_and_named_by_info(tmp_path, capsys):
    a = icosphere(1)
    two = Mesh(
        np.vstack([a.vertices, a.vertices + 3]),
        np.vstack([a.faces, a.faces + a.n_vertices]),
        allow_components=True,
    )
    save_mesh(two, tmp_path / "two.off")
    assert main(["basis", str(tmp_path / "two.off"), "--k", "5", "--out", str(tmp_path / "b.npz")]) == 2
    assert "--allow-components" in capsys.readouterr().err
    out = ["--out", str(tmp_path / "b.npz")]
    assert main(["basis", str(tmp_path / "two.off"), "--k", "5", "--allow-components", *out]) == 0
    capsys.readouterr()
    assert main(["info", str(tmp_path / "two.off")]) == 0
    assert "2 connected components" in capsys.readouterr().out


def test_basis_command(tmp_path, capsys):
    """``torchfmap basis`` builds a registered kind's basis of exactly --k columns: feature-aware
    kinds seeded at --landmarks first (farthest points fill the rest), also without landmarks."""
    from torchfmap import Basis

    mesh_path = demo_pair_paths()[0]
    lm = tmp_path / "landmarks.txt"
    lm.write_text("# two landmarks\n10\n200\n")
    out = tmp_path / "b.npz"
    args = ["basis", str(mesh_path), "--landmarks", str(lm), "--times", "0.01,0.001"]
    assert main([*args, "--basis", "stack", "--k", "18", "--out", str(out), "--quiet"]) == 0
    basis = Basis.load(out)
    assert basis.k == 18 and np.abs(basis.gram() - np.eye(basis.k)).max() < 1e-10
    assert {c.family for c in basis.provenance} == {"diffusion", "harmonic"}
    seeds = [c.seed for c in basis.provenance if c.family == "harmonic"]
    assert seeds[:2] == [10, 200]
    assert {c.time for c in basis.provenance if c.family == "diffusion"} == {0.01, 0.001}
    # with the command's own defaults, every kind works (no landmarks needed to build one basis)
    for kind in ("harmonic", "eigen_diffusion"):
        flags = ["--basis", kind, "--k", "12", "--out", str(out), "--quiet"]
        assert main(["basis", str(mesh_path), *flags]) == 0
        assert Basis.load(out).k == 12
    assert main(["basis", str(mesh_path), "--out", str(out), "--quiet"]) == 0
    assert {c.family for c in Basis.load(out).provenance} == {"laplacian"}
    assert (
        main(["basis", str(mesh_path), "--landmarks", str(lm), "--basis", "laplacian", "--out", str(out)])
        == 2
    )
    assert "has none" in capsys.readouterr().err
    lm.write_text("10 99\n200 5\n")  # a pairs file is not a landmark list: refused, not half-read
    assert main([*args, "--out", str(out), "--quiet"]) == 2
    assert "expected 1 integer column" in capsys.readouterr().err


def test_cli_basis_larger_than_the_mesh_is_a_clear_error(tmp_path, sphere2, capsys):
    from torchfmap import save_mesh

    path = save_mesh(sphere2, tmp_path / "s.off")
    out = str(tmp_path / "b.npz")
    code = main(["basis", str(path), "--basis", "diffusion", "--k", str(sphere2.n_vertices), "--out", out])
    assert code == 2
    assert f"--k {sphere2.n_vertices} needs a mesh of more than" in capsys.readouterr().err


def test_basis_pair_corresponds_and_unrelated_bases_warn(tmp_path, capsys):
    x = bumpy_blob(2)
    y = x.copy(bend(x.vertices, 0.3))
    px, py = save_mesh(x, tmp_path / "x.off"), save_mesh(y, tmp_path / "y.off")
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("3 3\n60 60\n120 120\n")
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    assert (
        main(
            [
                "basis",
                str(px),
                str(py),
                "--landmarks",
                str(pairs),
                "--k",
                "20",
                "--out",
                str(a),
                str(b),
                "--quiet",
            ]
        )
        == 0
    )
    out = tmp_path / "m.txt"
    capsys.readouterr()
    assert main(["match", str(px), str(py), "--bases", str(a), str(b), "--out", str(out), "--quiet"]) == 0
    assert "warning" not in capsys.readouterr().err  # the CLI prints warnings as 'torchfmap: warning:'
    from torchfmap.bases import Basis, prepare_shape
    from torchfmap.matching.solve import match_bases

    built = match_bases(
        prepare_shape(x, 0), prepare_shape(y, 0), "diffusion", 20, np.loadtxt(pairs, dtype=int)
    )
    for saved, fresh in zip((Basis.load(a), Basis.load(b)), built[:2], strict=True):
        # match's own pair; the meshes went through OFF text (9 significant digits), so the
        # values agree to far below any seed mismatch (a wrong seed changes whole columns)
        np.testing.assert_allclose(saved.values, fresh.values, rtol=0, atol=1e-6 * np.abs(fresh.values).max())
        np.testing.assert_array_equal(saved.pair_landmarks, built[2])
    lm = tmp_path / "seeds.txt"
    lm.write_text("3\n60\n120\n")
    for mesh, path in ((px, a), (py, b)):  # one at a time: each mesh seeded on its own
        assert (
            main(["basis", str(mesh), "--landmarks", str(lm), "--k", "20", "--out", str(path), "--quiet"])
            == 0
        )
    main(["match", str(px), str(py), "--bases", str(a), str(b), "--out", str(out), "--quiet"])
    assert "torchfmap: warning: the given bases have seeded columns but were not built" in _err(capsys)
    assert main(["basis", str(px), "--k", "10", "--out", str(tmp_path / "lap.txt")]) == 2
    assert "a basis file is .npz" in _err(capsys)
    assert main(["basis", str(px), str(py), "--k", "10", "--out", str(a)]) == 2
    assert "one --out file per mesh" in _err(capsys)


def test_match_solves_in_saved_bases_from_the_basis_command(tmp_path, capsys):
    """`torchfmap basis` files go straight into `match --bases`; on the demo pair (a bend, close
    to an isometry) the eigenbasis files give the same map as `match --basis laplacian`."""
    src, tgt = (str(p) for p in demo_pair_paths()[:2])
    files = []
    for name, mesh in (("x", src), ("y", tgt)):
        out = tmp_path / f"{name}.npz"
        assert main(["basis", mesh, "--basis", "laplacian", "--k", "30", "--out", str(out), "--quiet"]) == 0
        files.append(str(out))
    via_files, direct = tmp_path / "a.txt", tmp_path / "b.txt"
    assert main(["match", src, tgt, "--bases", *files, "--out", str(via_files)]) == 0
    assert main(["match", src, tgt, "--basis", "laplacian", "--k", "30", "--out", str(direct)]) == 0
    np.testing.assert_array_equal(np.loadtxt(via_files, dtype=int), np.loadtxt(direct, dtype=int))
    assert main(["match", src, tgt, "--bases", files[1], files[0], "--out", str(via_files)]) in (0, 2)
    capsys.readouterr()
    assert (
        main(
            [
                "match",
                src,
                tgt,
                "--bases",
                *files,
                "--refine",
                "zoomout",
                "--basis",
                "stack",
                "--out",
                str(via_files),
            ]
        )
        == 2
    )
    assert "ZoomOut" in capsys.readouterr().err


def test_cli_match_writes_target_to_source_map(tmp_path, bent_pair, capsys):
    from torchfmap import save_mesh

    x, y, gt = bent_pair
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


def test_landmark_pairs_with_swapped_columns_are_named(tmp_path, capsys):
    from torchfmap import save_mesh
    from torchfmap.data import icosphere

    big, small = tmp_path / "big.off", tmp_path / "small.off"
    save_mesh(icosphere(3), big)
    save_mesh(icosphere(1), small)
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("5 600\n7 610\n9 620\n")  # (small vertex, big vertex)
    out = str(tmp_path / "m.txt")
    assert main(["match", str(small), str(big), "--landmarks", str(pairs), "--k", "20", "--out", out]) == 0
    capsys.readouterr()
    assert main(["match", str(big), str(small), "--landmarks", str(pairs), "--k", "20", "--out", out]) == 2
    assert "swap the columns" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "cannot read the landmark pair file"),
        ("", "holds no entries"),
        ("1 2 3\n", "expected 2 integer column"),
        ("1\n", "expected 2 integer column"),
        ("1 x\n", "is not 2 integer vertex index"),
    ],
)
def test_cli_landmark_files_give_clear_errors(tmp_path, sphere2, capsys, content, message):
    from torchfmap import save_mesh

    path = save_mesh(sphere2, tmp_path / "s.off")
    lm = tmp_path / "lm.txt"
    if content is not None:
        lm.write_text(content)
    code = main(["match", str(path), str(path), "--landmarks", str(lm), "--out", str(tmp_path / "m.txt")])
    assert code == 2 and message in capsys.readouterr().err


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
    assert "chosen by geodesic distortion and held-out landmarks (laplacian" in out and "hybrid" in out


def test_cli_matches_nonmanifold_files(tmp_path, capsys):
    base = bumpy_blob(2)
    v, f = with_fin(base)
    with pytest.warns(MeshWarning):
        save_mesh(Mesh(v, f, allow_nonmanifold="warn"), tmp_path / "a.off")
    save_mesh(base, tmp_path / "b.off")
    out = tmp_path / "m.txt"
    capsys.readouterr()
    args = ["match", str(tmp_path / "a.off"), str(tmp_path / "b.off"), "--k", "10", "--out", str(out)]
    assert main(args) == 0
    assert len(np.loadtxt(out)) == base.n_vertices
    # the command line prints a warning as one line, without Python's source line
    err = capsys.readouterr().err
    assert "torchfmap: warning: a: 1 non-manifold edges" in err and ".py:" not in err


@requires_plotly
def test_match_html_writes_the_page(tmp_path, capsys):
    a, b, _ = demo_pair_paths()
    out, html = tmp_path / "map.txt", tmp_path / "map.html"
    assert main(["match", str(a), str(b), "--out", str(out), "--html", str(html)]) == 0
    assert "browser page" in capsys.readouterr().out and html.stat().st_size > 0
    assert main(["match", str(a), str(b), "--out", str(out), "--html", str(tmp_path / "no" / "m.html")]) == 2
    assert "--html" in capsys.readouterr().err


def test_match_command_with_checkpoint(tiny_folder, tmp_path, capsys):
    ckpt = tmp_path / "model.ckpt"
    main(
        [
            "train",
            str(tiny_folder),
            "--out",
            str(ckpt),
            "--k",
            "8",
            "--no-cache",
            "--quiet",
            "--max-steps",
            "2",
        ]
    )
    out = tmp_path / "map.txt"
    src, tgt = tiny_folder / "blob0.ply", tiny_folder / "blob1.ply"
    assert (
        main(
            [
                "match",
                str(src),
                str(tgt),
                "--checkpoint",
                str(ckpt),
                "--out",
                str(out),
                "--adapt",
                "1",
                "--refine",
                "zoomout",
                "--device",
                "cpu",
            ]
        )
        == 0
    )
    p2p = np.loadtxt(out, dtype=np.int64)
    assert p2p.shape == (162,) and p2p.min() >= 0 and p2p.max() < 162
    assert all(line.strip().isdigit() for line in out.read_text().splitlines())
    assert "adapt 1 steps, refine zoomout 8 -> 16, device cpu" in capsys.readouterr().out
    from torchfmap.io import load_mesh
    from torchfmap.nn import LearnedMatcher

    matcher = LearnedMatcher.from_checkpoint(ckpt, device="cpu", adapt_steps=1)
    np.testing.assert_array_equal(p2p, matcher(load_mesh(src), load_mesh(tgt), refine="zoomout").p2p_yx)


def test_match_and_eval_refuse_the_same_flags_with_a_checkpoint(tiny_folder, tmp_path, capsys):
    """One rule for both commands (bug 3: ``eval --checkpoint`` ignored ``--k`` that ``match``
    refused, and refused ``--landmarks`` that ``match`` took): flags the checkpoint fixes are
    refused with the fix, landmarks too (the learned matcher takes none: the classical ``match
    --landmarks`` does), refinement is ZoomOut or none, ``--k-final`` needs ZoomOut, and
    ``--adapt`` / ``--device`` need a checkpoint."""
    ckpt = tmp_path / "model.ckpt"
    args = ["train", str(tiny_folder), "--out", str(ckpt), "--k", "8", "--no-cache", "--quiet"]
    assert main([*args, "--max-steps", "1"]) == 0
    (tmp_path / "lm.txt").write_text("0 0\n5 5\n")
    (tmp_path / "lms").mkdir()
    pair = [str(tiny_folder / "blob0.ply"), str(tiny_folder / "blob1.ply")]
    match = ["match", *pair, "--checkpoint", str(ckpt), "--out", str(tmp_path / "m.txt")]
    evaluate = ["eval", str(tiny_folder), "--checkpoint", str(ckpt)]
    shared = [
        (["--k", "10"], "--k would change nothing"),
        (["--basis", "laplacian"], "--basis would change nothing"),
        (["--w-lap", "0.5"], "--w-lap would change nothing"),
        (["--refine", "icp"], "ZoomOut only"),
        (["--k-final", "20"], "without --refine zoomout it changes nothing"),
    ]
    cases = [(match, extra, message) for extra, message in shared]
    cases += [(evaluate, extra, message) for extra, message in shared]
    cases += [
        (match, ["--bases", "a.npz", "b.npz"], "--bases would change nothing"),
        (match, ["--times", "0.01"], "--times would change nothing"),
        (match, ["--p2p-mode", "pullback"], "--p2p-mode would change nothing"),
        (match, ["--landmarks", str(tmp_path / "lm.txt")], "--landmarks would not be used"),
        (evaluate, ["--landmarks", str(tmp_path / "lms")], "--landmarks would not be used"),
        (evaluate, ["--gt-landmarks", "3"], "--gt-landmarks would not be used"),
        (match[:3] + match[5:], ["--adapt", "2"], "--adapt is a setting of a trained network"),
        (evaluate[:2], ["--device", "cpu"], "--device is a setting of a trained network"),
    ]
    for base, extra, message in cases:
        capsys.readouterr()
        assert main([*base, *extra]) == 2, (base[0], extra)
        err = capsys.readouterr().err
        assert message in err and "Fix:" in err, (base[0], extra, err)
    landmark_err = "drop --checkpoint: the classical pipeline takes them (torchfmap match --landmarks)"
    assert main([*match, "--landmarks", str(tmp_path / "lm.txt")]) == 2
    assert landmark_err in capsys.readouterr().err


def test_eval_on_a_folder_of_gzipped_meshes(tmp_path, capsys):
    """Meshes, .vts ground truth and the test-pairs file may all be .gz (one suffix rule)."""
    import gzip

    from torchfmap import save_mesh
    from torchfmap.data import icosphere
    from torchfmap.io import read_map

    a, b, gt_ba = make_demo_pair(subdivisions=2)
    save_mesh(a, tmp_path / "blob_a.off.gz")
    save_mesh(b, tmp_path / "blob_b.off.gz")
    (tmp_path / "corres").mkdir()
    for name, ids in (("blob_a", gt_ba + 1), ("blob_b", np.arange(1, len(gt_ba) + 1))):
        (tmp_path / "corres" / f"{name}.vts.gz").write_bytes(gzip.compress("\n".join(map(str, ids)).encode()))
    (tmp_path / "test_pairs.txt.gz").write_bytes(gzip.compress(b"blob_a blob_b\n"))
    assert main(["eval", str(tmp_path), "--k", "10", "--quiet"]) == 0
    assert "| blob_a | blob_b |" in capsys.readouterr().out
    # without ground-truth files: consecutive same-size meshes, identity ground truth
    plain = tmp_path / "plain"
    plain.mkdir()
    for name in ("s0", "s1"):
        save_mesh(icosphere(1), plain / f"{name}.ply.gz")
    assert main(["eval", str(plain), "--k", "8", "--quiet"]) == 0
    assert "| s0 | s1 |" in capsys.readouterr().out
    # match writes a gzipped map when asked to
    out = tmp_path / "map.txt.gz"
    meshes = [str(plain / "s0.ply.gz"), str(plain / "s1.ply.gz")]
    assert main(["match", *meshes, "--k", "8", "--out", str(out)]) == 0
    assert read_map(out).shape == (42,)


def test_cli_eval_on_identity_folder(tmp_path, capsys):
    folder = data_path("tosca_hires_wolf")
    png = tmp_path / "pck.png"
    args = ["eval", str(folder), "--k", "30", "--max-pairs", "1", "--max-points", "200", "--png", str(png)]
    assert main([*args, "--threads", "1", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "| wolf0 | wolf1 |" in out and png.exists()
    mean = float(out.split("| **all** | | ")[1].split(" ")[0])
    assert mean < 0.1


def test_eval_scores_saved_maps_and_passes_its_match_settings(tmp_path, monkeypatch, capsys):
    import torchfmap.cli.commands as commands
    from torchfmap.evaluate.scores import discover_pairs

    folder = _identity_folder(tmp_path)
    maps = tmp_path / "maps"
    maps.mkdir()
    pairs = list(discover_pairs(folder))
    for a, b, *_ in pairs:  # the identity for the first pair, a constant map for the rest
        n = 162
        p2p = np.arange(n) if (a, b) == pairs[0][:2] else np.zeros(n, dtype=int)
        (maps / f"{a}-{b}.txt").write_text("\n".join(map(str, p2p)) + "\n")
    assert main(["eval", str(folder), "--maps", str(maps), "--quiet"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| m")]
    assert rows[0].split("|")[3].strip() == "0.0000"  # the exact map scores 0
    assert all(float(r.split("|")[3]) > 0.1 for r in rows[1:])  # the constant map is far off
    (maps / f"{pairs[1][0]}-{pairs[1][1]}.txt").unlink()
    assert main(["eval", str(folder), "--maps", str(maps), "--quiet"]) == 2
    assert f"no saved map {pairs[1][0]}-{pairs[1][1]}.txt" in _err(capsys)
    assert main(["eval", str(folder), "--maps", str(maps), "--basis", "laplacian"]) == 2
    assert "takes no matching options" in _err(capsys)

    seen = {}

    def record(pairs, **kwargs):
        seen.update(kwargs, paths=[p for pair in pairs for p in pair[2:4]])
        return []

    monkeypatch.setattr(commands, "evaluate_pairs", record)
    monkeypatch.chdir(tmp_path)
    try:
        main(["eval", "set", "--k-final", "30", "--w-lap", "0.5", "--k", "12", "--quiet"])
    except ValueError:  # no results to print: the settings were recorded
        pass
    assert seen["k_final"] == 30 and seen["w_lap"] == 0.5 and seen["k"] == 12
    assert all(p.is_absolute() for p in seen["paths"])  # sent resolved, for workers elsewhere


@pytest.mark.slow
def test_eval_command_with_checkpoint_prepares_each_mesh_once_and_pools_agree(
    tiny_folder, tmp_path, capsys, monkeypatch
):
    """``torchfmap eval --checkpoint``: ``evaluate_pairs`` prepares each mesh once and hands the
    prepared shapes to the learned matcher (one Laplacian per mesh in all), the maps are the
    matcher's pair by pair, and a pool of 2 gives the same table."""
    import torchfmap.bases.prepared as prepared
    from torchfmap.evaluate.collection import evaluate_pairs
    from torchfmap.evaluate.scores import discover_pairs, evaluate_map
    from torchfmap.io import load_mesh
    from torchfmap.nn import LearnedMatcher

    ckpt = tmp_path / "model.ckpt"
    train = ["train", str(tiny_folder), "--out", str(ckpt), "--k", "8", "--no-cache", "--quiet"]
    assert main([*train, "--max-steps", "2"]) == 0
    capsys.readouterr()
    pairs = list(discover_pairs(tiny_folder))
    assert len(pairs) >= 2
    made = []
    real = prepared.laplacian_operators
    matcher = LearnedMatcher.from_checkpoint(ckpt, device="cpu")
    monkeypatch.setattr(prepared, "laplacian_operators", lambda *a, **kw: made.append(1) or real(*a, **kw))
    results = evaluate_pairs(pairs, threads=1, matcher=matcher, refine="zoomout")
    monkeypatch.undo()
    assert len(made) == len({p for pair in pairs for p in pair[2:4]})  # once per mesh
    for (_, _, pa, pb, gt), result in zip(pairs, results, strict=True):
        x, y = load_mesh(pa), load_mesh(pb)
        p2p = matcher(x, y, refine="zoomout").p2p_yx
        np.testing.assert_array_equal(result.errors, evaluate_map(x, y, p2p, gt)[1])

    def table(*extra):
        flags = ["--checkpoint", str(ckpt), "--threads", "1", "--quiet", "--device", "cpu", *extra]
        assert main(["eval", str(tiny_folder), *flags]) == 0
        lines = capsys.readouterr().out.splitlines()
        return [line.rsplit("|", 2)[0] for line in lines if line.startswith("| ")], lines[-1]

    one, title = table()
    assert len(one) == len(pairs) + 2 and table("--workers", "2")[0] == one
    rows, title = table("--refine", "zoomout", "--k-final", "12", "--adapt", "1")
    assert len(rows) == len(pairs) + 2
    assert "adapt 1 steps, refine zoomout 8 -> 12, device cpu" in title
    with pytest.raises(ParameterError, match="does not take k, landmarks"):
        evaluate_pairs(pairs, matcher=matcher, gt_landmarks=2, k=8)


def test_cli_eval_and_info_edge_cases(tmp_path, capsys):
    from torchfmap import Mesh, save_mesh

    assert main(["eval", str(tmp_path / "nowhere")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    s = icosphere(1)
    for name in ("a", "b"):
        save_mesh(s, tmp_path / f"{name}.off")
    (tmp_path / "test_pairs.txt").write_text("a c\n")
    assert main(["eval", str(tmp_path)]) == 2
    assert "does not hold" in capsys.readouterr().err
    tet = Mesh(np.eye(4, 3) + [0.1, 0.2, 0.3], [[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    assert main(["info", str(save_mesh(tet, tmp_path / "tet.off"))]) == 0


def test_eval_pairs_protocol_is_chosen_and_said_in_the_footer(tmp_path, sphere2, capsys):
    from torchfmap import save_mesh

    for name in ("a", "b", "c"):
        save_mesh(sphere2, tmp_path / f"{name}.off")
    assert main(["eval", str(tmp_path), "--k", "6", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert out.count("| a | b |") + out.count("| b | c |") == 2 and "| a | c |" not in out
    assert "Pairs: 2 consecutive pairs of 3 meshes in name order (of 6 ordered pairs: --pairs all" in out
    assert main(["eval", str(tmp_path), "--k", "6", "--pairs", "all", "--max-pairs", "4", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert out.count("\n| ") - out.count("| **all**") == 4  # pair rows (the header opens the output)
    assert "Pairs: all 6 ordered pairs of 3 meshes, the first 4 (--max-pairs)." in out
    assert main(["eval", str(tmp_path), "--pairs", "every", "--quiet"]) == 2
    assert "neither a protocol nor an existing file" in capsys.readouterr().err


def test_cli_match_says_the_sizes_and_the_refinement_verdict(tmp_path, bent_pair, capsys):
    """What k means on the line: the start and the size ZoomOut grew it to; with landmarks, the
    guard's verdict and its figures (held-out landmark errors before and after)."""
    from torchfmap import save_mesh

    x, y, gt = bent_pair
    px, py = str(save_mesh(x, tmp_path / "x.off")), str(save_mesh(y, tmp_path / "y.off"))
    out = str(tmp_path / "m.txt")
    assert main(["match", px, py, "--k", "12", "--refine", "zoomout", "--out", out]) == 0
    line = capsys.readouterr().out
    assert "k 12 -> 24 (ZoomOut grows k to --k-final, default 2k), refined by zoomout" in line, line
    lm = tmp_path / "lm.txt"
    np.savetxt(lm, landmarks_from_gt(x, gt, 6), fmt="%d")
    args = [
        "match",
        px,
        py,
        "--k",
        "12",
        "--refine",
        "zoomout",
        "--landmarks",
        str(lm),
        "--out",
        out,
    ]
    assert main(args) == 0
    line = capsys.readouterr().out
    figure = r"\d\.\d{4} -> \d\.\d{4}"
    verdict = rf"\(refinement (kept|dropped).*: geodesic distortion {figure}, held-out landmark error "
    verdict += rf"{figure}\)"
    assert re.search(rf"(refined by zoomout|zoomout dropped) {verdict}", line), line
