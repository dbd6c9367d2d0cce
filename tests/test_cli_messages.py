"""Command-line messages (``torchfmap.cli_messages``): fixes in flag terms, not Python arguments;
error lines name the class once."""

from __future__ import annotations

import numpy as np

from torchfmap import Mesh, save_mesh
from torchfmap.cli import in_cli_terms, main
from torchfmap.data import icosphere

from .conftest import _err


def test_error_lines_name_the_class_once(tmp_path, capsys):
    assert main(["info", str(tmp_path / "none.off")]) == 2
    err = _err(capsys)
    assert err.startswith("torchfmap: error (MeshError): ") and "TorchFmapError" not in err


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
