"""The maintainers' tools (``tools/``): shipping a model keeps what a re-documentation does not give."""

from __future__ import annotations

import shutil

import pytest

from tools import ship_model
from torchfmap.nn.checkpoints import load_checkpoint
from torchfmap.nn.shipped import MODELS_DIR


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
