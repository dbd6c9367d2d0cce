"""The benchmark runner (``python -m bench``): each suite's smallest case runs in ``--quick`` mode on
the shipped demo pair or tiny synthetic meshes (no ../shared/data) and writes its results file,
a table whose rows are the compared methods; settings are checked; pyFM is optional."""

from __future__ import annotations

import json
import shutil
import sys

import pytest

from bench import pairs
from bench.__main__ import SUITES, cases, main
from tools import ship_model
from torchfmap.nn.checkpoints import load_checkpoint
from torchfmap.nn.shipped import MODELS_DIR

#: suite -> (its smallest case, extra settings, the methods its table compares).
SMALLEST = {
    "accuracy": ("weight_sweep", [], ["laplacian w_lap=0.1", "diffusion w_lap=0.1"]),
    "speed": ("eigenpairs", [], ["arpack", "block"]),
    "learned": ("checkpoints", ["all_rules=false", "adapt=0"], ["trained, fmap", "trained, fmap + zoomout"]),
    "robustness": ("fuzz", ["readers=off,map"], ["off", "map"]),
}


def _methods(markdown: str) -> list[str]:
    """The ``method`` column of every table row in a results file."""
    methods, column = [], None
    for line in markdown.splitlines():
        if not line.startswith("|") or line.startswith("|---"):
            column = None if not line.startswith("|") else column
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        if "method" in cells and column is None:
            column = cells.index("method")
        elif column is not None:
            methods.append(cells[column])
    return methods


@pytest.mark.slow
@pytest.mark.parametrize("suite", sorted(SUITES))
def test_smallest_case_writes_a_table_of_the_methods(suite, tmp_path, monkeypatch):
    case, settings, expected = SMALLEST[suite]
    assert case in cases(suite)
    had_pyfm = "pyFM" in sys.modules
    argv = [suite, "--case", case, "--quick", "--out", str(tmp_path)]
    argv += [a for s in settings for a in ("--set", s)]
    if suite == "accuracy":  # pyFM absent: its rows are left out with a note, the case still runs
        monkeypatch.setitem(sys.modules, "pyFM", None)
        argv += ["--set", 'pyfm={"refine": []}']
    written = main(argv)
    assert written == [tmp_path / f"{suite}_{case}.md"]
    text = written[0].read_text()
    assert set(expected) <= set(_methods(text)), text
    if suite == "accuracy":
        assert "pyFM (PyPI pyfmaps) is not installed" in text and "pyFM |" not in text
        assert (tmp_path / f"{suite}_{case}.csv").is_file()
    elif not had_pyfm:
        assert "pyFM" not in sys.modules  # no case that does not compare with pyFM imports it


def test_settings_are_checked_and_merged(tmp_path, capsys):
    with pytest.raises(SystemExit, match="unknown setting.*nonsense"):
        main(["speed", "--case", "eigenpairs", "--quick", "--set", "nonsense=1", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="unknown case"):
        main(["speed", "--case", "nope"])
    config = tmp_path / "c.json"
    config.write_text(json.dumps({"eigenpairs": {"sizes": [300], "ks": [10]}}))
    (path,) = main(
        [
            "speed",
            "--case",
            "eigenpairs",
            "--quick",
            "--config",
            str(config),
            "--name",
            "tiny",
            "--out",
            str(tmp_path),
        ]
    )
    assert path.name == "speed_eigenpairs_tiny.md" and '"sizes": [300]' in path.read_text()
    main(["learned", "--list"])
    assert "stage_two" in capsys.readouterr().out


def test_a_case_without_its_data_is_skipped(tmp_path, monkeypatch):
    monkeypatch.setattr("bench.common.DATA_DIR", tmp_path / "absent")
    assert main(["accuracy", "--case", "weight_sweep", "--out", str(tmp_path)]) == []
    with pytest.raises(pairs.Skip):
        pairs.expand(["@tosca_test"])


@pytest.mark.slow
def test_the_species_split_holds_whole_shape_families_out():
    """``smal_families`` partitions the 32 SMAL_r animals; the split validates on whole families
    (the two smallest), so no validation animal shares a family with a training one; the four
    hippos (named so in the folder) are one family, which a signature blind to proportions would
    not give."""
    try:
        families = pairs.smal_families()
    except pairs.Skip as why:
        pytest.skip(str(why))
    names = [n for f in families for n in f]
    assert len(names) == len(set(names)) == 32 and len(families) == 5
    train, val = pairs.smal_family_split(families)
    assert set(train) | set(val) == set(names) and not set(train) & set(val)
    assert all(set(f) <= set(val) or set(f) <= set(train) for f in families)
    assert sorted(val) == sorted(families[0] + families[1])
    hippos = {n for n in names if "hippo" in n.lower()}
    assert len(hippos) == 4 and any(set(f) == hippos for f in families)


def test_re_documenting_a_shipped_model_keeps_its_run_and_replaces_what_is_given(tmp_path, monkeypatch):
    src = tmp_path / "src" / "faust_r.ckpt"
    src.parent.mkdir()
    shutil.copy(MODELS_DIR / "faust_r.ckpt", src)
    monkeypatch.setattr(ship_model, "MODELS_DIR", tmp_path)
    before = load_checkpoint(src)[2]["provenance"]
    ship_model.main([str(src), "faust_r", "--validation", "new figures"])
    net, _, after = load_checkpoint(tmp_path / "faust_r.ckpt")
    assert after["provenance"] == before | {"validation": "new figures"}
    for a, b in zip(load_checkpoint(src)[0].state_dict().values(), net.state_dict().values(), strict=True):
        assert (a == b).all()  # the same weights


def test_shipping_needs_every_field_a_checkpoint_cannot_give(tmp_path, monkeypatch, capsys):
    src = tmp_path / "faust_r.ckpt"
    shutil.copy(MODELS_DIR / "faust_r.ckpt", src)
    monkeypatch.setattr(ship_model, "MODELS_DIR", tmp_path / "out")
    monkeypatch.setattr(ship_model, "load_checkpoint", lambda path: (None, None, {}))
    with pytest.raises(SystemExit):
        ship_model.main([str(src), "x", "--command", "c"])
    assert "--data, --validation, --use required" in capsys.readouterr().err
