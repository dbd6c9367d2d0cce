"""The training loop (``torchfmap.nn.trainer``): a short run on dev data, the recipe read whole
from its config, resuming, 2-process DDP on the CPU (nothing left beside the checkpoint), and
CUDA against CPU where CUDA exists (``tests/test_examples.py`` runs ``examples/04_train.py``)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import torch

from torchfmap import save_mesh
from torchfmap.errors import ParameterError
from torchfmap.evaluate.scores import gt_from_vts
from torchfmap.io import read_vts
from torchfmap.nn import Budget, Trainer
from torchfmap.nn.checkpoints import load_checkpoint, read_checkpoint
from torchfmap.nn.config import TrainConfig, build_model
from torchfmap.nn.data import PairDataset, ShapeDataset
from torchfmap.nn.item_inference import evaluate
from torchfmap.nn.trainer import spawn_ddp

from ..conftest import bend, bumpy_blob, data_path

TINY = TrainConfig(k=8, n_wks=6, k_net=16, width=8, c_out=8, n_blocks=1)


def _two_blobs(folder: Path) -> list[Path]:
    mesh = bumpy_blob(2)
    folder.mkdir(exist_ok=True)
    return [
        save_mesh(mesh, folder / "a0.off"),
        save_mesh(mesh.copy(bend(mesh.vertices, 0.3)), folder / "a1.off"),
    ]


def test_short_training_improves_dev_pair(tmp_path):
    folder = data_path("tosca5k_dev")
    files = [folder / "cat0.off", folder / "cat1.off"]
    config = TrainConfig(k=20, n_wks=16, k_net=32, lr=3e-3, width=32, c_out=32, n_blocks=2, epochs=8)
    shapes = ShapeDataset(files, tmp_path, **config.dataset_kwargs(), progress=False)
    gt = gt_from_vts(read_vts(folder / "corres" / "cat0.vts"), read_vts(folder / "corres" / "cat1.vts"))
    net, solver, loss_fn = build_model(config)
    before = evaluate(net, shapes, [(0, 1)], [gt], solver, max_points=200)
    ckpt = tmp_path / "net.ckpt"
    opt = torch.optim.Adam(net.parameters(), lr=config.lr)
    trainer = Trainer(
        net, PairDataset(shapes), loss_fn, opt, config=config, solver=solver, device="cpu", checkpoint=ckpt
    )
    state = trainer.fit(progress=False)
    after = evaluate(net, shapes, [(0, 1)], [gt], solver, max_points=200)
    first, last = state.losses[0]["total"], np.mean([t["total"] for t in state.losses[-4:]])
    assert last < first
    assert after < before
    loaded, cfg, meta = load_checkpoint(ckpt, best=False)
    assert cfg == config and meta["train_state"]["epoch"] == 8 and state.step == 16
    for a, b in zip(loaded.state_dict().values(), net.state_dict().values(), strict=True):
        assert torch.equal(a, b)


def test_from_config_reads_the_recipe_whole_and_resume_continues_the_run(tmp_path):
    """The recipe's network, Adam at its lr, the cosine over its budget, its clipping; a second
    trainer resumes from the checkpoint: the steps and losses of the first run are kept and the
    schedule ends at its floor at the (whole run's) step bound."""
    files = _two_blobs(tmp_path / "m")
    config = TINY.with_budget(Budget(steps=2))
    shapes = ShapeDataset(files, False, **config.dataset_kwargs(), progress=False)
    ckpt = tmp_path / "r.ckpt"
    first = Trainer.from_config(config, shapes, device="cpu", checkpoint=ckpt)
    assert first.batches_per_epoch == 2 and first.optimizer.param_groups[0]["initial_lr"] == config.lr
    state = first.fit(progress=False)
    assert state.step == 2 and read_checkpoint(ckpt)["train_state"]["step"] == 2
    longer = config.with_budget(Budget(steps=4))
    second = Trainer.from_config(longer, shapes, device="cpu", checkpoint=ckpt)
    assert second.resume() and second.state.step == 2
    state = second.fit(progress=False)
    assert state.step == 4 and len(state.losses) == 4
    assert state.losses[:2] == read_checkpoint(ckpt)["train_state"]["losses"][:2]
    assert second.optimizer.param_groups[0]["lr"] == pytest.approx(config.lr * 0.02)  # the floor
    assert not Trainer.from_config(longer, shapes, device="cpu", checkpoint=tmp_path / "no.ckpt").resume()


def test_validation_keeps_the_best_weights_and_step_returns_the_terms(tmp_path):
    files = _two_blobs(tmp_path / "m")
    shapes = ShapeDataset(files, False, **TINY.dataset_kwargs(), progress=False)
    scores = iter([5.0, 3.0, 1.0, 2.0])  # the untrained network's at step 0, then one a step
    trainer = Trainer.from_config(
        TINY.with_budget(Budget(steps=3)), shapes, device="cpu", validate=lambda net: next(scores),
        validate_every=1, checkpoint=tmp_path / "v.ckpt",
    )  # fmt: skip
    state = trainer.fit(progress=False)
    assert state.scores == [(0, 5.0), (1, 3.0), (2, 1.0), (3, 2.0)] and state.best_score == 1.0
    best = read_checkpoint(tmp_path / "v.ckpt")["best_state_dict"]
    assert any(not torch.equal(best[k], v) for k, v in trainer.net.state_dict().items())
    batch = next(iter(trainer.loader))
    terms = trainer.step(batch)
    assert set(terms) >= {"total", "bij", "orth"} and trainer.state.step == 4


def test_a_trainer_refuses_an_unknown_augmentation_device_or_budget(tmp_path):
    files = _two_blobs(tmp_path / "m")
    shapes = ShapeDataset(files, False, **TINY.dataset_kwargs(), progress=False)
    net, solver, loss = build_model(TINY)
    opt = torch.optim.Adam(net.parameters())
    with pytest.raises(ParameterError, match="augment must be one of"):
        Trainer(net, PairDataset(shapes), loss, opt, config=TrainConfig(augment="spin"), device="cpu")
    with pytest.raises(ParameterError, match="unknown device"):
        Trainer(net, PairDataset(shapes), loss, opt, device="tpu")
    with pytest.raises(ParameterError, match="needs a budget"):
        Trainer(net, PairDataset(shapes), loss, opt, config=TrainConfig(epochs=None), device="cpu")
    with pytest.raises(ParameterError, match="width: config 48, network 8"):  # before any training
        Trainer(net, PairDataset(shapes), loss, opt, device="cpu", checkpoint=tmp_path / "x.ckpt")


@pytest.mark.slow
def test_ddp_ranks_agree_follow_the_time_budget_and_leave_only_the_checkpoint(tmp_path, blob_files):
    """Two DDP ranks (gloo) end with identical, trained weights; the run reads its whole budget
    from the config: a time budget stops it (the epochs alone would run far longer) and the
    cosine schedule reaches its floor there. Nothing but the checkpoint is left in its folder
    (the ranks' weights went through a temporary folder). (One spawn checks all.)"""
    budget_s = 2.0
    config = TrainConfig(
        k=8, n_wks=8, k_net=8, epochs=None, minutes=budget_s / 60, width=16, c_out=16, n_blocks=1,
        clip_grad=1.0,
    )  # fmt: skip
    out = tmp_path / "run" / "ddp.ckpt"
    out.parent.mkdir()
    t0 = time.perf_counter()
    w0, w1 = spawn_ddp(config, blob_files, out, world_size=2, cache_dir=tmp_path / "cache")
    assert time.perf_counter() - t0 < 120  # spawn and imports included; the epochs are unbounded
    assert sorted(p.name for p in out.parent.iterdir()) == ["ddp.ckpt"]
    ckpt = read_checkpoint(out)
    state = ckpt["train_state"]
    # training stops at the first step boundary after the budget: within one step of it
    steps = max(state["step"], 1)
    assert budget_s <= state["seconds"] <= budget_s + 3 * state["seconds"] / steps + 1.0
    assert ckpt["config"]["minutes"] == config.minutes and ckpt["config"]["clip_grad"] == 1.0
    lr = ckpt["optimizer"]["param_groups"][0]["lr"]
    assert lr == pytest.approx(config.lr * 0.02, rel=0.05)  # the cosine's floor at the budget's end
    assert w0.keys() == w1.keys()
    for key in w0:
        assert torch.equal(w0[key], w1[key]), key
    untrained = build_model(config)[0].state_dict()
    assert any(not torch.equal(w0[k], untrained[k]) for k in w0)  # it did train


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_training_on_cuda_follows_the_cpu(tmp_path):
    """The same recipe and seed on CUDA and on the CPU: the first step's loss agrees to float32
    round-off of the solve (the data, drawn samples and initial weights are the same; the
    generators differ by device, so the coupling loss's samples are compared with none)."""
    files = _two_blobs(tmp_path / "m")
    config = TINY.with_budget(Budget(steps=3))
    config.loss_weights = {**config.loss_weights, "n_samples": 0}
    shapes = ShapeDataset(files, False, **config.dataset_kwargs(), progress=False)
    losses = {}
    for device in ("cpu", "cuda"):
        trainer = Trainer.from_config(config, shapes, device=device)
        assert next(trainer.net.parameters()).device.type == device
        losses[device] = [t["total"] for t in trainer.fit(progress=False).losses]
    np.testing.assert_allclose(losses["cuda"], losses["cpu"], rtol=1e-3)


def test_a_solver_other_than_the_recorded_recipe_is_refused(tmp_path):
    """The checkpoint records ``config.w_lap`` and inference solves with it: a trainer given a
    solver with another weight would ship a model used with another solve than it learned."""
    from torchfmap.nn import RegularizedFMSolver

    files = _two_blobs(tmp_path / "m")
    shapes = ShapeDataset(files, False, **TINY.dataset_kwargs(), progress=False)
    net, _, loss_fn = build_model(TINY)
    opt = torch.optim.Adam(net.parameters())
    data = PairDataset(shapes)
    with pytest.raises(ParameterError, match="w_lap"):
        Trainer(
            net,
            data,
            loss_fn,
            opt,
            config=TINY,
            solver=RegularizedFMSolver(w_lap=0.1),
            checkpoint=tmp_path / "c",
        )
    trainer = Trainer(net, data, loss_fn, opt, config=TINY, solver=RegularizedFMSolver(w_lap=TINY.w_lap),
                      checkpoint=tmp_path / "c")  # fmt: skip
    assert trainer.solver.w_lap == TINY.w_lap


def test_a_run_resumed_mid_epoch_ends_with_the_uninterrupted_runs_weights(tmp_path):
    """Interrupted (Ctrl-C) after step 3 of an epoch of 6 batches, with a checkpoint at every
    step, then resumed with the same recipe: the same pairs in the same order and the same
    draws, so the weights equal those of one uninterrupted run (CPU, one thread)."""
    mesh = bumpy_blob(2)
    folder = tmp_path / "m"
    folder.mkdir()
    files = [
        save_mesh(mesh.copy(bend(mesh.vertices, s)), folder / f"a{i}.off")
        for i, s in enumerate((0.1, 0.2, 0.4))
    ]
    config = TINY.with_budget(Budget(steps=8))
    shapes = ShapeDataset(files, False, **config.dataset_kwargs(), progress=False)

    def run(path, interrupt_at=None):
        def validate(net):
            if interrupt_at is not None and trainer.state.step == interrupt_at:
                raise KeyboardInterrupt
            return 0.0

        torch.manual_seed(0)
        trainer = Trainer.from_config(
            config, shapes, device="cpu", checkpoint=path, validate=validate, validate_every=1
        )  # fmt: skip
        assert trainer.batches_per_epoch > 3
        trainer.resume()
        trainer.fit(progress=False)
        return trainer

    with torch.random.fork_rng():
        straight = run(tmp_path / "s.ckpt")
        with pytest.raises(KeyboardInterrupt):
            run(tmp_path / "r.ckpt", interrupt_at=3)
        assert read_checkpoint(tmp_path / "r.ckpt")["train_state"]["batch"] == 2  # mid-epoch
        resumed = run(tmp_path / "r.ckpt")
    assert resumed.state.step == straight.state.step == 8
    for a, b in zip(resumed.net.state_dict().values(), straight.net.state_dict().values(), strict=True):
        assert torch.equal(a, b)
