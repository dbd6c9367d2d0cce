"""Checkpoints (``torchfmap.nn.checkpoints``): checksummed and weights only (foreign or corrupt
files refused, nothing in them run), provenance, networks rebuilt from their record, old files."""

from __future__ import annotations

import io
import pickle
from dataclasses import asdict, replace

import numpy as np
import pytest
import torch

from torchfmap import ParameterError
from torchfmap._util.files import save_checked_bytes
from torchfmap.cli import main
from torchfmap.errors import CorruptFileError
from torchfmap.nn.checkpoints import (
    load_checkpoint,
    load_network,
    network_record,
    read_checkpoint,
    save_checkpoint,
)
from torchfmap.nn.config import TrainConfig, build_model
from torchfmap.nn.networks import DiffusionNet

from ..conftest import DEMO, TinyNet, _err


def test_checkpoints_are_checksummed_and_load_no_code(tmp_path):
    """Checkpoints had no checksum (38 of 40 byte flips loaded) and loaded with
    weights_only=False (pickled code from the file would run)."""
    import torch

    from torchfmap.errors import CorruptFileError
    from torchfmap.nn.checkpoints import read_checkpoint, save_checkpoint

    net = torch.nn.Linear(3, 2)
    path = save_checkpoint(tmp_path / "m.ckpt", net, {"k": 5}, note="x")
    back = read_checkpoint(path)
    torch.testing.assert_close(back["state_dict"]["weight"], net.weight.detach())
    data = bytearray(path.read_bytes())
    rng = np.random.default_rng(0)
    for i in rng.choice(len(data), 20, replace=False):
        flipped = bytearray(data)
        flipped[i] ^= 0xFF
        bad = tmp_path / "bad.ckpt"
        bad.write_bytes(bytes(flipped))
        with pytest.raises(CorruptFileError):
            read_checkpoint(bad)
    plain = tmp_path / "plain.pt"
    torch.save({"state_dict": net.state_dict()}, plain)  # no header: refused, never unpickled
    with pytest.raises(CorruptFileError, match=r"not a torchfmap checkpoint.*torch.save.*load_state_dict"):
        read_checkpoint(plain)


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


def _checked(path, payload: bytes):
    from torchfmap._util.files import save_checked_bytes

    return save_checked_bytes(path, payload)


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
def test_foreign_pickle_behind_a_valid_header_is_refused_not_run(tmp_path, capsys):
    """A pickle of ``os.system`` with a valid checksummed header: refused as a corrupt
    checkpoint (API and CLI), and the payload never runs."""
    from torchfmap.nn.checkpoints import load_checkpoint

    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            import os

            return (os.system, (f"touch {marker}",))

    path = _checked(tmp_path / "evil.ckpt", pickle.dumps(Payload()))
    with pytest.raises(CorruptFileError, match="not a weights-only torch file.*Nothing in it was run"):
        load_checkpoint(path)
    src, tgt = f"{DEMO}/blob_a.off", f"{DEMO}/blob_b.off"
    assert main(["match", src, tgt, "--checkpoint", str(path), "--out", str(tmp_path / "m.txt")]) == 2
    assert "holds no torchfmap checkpoint" in _err(capsys)
    assert not marker.exists()


def test_checkpoint_without_weights_or_with_weights_that_do_not_fit(tmp_path):
    import torch

    from torchfmap.nn.checkpoints import load_checkpoint, read_checkpoint, save_checkpoint
    from torchfmap.nn.config import TrainConfig, build_model

    buffer = io.BytesIO()
    torch.save({"config": {}}, buffer)
    path = _checked(tmp_path / "noweights.ckpt", buffer.getvalue())
    with pytest.raises(CorruptFileError, match=r"without \['state_dict'\]"):
        read_checkpoint(path)
    config = TrainConfig(k=8, n_wks=8, width=8, c_out=8)
    net = build_model(config)[0]
    good = save_checkpoint(tmp_path / "good.ckpt", net, config)
    ckpt = read_checkpoint(good)
    ckpt["state_dict"]["head.weight"] = torch.zeros(3, 3)  # wrong size for the recorded network
    buffer = io.BytesIO()
    torch.save(ckpt, buffer)
    bad = _checked(tmp_path / "bad.ckpt", buffer.getvalue())
    with pytest.raises(
        ParameterError, match="weights do not fit.*size mismatch.*Fix: the config and the weights"
    ):
        load_checkpoint(bad)
    ckpt["state_dict"] = [1, 2]
    buffer = io.BytesIO()
    torch.save(ckpt, buffer)
    with pytest.raises(ParameterError, match="not a state dict"):
        load_checkpoint(_checked(tmp_path / "list.ckpt", buffer.getvalue()))


def test_checkpoints_refuse_networks_they_cannot_rebuild(tmp_path):
    class Local(TinyNet):  # defined in a function: not importable
        pass

    path = save_checkpoint(tmp_path / "local.ckpt", Local(6), {})
    with pytest.raises(ParameterError, match="cannot be imported"):
        load_checkpoint(path)
    path = save_checkpoint(tmp_path / "nowhere.ckpt", TinyNet(6), {})
    ckpt = read_checkpoint(path)
    ckpt["network"]["class"] = "torchfmap.nowhere:TinyNet"
    with pytest.raises(ParameterError, match="cannot import"):
        load_network(ckpt)
    ckpt["network"]["class"] = "torchfmap.errors:ParameterError"
    with pytest.raises(ParameterError, match="not a torch.nn.Module"):
        load_network(ckpt)
    plain = torch.nn.Linear(3, 2)  # no init_kwargs: the record has the class only
    assert network_record(plain) == {"class": "torch.nn.modules.linear:Linear", "kwargs": None}
    with pytest.raises(ParameterError, match="not its constructor arguments"):
        load_checkpoint(save_checkpoint(tmp_path / "linear.ckpt", plain, {}))
    back = load_checkpoint(
        save_checkpoint(tmp_path / "args.ckpt", plain, {}, net_kwargs={"in_features": 3, "out_features": 2})
    )[0]
    assert torch.equal(back.weight, plain.weight)
    with pytest.raises(ParameterError, match="plain values"):
        save_checkpoint(tmp_path / "bad.ckpt", plain, {}, net_kwargs={"in_features": torch.ones(1)})
    # a checkpoint without the record (a development format never released): refused, named
    config = TrainConfig(k=8, n_wks=6, k_net=8, width=8, c_out=8, n_blocks=1)
    net = build_model(config)[0]
    buffer = io.BytesIO()
    torch.save({"state_dict": net.state_dict(), "config": asdict(config)}, buffer)
    old = save_checked_bytes(tmp_path / "old.ckpt", buffer.getvalue())
    with pytest.raises(ParameterError, match="does not record its network.*Fix: train it again"):
        load_checkpoint(old)
    # the recipe's network records itself and comes back the same
    again = load_checkpoint(save_checkpoint(tmp_path / "new.ckpt", net, config))[0]
    stacked = replace(config, basis="stack")  # a new checkpoint's 'stack' is the stack kind
    assert load_checkpoint(save_checkpoint(tmp_path / "stack.ckpt", net, stacked))[1].basis == "stack"
    assert type(again) is DiffusionNet and again.init_kwargs == net.init_kwargs


def test_a_checkpoints_recipe_reads_back_without_its_network(tmp_path):
    """``read_recipe``: the config a checkpoint records, as a ``TrainConfig``, written back as a
    recipe file."""
    from torchfmap.nn import TrainConfig, read_recipe

    recipe = read_recipe("smal_r")
    assert recipe == TrainConfig.from_dict(read_checkpoint("smal_r")["config"])
    recipe.to_json(tmp_path / "smal_r.json")
    assert TrainConfig.from_json(tmp_path / "smal_r.json") == recipe


@pytest.mark.parametrize(
    "edit, problem",
    [
        (lambda c: c.update(network="DiffusionNet"), "network record is a str"),
        (lambda c: c["config"].update(k=-3), "k must be >= 1"),
        (lambda c: c["config"].update(lr=float("nan")), "lr must be finite"),
        (lambda c: [t.fill_(float("inf")) for t in c["state_dict"].values()], "NaN or infinite"),
    ],
    ids=["record", "k", "lr", "weights"],
)
def test_checkpoint_contents_are_checked_and_errors_name_the_file(tmp_path, edit, problem):
    """Found by the fuzz suite: a network record that is no dict raised AttributeError, a negative
    k or NaN lr loaded, NaN weights loaded, and errors about the contents did not name the file."""
    config = TrainConfig(k=8, n_wks=8, width=8, c_out=8, n_blocks=1)
    path = save_checkpoint(tmp_path / "m.ckpt", build_model(config)[0], config)
    ckpt = read_checkpoint(path)
    edit(ckpt)
    buffer = io.BytesIO()
    torch.save(ckpt, buffer)
    _checked(path, buffer.getvalue())
    with pytest.raises(ParameterError, match=rf"m\.ckpt: .*{problem}"):
        load_checkpoint(path)
