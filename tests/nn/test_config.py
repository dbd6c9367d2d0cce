"""The reference recipe (``torchfmap.nn.config``): ``build_model`` / ``build_solver``, and the
cosine learning-rate schedule over a step or time budget."""

from __future__ import annotations

import math

import pytest
import torch

from torchfmap import ParameterError
from torchfmap.nn import (
    LearnedMatcher,
    TrainConfig,
    TrainState,
    build_model,
    build_solver,
    load_checkpoint,
    shipped_models,
    train,
    train_recipe,
)
from torchfmap.nn import config as config_module
from torchfmap.nn.config import CosineBudget


def test_recipe_pieces_without_a_network():
    config = TrainConfig(w_lap=0.25)
    solver, loss = build_solver(config)
    assert solver.w_lap == 0.25 and loss.n_samples == config.loss_weights["n_samples"]
    net, solver2, _ = build_model(config)
    assert solver2.w_lap == solver.w_lap and sum(p.numel() for p in net.parameters()) > 0
    state = TrainState()
    assert state.step == 0 and state.losses == [] and state.best_score == float("inf")
    assert "faust_r" in shipped_models()
    net, config, ckpt = load_checkpoint("faust_r")
    assert "provenance" in ckpt and callable(train) and callable(train_recipe)
    assert LearnedMatcher.from_checkpoint("faust_r", device="cpu").checkpoint == "faust_r"


def cosine(frac: float, floor: float = 0.02) -> float:
    return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * frac))


def test_step_budget_drives_the_cosine_to_its_floor_at_the_last_step():
    f = CosineBudget(steps=10)
    assert f(0) == pytest.approx(1.0)
    assert f(5) == pytest.approx(cosine(0.5))
    assert f(10) == pytest.approx(0.02) and f(25) == pytest.approx(0.02)


def test_time_budget_and_both_budgets_follow_the_one_further_spent(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr(config_module.time, "perf_counter", lambda: clock[0])
    f = CosineBudget(minutes=1.0)  # 60 s
    assert f(0) == pytest.approx(1.0)
    clock[0] += 15.0
    assert f(1) == pytest.approx(cosine(0.25))
    both = CosineBudget(minutes=1.0, steps=100)
    both(0)
    clock[0] += 6.0  # 10 % of the time, 50 % of the steps: the steps decide
    assert both(50) == pytest.approx(cosine(0.5))
    clock[0] += 48.0  # 90 % of the time, 51 % of the steps: the time decides
    assert both(51) == pytest.approx(cosine(0.9))


def test_a_set_clock_replaces_the_processs_own_time(monkeypatch):
    """DDP ranks set one agreed clock before each step: the factor then depends on it alone, not
    on the microseconds each rank's own clock differs by."""
    clock = [100.0]
    monkeypatch.setattr(config_module.time, "perf_counter", lambda: clock[0])
    a, b = CosineBudget(minutes=1.0), CosineBudget(minutes=1.0)
    a(0), b(0)
    clock[0] += 30.0
    a.set_clock(15.0)
    assert a(1) == cosine(0.25) and b(1) == pytest.approx(cosine(0.5))
    clock[0] += 1e-6  # a rank's own drift after the agreed clock
    b.set_clock(15.0)
    assert b(1) == a.floor + (1 - a.floor) * 0.5 * (1 + math.cos(math.pi * 0.25)) == cosine(0.25)


def test_resumed_schedule_keeps_its_clock_and_takes_the_new_budget(tmp_path):
    net = torch.nn.Linear(2, 2)
    opt = torch.optim.SGD(net.parameters(), lr=1.0)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, CosineBudget(minutes=10.0, steps=4))
    for _ in range(2):
        opt.step()
        sched.step()
    saved = sched.state_dict()
    fresh = CosineBudget(steps=8)
    other = torch.optim.lr_scheduler.LambdaLR(torch.optim.SGD(net.parameters(), lr=1.0), fresh)
    budget = fresh.budget
    other.load_state_dict(saved)
    assert fresh.budget != budget  # LambdaLR restored the saved budget ...
    fresh.budget = budget  # ... which train() puts back, as here
    assert other.last_epoch == 2 and fresh(2) == pytest.approx(cosine(2 / 8))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(), "needs a budget"),
        (dict(minutes=float("nan")), "finite"),
        (dict(minutes=-1.0), "finite and >= 0"),
        (dict(steps=-3), ">= 0"),
        (dict(steps=3, floor=2.0), "floor"),
    ],
)
def test_invalid_budgets_are_refused(kwargs, message):
    with pytest.raises(ParameterError, match=message):
        CosineBudget(**kwargs)
