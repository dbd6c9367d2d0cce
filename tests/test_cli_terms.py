"""Command-line messages name flags, not Python arguments (torchfmap.cli.in_cli_terms)."""

from __future__ import annotations

import numpy as np

from torchfmap import Mesh, save_mesh
from torchfmap.cli import in_cli_terms, main
from torchfmap.data import icosphere


def test_python_fixes_become_flags():
    assert (
        in_cli_terms("Fix: pass landmarks, or use basis='laplacian'.")
        == "Fix: pass landmarks, or use --basis laplacian."
    )
    assert "--allow-components" in in_cli_terms(
        "or pass allow_components=True and give every component a seed"
    )
    assert in_cli_terms("Fix: refine='icp', or ...") == "Fix: --refine icp, or ..."
    assert "--k (basis size, default 50)" in in_cli_terms(
        "k (basis size) must be an integer in [1, 11], got 50"
    )


def test_cli_errors_name_flags(tmp_path, capsys):
    a, b = icosphere(1), icosphere(2)
    two = Mesh(
        np.vstack([a.vertices, a.vertices + 3]),
        np.vstack([a.faces, a.faces + a.n_vertices]),
        allow_components=True,
    )
    save_mesh(two, tmp_path / "two.off")
    save_mesh(b, tmp_path / "b.off")
    assert (
        main(["match", str(tmp_path / "two.off"), str(tmp_path / "b.off"), "--out", str(tmp_path / "m.txt")])
        == 2
    )
    err = capsys.readouterr().err
    assert "--allow-components" in err and "allow_components=True" not in err
    small = icosphere(0)  # 12 vertices: the default k = 50 does not fit
    save_mesh(small, tmp_path / "s.off")
    assert (
        main(["match", str(tmp_path / "s.off"), str(tmp_path / "s.off"), "--out", str(tmp_path / "m.txt")])
        == 2
    )
    assert "--k (basis size, default 50) must be an integer in [1, 11], got 50" in capsys.readouterr().err


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


def test_quiet_means_the_same_in_every_command(tmp_path, capsys):
    """``--quiet``: no progress and no status lines in every command; the help says so in the
    same words; ``basis --kind`` is the hidden old name of ``--basis``."""
    from torchfmap.cli import build_parser, main
    from torchfmap.data import demo_pair_paths

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices
    helps = {
        n: next(a.help for a in p._actions if "--quiet" in a.option_strings)
        for n, p in sub.items()
        if any("--quiet" in a.option_strings for a in p._actions)
    }
    assert len(set(helps.values())) == 1 and {"match", "eval", "basis", "train"} <= set(helps)
    a, b, _ = demo_pair_paths()
    capsys.readouterr()
    assert (
        main(
            ["basis", str(a), "--kind", "laplacian", "--k", "8", "--out", str(tmp_path / "a.npz"), "--quiet"]
        )
        == 0
    )
    assert main(["match", str(a), str(b), "--k", "10", "--out", str(tmp_path / "m.txt"), "--quiet"]) == 0
    ckpt = str(tmp_path / "m.ckpt")
    flags = [
        "--k",
        "8",
        "--width",
        "8",
        "--c-out",
        "8",
        "--max-steps",
        "1",
        "--validate-every",
        "0",
        "--no-cache",
    ]
    assert main(["train", str(a.parent), "--out", ckpt, *flags, "--quiet"]) == 0
    assert capsys.readouterr().out == ""
