"""The reference recipe (``torchfmap.nn.config``): ``build_model`` / ``build_solver``, the one
``Budget``, recipe files (JSON round trip, unknown keys refused), and the cosine learning-rate
schedule over a step or time budget."""

from __future__ import annotations

import math

import pytest
import torch

from torchfmap import ParameterError
from torchfmap.nn import (
    Budget,
    LearnedMatcher,
    TrainConfig,
    build_model,
    build_solver,
    load_checkpoint,
    shipped_models,
)
from torchfmap.nn import config as config_module
from torchfmap.nn.config import CosineBudget


def test_recipe_pieces_without_a_network():
    config = TrainConfig(w_lap=0.25)
    solver, loss = build_solver(config)
    assert solver.w_lap == 0.25 and loss.n_samples == config.loss_weights["n_samples"]
    net, solver2, _ = build_model(config)
    assert solver2.w_lap == solver.w_lap and sum(p.numel() for p in net.parameters()) > 0
    assert set(shipped_models()) >= {"faust_r", "humans", "smal_r"}
    for name in shipped_models():
        net, config, ckpt = load_checkpoint(name)
        assert "provenance" in ckpt and not hasattr(config, "stages")


def test_the_budget_is_one_object_with_one_rule():
    budget = Budget(epochs=2, minutes=1.5, steps=3)
    assert budget.step_bound(2) == 3 and Budget(epochs=2).step_bound(5) == 10
    assert Budget(minutes=1.0).step_bound(5) is None  # time alone
    assert Budget(epochs=2, steps=3).describe(2) == "2 epochs, 3 steps"
    assert budget.describe(2) == "2 epochs, 3 steps, 1.5 minutes"
    assert budget.spent(step=3) == ["--max-steps 3 (done: 3 steps)"] and budget.spent(2, 10.0, 1) == []
    assert Budget(epochs=2).spent(epoch=2) == ["--epochs 2 (done: 2)"]
    config = TrainConfig(minutes=10.0)  # the dataclass: the default epochs stay
    assert config.budget == Budget(epochs=5, minutes=10.0)
    assert TrainConfig.from_dict({"minutes": 10.0}).budget == Budget(minutes=10.0)  # replaces it whole
    assert config.with_budget(Budget(steps=4)).budget == Budget(steps=4)
    assert config.updated({"k": 20}).budget == config.budget
    with pytest.raises(ParameterError, match="needs a budget"):
        TrainConfig(epochs=None).budget  # noqa: B018
    with pytest.raises(ParameterError, match="epochs must be an integer"):
        Budget(epochs=0)


def test_a_recipe_file_round_trips_and_refuses_unknown_keys_and_wrong_types(tmp_path):
    config = TrainConfig(k=20, basis="eigen_diffusion", epochs=None, minutes=2.5, clip_grad=1.0)
    path = tmp_path / "recipe.json"
    text = config.to_json(path)
    assert path.read_text() == text and TrainConfig.from_json(path) == config
    assert TrainConfig.read_json(path)["k"] == 20
    path.write_text('{"k": 20, "widht": 8}')
    with pytest.raises(ParameterError, match="'widht' \\(did you mean 'width'\\?\\).*Fix"):
        TrainConfig.from_json(path)
    path.write_text('{"k": "20"}')
    with pytest.raises(ParameterError, match="k must be int"):
        TrainConfig.from_json(path)
    path.write_text('{"lr": 1}')  # an int for a float is fine
    assert TrainConfig.from_json(path).lr == 1
    path.write_text("k = 20")
    with pytest.raises(ParameterError, match="is not JSON"):
        TrainConfig.from_json(path)
    with pytest.raises(ParameterError, match="cannot read"):
        TrainConfig.from_json(tmp_path / "missing.json")
    assert LearnedMatcher.from_checkpoint("faust_r", device="cpu").checkpoint == "faust_r"


def cosine(frac: float, floor: float = 0.02) -> float:
    return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * frac))


def test_step_budget_drives_the_cosine_to_its_floor_at_the_last_step():
    assert CosineBudget(Budget(epochs=5), batches_per_epoch=2).steps == 10
    f = CosineBudget(Budget(steps=10))
    assert f(0) == pytest.approx(1.0)
    assert f(5) == pytest.approx(cosine(0.5))
    assert f(10) == pytest.approx(0.02) and f(25) == pytest.approx(0.02)


def test_time_budget_and_both_budgets_follow_the_one_further_spent(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr(config_module.time, "perf_counter", lambda: clock[0])
    f = CosineBudget(Budget(minutes=1.0))  # 60 s
    assert f(0) == pytest.approx(1.0)
    clock[0] += 15.0
    assert f(1) == pytest.approx(cosine(0.25))
    both = CosineBudget(Budget(minutes=1.0, steps=100))
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
    a, b = CosineBudget(Budget(minutes=1.0)), CosineBudget(Budget(minutes=1.0))
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
    sched = torch.optim.lr_scheduler.LambdaLR(opt, CosineBudget(Budget(minutes=10.0, steps=4)))
    for _ in range(2):
        opt.step()
        sched.step()
    saved = sched.state_dict()
    fresh = CosineBudget(Budget(steps=8))
    other = torch.optim.lr_scheduler.LambdaLR(torch.optim.SGD(net.parameters(), lr=1.0), fresh)
    bounds = fresh.bounds
    other.load_state_dict(saved)
    assert fresh.bounds != bounds  # LambdaLR restored the saved bounds ...
    fresh.bounds = bounds  # ... which Trainer.resume puts back, as here
    assert other.last_epoch == 2 and fresh(2) == pytest.approx(cosine(2 / 8))


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: Budget(), "needs a budget"),
        (lambda: Budget(minutes=float("nan")), "finite"),
        (lambda: Budget(minutes=-1.0), "finite and >= 0"),
        (lambda: Budget(steps=-3), ">= 0"),
        (lambda: CosineBudget(Budget(steps=3), floor=2.0), "floor"),
        (lambda: CosineBudget(Budget(epochs=3)), "batches of an epoch"),
        (lambda: CosineBudget(3), "follows a Budget"),
    ],
)
def test_invalid_budgets_are_refused(make, message):
    with pytest.raises(ParameterError, match=message):
        make()
