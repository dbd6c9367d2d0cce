"""The command line: demo on the shipped pair, info on a file, clean errors."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import load_mesh
from torchfmap.cli import main
from torchfmap.data import demo_pair, demo_pair_paths, make_demo_pair


def test_shipped_demo_pair_is_consistent():
    a, b, gt = demo_pair()
    assert a.n_vertices == b.n_vertices == len(gt)
    assert np.array_equal(np.sort(gt), np.arange(a.n_vertices))
    # regenerating gives the same files (the generator is deterministic)
    a2, b2, gt2 = make_demo_pair()
    assert np.array_equal(gt, gt2)
    assert np.allclose(a.vertices, a2.vertices, atol=1e-7) and np.allclose(b.vertices, b2.vertices, atol=1e-7)
    # the bend is near-isometric: areas agree to 1 %
    assert abs(a.area - b.area) < 0.01 * a.area


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
    assert {c.kind for c in basis.provenance} == {"diffusion", "harmonic"}
    seeds = [c.seed for c in basis.provenance if c.kind == "harmonic"]
    assert seeds[:2] == [10, 200]
    assert {c.time for c in basis.provenance if c.kind == "diffusion"} == {0.01, 0.001}
    # with the command's own defaults, every kind works (no landmarks needed to build one basis)
    for kind in ("harmonic", "eigen_diffusion"):
        assert main(["basis", str(mesh_path), "--kind", kind, "--k", "12", "--out", str(out), "--quiet"]) == 0
        assert Basis.load(out).k == 12
    assert main(["basis", str(mesh_path), "--out", str(out), "--quiet"]) == 0
    assert {c.kind for c in Basis.load(out).provenance} == {"laplacian"}
    assert (
        main(["basis", str(mesh_path), "--landmarks", str(lm), "--basis", "laplacian", "--out", str(out)])
        == 2
    )
    assert "has none" in capsys.readouterr().err
    lm.write_text("10 99\n200 5\n")  # a pairs file is not a landmark list: refused, not half-read
    assert main([*args, "--out", str(out), "--quiet"]) == 2
    assert "expected 1 integer column" in capsys.readouterr().err


def test_version_and_defaults_in_help(capsys):
    import pytest

    import torchfmap

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and torchfmap.__version__ in capsys.readouterr().out
    for command, flag in (
        ("match", "--k"),
        ("eval", "--gt-landmarks"),
        ("basis", "--k"),
        ("train", "--k"),
    ):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        text = capsys.readouterr().out
        assert flag in text and "(default: " in text, command


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
