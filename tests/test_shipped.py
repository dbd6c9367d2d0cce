"""Shipped pretrained models: resolved by name, provenance inside, listed by `torchfmap models`."""

from __future__ import annotations

import pytest

from torchfmap import ParameterError
from torchfmap.cli import main
from torchfmap.nn.checkpoints import load_checkpoint, read_checkpoint
from torchfmap.nn.shipped import resolve_checkpoint, shipped_models


def test_faust_r_is_shipped_small_and_resolves_by_name():
    models = shipped_models()
    assert "faust_r" in models and models["faust_r"].stat().st_size < 5e6  # "a few MB at most"
    assert resolve_checkpoint("faust_r") == models["faust_r"]
    net, config, ckpt = load_checkpoint("faust_r")
    assert config.k == ckpt["config"]["k"] and sum(p.numel() for p in net.parameters()) > 0
    for key in ("command", "data", "commit", "validation"):
        assert ckpt["provenance"][key]
    assert "070..079" in ckpt["provenance"]["validation"]  # selected on its own split, not the test


def test_a_file_wins_over_a_shipped_name_and_unknown_names_list_the_shipped(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "faust_r").write_bytes(b"not a checkpoint")
    assert resolve_checkpoint("faust_r").resolve() == (tmp_path / "faust_r").resolve()
    with pytest.raises(ParameterError, match="no shipped model of that name.*shipped: .*faust_r"):
        resolve_checkpoint("nope")


def test_provenance_round_trips_through_save_and_read(tmp_path):
    import torch

    from torchfmap.nn.checkpoints import save_checkpoint
    from torchfmap.nn.config import TrainConfig, build_model

    config = TrainConfig(k=8, n_wks=8, width=8, c_out=8, n_blocks=1)
    net = build_model(config)[0]
    prov = {"command": "torchfmap train x", "validation": "0.1"}
    save_checkpoint(tmp_path / "m.ckpt", net, config, provenance=prov)
    assert read_checkpoint(tmp_path / "m.ckpt")["provenance"] == prov
    loaded = load_checkpoint(tmp_path / "m.ckpt")[0]
    for a, b in zip(net.state_dict().values(), loaded.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b)


def test_models_command_lists_the_shipped_models(capsys):
    assert main(["models"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("faust_r") and "command: torchfmap train" in out and "validation:" in out
