"""The losses of a pair batch (``torchfmap.nn.train``): plug-in terms added to the loss, the
unsupervised validation score, the run's state."""

from __future__ import annotations

import pytest
import torch

from torchfmap import save_mesh
from torchfmap.nn import TrainConfig, TrainState, adapt, build_model, unsupervised_score
from torchfmap.nn.config import build_solver
from torchfmap.nn.data import ShapeDataset, collate_pairs
from torchfmap.nn.train import ExtraLoss, forward_pair, pair_loss

from ..conftest import bend, bumpy_blob

TINY = TrainConfig(k=8, n_wks=6, k_net=16, width=8, c_out=8, n_blocks=1)


@pytest.fixture
def shapes(tmp_path):
    mesh = bumpy_blob(2)
    files = [
        save_mesh(mesh, tmp_path / "a0.off"),
        save_mesh(mesh.copy(bend(mesh.vertices, 0.3)), tmp_path / "a1.off"),
    ]
    return ShapeDataset(files, False, **TINY.dataset_kwargs(), progress=False)


class MapNorm:
    """A plug-in term: the squared norm of ``C_xy`` times ``weight``."""

    name = "norm"

    def __init__(self, weight: float) -> None:
        self.weight = weight

    def __call__(self, out, batch, *, solver, loss_fn, generator):
        value = self.weight * out.C_xy.square().sum()
        return {"total": value, "raw": value / self.weight}


def test_plug_in_terms_are_logged_by_name_and_added_to_the_total(shapes):
    net, solver, loss_fn = build_model(TINY)
    loss_fn.n_samples = 0  # no draws: the two calls see the same loss
    batch = collate_pairs([(shapes[0], shapes[1])])
    plain = pair_loss(net, solver, loss_fn, batch)
    extra = MapNorm(0.5)
    assert isinstance(extra, ExtraLoss)
    terms = pair_loss(net, solver, loss_fn, batch, extra_losses=[extra])
    out = forward_pair(net, solver, batch)
    torch.testing.assert_close(terms["norm_raw"], out.C_xy.square().sum())
    torch.testing.assert_close(terms["total"], plain["total"] + 0.5 * terms["norm_raw"])
    assert set(plain) < set(terms) and {"norm_total", "norm_raw"} <= set(terms)


def test_the_validation_score_is_the_mean_full_loss_and_leaves_eval_mode(shapes):
    net, solver, loss_fn = build_model(TINY)
    score = unsupervised_score(shapes, [(0, 1), (1, 0)], solver, loss_fn)
    net.train()
    value = score(net)
    assert not net.training and loss_fn.n_samples == TINY.loss_weights["n_samples"]  # a copy had 0
    full = build_solver(TINY)[1]
    full.n_samples = 0
    with torch.no_grad():
        each = [float(pair_loss(net, solver, full, collate_pairs([(shapes[a], shapes[b])]))["total"])
                for a, b in [(0, 1), (1, 0)]]  # fmt: skip
    assert value == pytest.approx(sum(each) / 2, rel=1e-6)
    with_extra = unsupervised_score(shapes, [(0, 1)], solver, loss_fn, extra_losses=[MapNorm(1.0)])(net)
    assert with_extra > each[0]


def test_the_validation_scores_pairs_moved_as_training_moves_them(shapes, tmp_path):
    """XYZ inputs and augment 'up': the score is of turned pairs (not of the pairs as stored,
    which a network trained facing one way would win), drawn once (every call the same), and
    from the seed; WKS inputs are never moved (the training's rule)."""
    from torchfmap import ParameterError

    xyz = TrainConfig(**{**TINY.__dict__, "inputs": "xyz", "augment": "up"})
    mesh = bumpy_blob(2)
    files = [
        save_mesh(mesh, tmp_path / "b0.off"),
        save_mesh(mesh.copy(bend(mesh.vertices, 0.3)), tmp_path / "b1.off"),
    ]
    data = ShapeDataset(files, False, **xyz.dataset_kwargs(), progress=False)
    net, solver, loss_fn = build_model(xyz)
    stored = unsupervised_score(data, [(0, 1)], solver, loss_fn)(net)
    turned = unsupervised_score(data, [(0, 1)], solver, loss_fn, augment="up")
    assert turned(net) == turned(net) != stored
    assert unsupervised_score(data, [(0, 1)], solver, loss_fn, augment="up", seed=1)(net) != turned(net)

    class HeightOnly(torch.nn.Module):
        """Features of the height alone, scaled to unit maximum: unchanged by a turn about y
        and a scaling, so the turned pairs score as stored (to float32 rounding of the turn)."""

        def forward(self, inputs, basis, grad):
            y = inputs[..., 1:2] / inputs[..., 1:2].abs().amax(dim=1, keepdim=True)
            return torch.cat([y, y.square(), y**3], dim=-1)

    as_stored = unsupervised_score(data, [(0, 1)], solver, loss_fn)(HeightOnly())
    assert turned(HeightOnly()) == pytest.approx(as_stored, rel=1e-3)
    wks_net, wks_solver, wks_loss = build_model(TINY)
    on_wks = unsupervised_score(shapes, [(0, 1)], wks_solver, wks_loss, augment="rigid")(wks_net)
    assert on_wks == unsupervised_score(shapes, [(0, 1)], wks_solver, wks_loss)(wks_net)
    with pytest.raises(ParameterError, match="augment must be one of"):
        unsupervised_score(data, [(0, 1)], solver, loss_fn, augment="yaw")


def test_a_fresh_state_and_adapt_returns_a_tuned_copy(shapes):
    state = TrainState()
    assert state.step == 0 and state.losses == [] and state.best_score == float("inf")
    net, solver, loss_fn = build_model(TINY)
    before = [p.detach().clone() for p in net.parameters()]
    tuned = adapt(net, solver, loss_fn, shapes[0], shapes[1], steps=2, lr=1e-2)
    assert all(torch.equal(p, q) for p, q in zip(before, net.parameters(), strict=True))
    assert any(not torch.equal(p, q) for p, q in zip(before, tuned.parameters(), strict=True))
