"""Command-line messages (``torchfmap.cli.messages``): fixes in flag terms, not Python arguments;
error lines name the class once."""

from __future__ import annotations

import numpy as np
import pytest

import torchfmap
from torchfmap import Mesh, save_mesh
from torchfmap.cli import in_cli_terms, main
from torchfmap.data import icosphere

from ..conftest import _err


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


def _whole_and_part():
    from torchfmap.data.cuts import cut_plane

    whole = icosphere(3)
    return whole, cut_plane(whole, 0.5, seed=0).mesh


def test_partial_and_mesh_fixes_become_flags():
    """The partial checks, the unreferenced-vertex refusal and the collapse warning, said by the
    library, reach the command line with flags (or what the command line cannot do, said so)."""
    from torchfmap.matching.checks import warn_if_partial
    from torchfmap.mesh_checks import validate_mesh

    texts = []
    for call in (
        lambda: torchfmap.match(*_whole_and_part(), partial=True, basis="diffusion"),
        lambda: validate_mesh(np.eye(4, 3), np.array([[0, 1, 2]])),
    ):
        with pytest.raises(torchfmap.TorchFmapError) as err:
            call()
        texts.append(in_cli_terms(str(err.value)))
    with pytest.warns(torchfmap.MapWarning) as record:
        warn_if_partial(*_whole_and_part())
    texts.append(in_cli_terms(str(record[0].message)))
    for text in texts:
        assert "=True" not in text.replace("allow_unreferenced=True", ""), text
    assert "--partial" in texts[0] and "--partial" in texts[2]
    assert texts[2].startswith("the target mesh looks partial"), texts[2]  # no Python names
    collapse = "Fix: check the weights (w_lap, w_orient), the landmarks"  # quality.warn_collapsed's
    assert in_cli_terms(collapse) == "Fix: check the weight --w-lap, the landmarks"


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
