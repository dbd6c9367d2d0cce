"""Training (``torchfmap.nn.train``): a short run on dev data, step budgets, augmentations,
``train_recipe``, and 2-process DDP on the CPU."""

from __future__ import annotations

import socket
import time
from dataclasses import asdict

import numpy as np
import pytest
import torch

from torchfmap import save_mesh
from torchfmap.eval import gt_from_vts
from torchfmap.io import read_vts
from torchfmap.nn.checkpoints import load_checkpoint, read_checkpoint
from torchfmap.nn.config import TrainConfig, build_model
from torchfmap.nn.data import PairDataset, ShapeDataset
from torchfmap.nn.inference import evaluate
from torchfmap.nn.train import ddp_worker, total_steps, train

from ..conftest import bend, bumpy_blob, data_path


def test_short_training_improves_dev_pair(tmp_path):
    folder = data_path("tosca5k_dev")
    files = [folder / "cat0.off", folder / "cat1.off"]
    config = TrainConfig(k=20, n_wks=16, k_net=32, lr=3e-3, width=32, c_out=32, n_blocks=2)
    shapes = ShapeDataset(files, tmp_path, **config.dataset_kwargs(), progress=False)
    gt = gt_from_vts(read_vts(folder / "corres" / "cat0.vts"), read_vts(folder / "corres" / "cat1.vts"))
    net, solver, loss_fn = build_model(config)
    before = evaluate(net, shapes, [(0, 1)], [gt], solver, max_points=200)
    ckpt = tmp_path / "net.ckpt"
    opt = torch.optim.Adam(net.parameters(), lr=config.lr)
    state = train(
        net,
        PairDataset(shapes),
        loss_fn,
        opt,
        solver=solver,
        epochs=8,
        checkpoint=ckpt,
        config=config,
        progress=False,
    )
    after = evaluate(net, shapes, [(0, 1)], [gt], solver, max_points=200)
    first, last = state.losses[0]["total"], np.mean([t["total"] for t in state.losses[-4:]])
    assert last < first
    assert after < before
    loaded, cfg, meta = load_checkpoint(ckpt, best=False)
    assert cfg == config and meta["train_state"]["epoch"] == 8
    for a, b in zip(loaded.state_dict().values(), net.state_dict().values(), strict=True):
        assert torch.equal(a, b)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
@pytest.mark.slow
def test_ddp_ranks_agree_and_follow_the_time_budget_and_schedule_of_one_process(tmp_path, blob_files):
    """Two DDP ranks (gloo) end with identical, trained weights; the run reads its whole budget
    from the config (train_recipe): a time budget stops it (the epochs alone would run far
    longer) and the cosine schedule reaches its floor there. (One spawn checks both.)"""
    budget_s = 4.0
    config = TrainConfig(
        k=8,
        n_wks=8,
        k_net=8,
        epochs=None,
        minutes=budget_s / 60,
        width=16,
        c_out=16,
        n_blocks=1,
        clip_grad=1.0,
    )
    t0 = time.perf_counter()
    torch.multiprocessing.spawn(
        ddp_worker,
        args=(2, _free_port(), blob_files, tmp_path / "cache", asdict(config), tmp_path / "ddp.ckpt"),
        nprocs=2,
    )
    assert time.perf_counter() - t0 < 120  # spawn and imports included; the epochs are unbounded
    ckpt = read_checkpoint(tmp_path / "ddp.ckpt")
    state = ckpt["train_state"]
    # training stops at the first step boundary after the budget: within one step of it
    steps = max(state["step"], 1)
    assert budget_s <= state["seconds"] <= budget_s + 3 * state["seconds"] / steps + 1.0
    assert ckpt["config"]["minutes"] == config.minutes and ckpt["config"]["clip_grad"] == 1.0
    lr = ckpt["optimizer"]["param_groups"][0]["lr"]
    assert lr == pytest.approx(config.lr * 0.02, rel=0.05)  # the cosine's floor at the budget's end
    w0, w1 = torch.load(tmp_path / "rank0.pt"), torch.load(tmp_path / "rank1.pt")
    assert w0.keys() == w1.keys()
    for key in w0:
        assert torch.equal(w0[key], w1[key]), key
    untrained = build_model(config)[0].state_dict()
    assert any(not torch.equal(w0[k], untrained[k]) for k in w0)  # it did train


def test_train_refuses_an_unknown_augmentation(tmp_path):
    from torchfmap.errors import ParameterError

    mesh = bumpy_blob(2)
    files = [save_mesh(mesh, tmp_path / "a0.off"), save_mesh(mesh.scaled(1.2), tmp_path / "a1.off")]
    shapes = ShapeDataset(files, False, k=8, n_wks=6, k_net=16, progress=False)
    net, solver, loss = build_model(TrainConfig(k=8, n_wks=6, width=8, c_out=8, n_blocks=1))
    opt = torch.optim.Adam(net.parameters())
    with pytest.raises(ParameterError, match="augment must be one of"):
        train(net, PairDataset(shapes), loss, opt, solver=solver, augment="spin", max_steps=1, progress=False)


def test_step_bound_of_each_budget_kind():
    assert total_steps(100, 5) == 500
    assert total_steps(100, 5, max_steps=120) == 120
    assert total_steps(100, None, max_steps=120) == 120
    assert total_steps(100, None) is None  # time budget only


def test_adapt_returns_a_tuned_copy_and_train_recipe_reads_its_config(tmp_path):
    """``adapt``: the network given is left as it was, the copy moved; ``train_recipe``: the
    recipe's network trained for the config's budget."""
    from torchfmap.nn import TrainConfig, adapt, train_recipe
    from torchfmap.nn.config import build_solver
    from torchfmap.nn.data import ShapeDataset

    mesh = bumpy_blob(2)
    files = [
        save_mesh(mesh, tmp_path / "a0.off"),
        save_mesh(mesh.copy(bend(mesh.vertices, 0.3)), tmp_path / "a1.off"),
    ]
    config = TrainConfig(k=8, n_wks=6, k_net=16, width=8, c_out=8, n_blocks=1, epochs=None, max_steps=2)
    shapes = ShapeDataset(files, False, **config.dataset_kwargs(), progress=False)
    state, net = train_recipe(config, shapes, progress=False)
    assert state.step == 2
    before = [p.detach().clone() for p in net.parameters()]
    solver, loss_fn = build_solver(config)
    tuned = adapt(net, solver, loss_fn, shapes[0], shapes[1], steps=2, lr=1e-2)
    assert all(torch.equal(p, q) for p, q in zip(before, net.parameters(), strict=True))
    assert any(not torch.equal(p, q) for p, q in zip(before, tuned.parameters(), strict=True))
