"""Shipped pretrained models (``torchfmap.nn.shipped``): resolved by name, small, provenance
inside; a file wins over a name."""

from __future__ import annotations

import pytest

from torchfmap import ParameterError
from torchfmap.nn.checkpoints import load_checkpoint
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
