"""The command line (``torchfmap.cli``): the parser (help and defaults, version, ``--quiet``, the
basis choices), output paths checked before the work, a broken pipe."""

from __future__ import annotations

import subprocess
import sys

import pytest

from torchfmap.cli import build_parser, main
from torchfmap.kinds import KINDS

from ..conftest import DEMO


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


def test_broken_pipe_ends_quietly(tmp_path):
    cmd = f"{sys.executable} -m torchfmap info {DEMO}/blob_a.off | head -c 10"
    done = subprocess.run(
        ["bash", "-c", f"set -o pipefail; {cmd}"], capture_output=True, text=True, timeout=120
    )
    assert "Traceback" not in done.stderr and "BrokenPipe" not in done.stderr


@pytest.mark.parametrize("command", ["basis", "match", "eval", "train"])
def test_help_shows_each_default_once_and_none_for_required_options(command, capsys):
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: None)" not in text and "(default: False)" not in text
    for line in text.split("--")[1:]:
        assert line.count("default") <= 1, line


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
            ["basis", str(a), "--basis", "laplacian", "--k", "8", "--out", str(tmp_path / "a.npz"), "--quiet"]
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


def test_every_kind_is_offered_by_the_commands_that_take_a_basis():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices
    for command, flag in (
        ("match", "--basis"),
        ("eval", "--basis"),
        ("train", "--basis"),
        ("basis", "--basis"),
    ):
        action = next(a for a in sub[command]._actions if flag in a.option_strings)
        offered = [n for n, kind in KINDS.items() if kind.learned or command != "train"]
        choose = ["auto"] if command in ("match", "eval") else []  # the landmark default's choice
        assert list(action.choices) == choose + offered, command


def test_cli_output_paths_are_checked_before_the_work(tmp_path, sphere2, capsys):
    from torchfmap import save_mesh

    path = str(save_mesh(sphere2, tmp_path / "s.off"))
    for out, message in ((tmp_path / "missing" / "m.txt", "no folder"), (tmp_path, "is a folder")):
        code = main(["match", path, path, "--k", "5", "--out", str(out)])
        assert code == 2 and message in capsys.readouterr().err


def test_match_out_dash_writes_the_map_to_stdout_and_status_to_stderr(tmp_path, capsys, monkeypatch):
    from torchfmap.data import demo_pair_paths

    monkeypatch.chdir(tmp_path)
    a, b, _ = demo_pair_paths()
    assert main(["match", str(a), str(b), "--k", "10", "--out", str(tmp_path / "m.txt"), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["match", str(a), str(b), "--k", "10", "--out", "-"]) == 0
    out, err = capsys.readouterr()
    assert out == (tmp_path / "m.txt").read_text() and "-> stdout" in err
    assert not (tmp_path / "-").exists()
