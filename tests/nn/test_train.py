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


def test_a_fresh_state_and_adapt_returns_a_tuned_copy(shapes):
    state = TrainState()
    assert state.step == 0 and state.losses == [] and state.best_score == float("inf")
    net, solver, loss_fn = build_model(TINY)
    before = [p.detach().clone() for p in net.parameters()]
    tuned = adapt(net, solver, loss_fn, shapes[0], shapes[1], steps=2, lr=1e-2)
    assert all(torch.equal(p, q) for p, q in zip(before, net.parameters(), strict=True))
    assert any(not torch.equal(p, q) for p, q in zip(before, tuned.parameters(), strict=True))
