"""Argument types of the command line (``torchfmap.cli.types``): bad numbers are usage errors."""

from __future__ import annotations

import pytest

from torchfmap.cli import main


@pytest.mark.parametrize(
    "argv",
    [
        ["basis", "MESH", "--basis", "diffusion", "--times", "1e-3,abc", "--out", "OUT"],
        ["basis", "MESH", "--k", "-2", "--out", "OUT"],
        ["match", "MESH", "MESH", "--k", "0", "--out", "OUT"],
        ["eval", "FOLDER", "--max-points", "-5"],
        ["eval", "FOLDER", "--max-points", "every"],
        ["eval", "FOLDER", "--max-pairs", "-1"],
        ["eval", "FOLDER", "--threads", "0"],
    ],
)
def test_cli_bad_numbers_are_usage_errors(tmp_path, sphere2, capsys, argv):
    """Refused by argparse (usage + 'error: argument ...'), never a traceback after the work."""
    from torchfmap import save_mesh

    mesh = str(save_mesh(sphere2, tmp_path / "s.off"))
    argv = [{"MESH": mesh, "OUT": str(tmp_path / "o.npz"), "FOLDER": str(tmp_path)}.get(a, a) for a in argv]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2 and "error: argument" in capsys.readouterr().err


def test_a_count_says_zero_is_allowed(capsys):
    """``--max-pairs`` takes 0 (all): its refusal of -1 says ">= 0", not ">= 1"."""
    with pytest.raises(SystemExit):
        main(["eval", ".", "--max-pairs", "-1"])
    assert "integer >= 0" in capsys.readouterr().err


def test_max_points_takes_auto_all_or_a_count(capsys):
    """``--max-points``: auto (the default: a sample on dense meshes), all (None: every point) or
    N; a refusal names the three."""
    from torchfmap.cli import build_parser
    from torchfmap.cli.types import point_count

    assert build_parser().parse_args(["eval", "F"]).max_points == "auto"
    assert (point_count("auto"), point_count("all"), point_count("300")) == ("auto", None, 300)
    with pytest.raises(SystemExit):
        main(["eval", ".", "--max-points", "0"])
    assert "must be auto, all or an integer >= 1, got '0'" in capsys.readouterr().err
