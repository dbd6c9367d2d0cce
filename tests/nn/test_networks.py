"""Feature networks (``torchfmap.nn.networks``): DiffusionNet's invariance, the plug-in protocol
(``FeatureNetwork``, ``check_network``, ``features``) and a user-written network trained and
rebuilt from its checkpoint."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
import torch

from torchfmap import Mesh
from torchfmap.errors import ParameterError
from torchfmap.nn.checkpoints import load_checkpoint, read_checkpoint
from torchfmap.nn.config import Budget, TrainConfig
from torchfmap.nn.data import PairDataset, ShapeDataset, collate_shapes
from torchfmap.nn.inputs import shape_arrays, shape_item
from torchfmap.nn.modules import UnsupervisedFMLoss
from torchfmap.nn.networks import DiffusionNet, FeatureNetwork, check_network, features
from torchfmap.nn.trainer import Trainer

from ..conftest import TinyNet, _batch, _grid, _identity_folder, bumpy_blob, random_rotation


def test_diffusion_net_with_wks_is_invariant_to_rigid_motions():
    """WKS, the eigenbasis and the gradient-feature magnitudes are intrinsic or frame-free; the
    eigensolver converges to ~1e-10, so outputs agree to 1e-6 of their scale. A reflection
    (mirror and re-wind faces) changes the output: gradient features see orientation."""
    mesh = bumpy_blob(2)
    rng = np.random.default_rng(3)
    moved = mesh.copy(mesh.vertices @ random_rotation(rng).T * 1.0 + rng.normal(size=3))
    torch.manual_seed(0)
    net = DiffusionNet(6, 8, width=16, n_blocks=2).double().eval()
    with torch.no_grad():
        a, b = (features(net, _batch(m)) for m in (mesh, moved))
    scale = float(a.abs().max())
    torch.testing.assert_close(a, b, rtol=0, atol=1e-6 * scale)
    mirrored = Mesh(mesh.vertices * np.array([-1.0, 1, 1]), mesh.faces[:, ::-1])
    with torch.no_grad():
        c = features(net, _batch(mirrored))
    assert float((a - c).abs().max()) > 1e-3 * scale


NETWORKS = {
    "DiffusionNet": lambda: DiffusionNet(6, 5, width=8, n_blocks=1),
    "TinyNet": lambda: TinyNet(6, 5),
}


def _padded_batch():
    """Two shapes of 42 and 36 vertices (vertex padding), K = 6, K_net = 8, float64."""
    items = [
        shape_item(shape_arrays(m, 6, 6, 20, k_net=8), dtype=torch.float64) for m in (bumpy_blob(1), _grid(6))
    ]
    return collate_shapes(items)


@pytest.mark.parametrize("name", sorted(NETWORKS))
def test_networks_follow_the_protocol(name):
    """Called with the protocol's arguments ``(inputs, basis, grad)`` on a padded batch of two
    shapes, every network returns ``(B, V, C)`` in the inputs' dtype; the static protocol type
    names the same call."""
    batch = _padded_batch()
    assert batch.lengths.tolist() == [42, 36]
    assert list(inspect.signature(FeatureNetwork.__call__).parameters) == ["self", "inputs", "basis", "grad"]
    for dtype in (torch.float64, torch.float32):
        torch.manual_seed(0)
        net = NETWORKS[name]().to(dtype).eval()  # eval: no dropout draws
        check_network(net)
        shape = batch.to(dtype)
        out = net(shape.inputs, shape.net_basis, shape.grad)
        assert out.shape == (2, 42, 5) and out.dtype == dtype
        torch.testing.assert_close(features(net, shape), out, rtol=0, atol=0)


class TwoArguments(torch.nn.Module):
    def forward(self, inputs, basis):
        return inputs


class WrongDtype(TinyNet):
    def forward(self, inputs, basis, grad):
        return super().forward(inputs, basis, grad).float()


def test_code_that_takes_networks_refuses_non_conforming_ones():
    """``len`` passed the old ``isinstance(net, FeatureNetwork)`` check; now a non-module, a
    forward without ``grad`` and an output in another dtype are refused, by the functions that
    take networks (Trainer, features)."""
    for bad in (len, lambda inputs, basis, grad: inputs):
        with pytest.raises(ParameterError, match="must be a torch.nn.Module"):
            check_network(bad)
    with pytest.raises(ParameterError, match=r"forward must take \(inputs, basis, grad\)"):
        check_network(TwoArguments())
    opt = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1.0)
    with pytest.raises(ParameterError, match="must be a torch.nn.Module"):
        Trainer(len, None, UnsupervisedFMLoss(), opt)
    with pytest.raises(ParameterError, match="returned"):
        features(WrongDtype(6, 5).double(), _padded_batch())


def test_user_network_plugs_in_and_its_checkpoint_rebuilds_it(tmp_path):
    folder = _identity_folder(tmp_path)
    shapes = ShapeDataset(folder, False, k=8, n_wks=6, k_net=12, dtype=torch.float64, progress=False)
    net = TinyNet(6).double()
    before = [p.detach().clone() for p in net.parameters()]
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    loss = UnsupervisedFMLoss(n_samples=100)  # sampled coupling: draws from the trainer's generator
    ckpt = tmp_path / "tiny.ckpt"
    run = TrainConfig(k=8, n_wks=6, k_net=12).with_budget(Budget(steps=3))  # the loop's settings
    trainer = Trainer(net, PairDataset(shapes), loss, opt, config=run, device="cpu", checkpoint=ckpt)
    state = trainer.fit(progress=False)
    assert state.step == 3 and all(np.isfinite(t["total"]) for t in state.losses)
    assert any(not torch.equal(a, b) for a, b in zip(before, net.parameters(), strict=True))
    # the checkpoint records the class and its arguments: load_checkpoint rebuilds a TinyNet
    record = read_checkpoint(ckpt)["network"]
    assert record == {"class": f"{TinyNet.__module__}:TinyNet", "kwargs": {"c_in": 6, "c_out": 8}}
    loaded, config, _ = load_checkpoint(ckpt)
    assert type(loaded) is TinyNet and config == run and not loaded.training
    for a, b in zip(loaded.state_dict().values(), net.state_dict().values(), strict=True):
        assert a.dtype == b.dtype and torch.equal(a, b)
    batch = collate_shapes([shapes[0]])
    with torch.no_grad():
        torch.testing.assert_close(features(loaded, batch), features(net.eval(), batch), rtol=0, atol=0)
    # the same training twice gives the same losses: every draw comes from seeded generators
    again = TinyNet(6).double()
    again.load_state_dict(dict(zip(again.state_dict(), before, strict=True)))
    opt = torch.optim.Adam(again.parameters(), lr=1e-2)
    loss = UnsupervisedFMLoss(n_samples=100)
    repeat = Trainer(again, PairDataset(shapes), loss, opt, config=run, device="cpu").fit(progress=False)
    assert [t["total"] for t in repeat.losses] == [t["total"] for t in state.losses]
