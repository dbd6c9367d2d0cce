"""The learning-rate schedule and the progress bar follow the training budget, whichever kind."""

from __future__ import annotations

import math

import pytest
import torch

from torchfmap import ParameterError
from torchfmap.nn import config as config_module
from torchfmap.nn.config import CosineBudget
from torchfmap.nn.train import total_steps


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


def test_step_bound_of_each_budget_kind():
    assert total_steps(100, 5) == 500
    assert total_steps(100, 5, max_steps=120) == 120
    assert total_steps(100, None, max_steps=120) == 120
    assert total_steps(100, None) is None  # time budget only


def test_train_command_progress_counts_to_the_step_budget(tmp_path, capsys):
    from torchfmap import save_mesh
    from torchfmap.cli import main
    from torchfmap.nn.checkpoints import read_checkpoint

    from .conftest import bend, bumpy_blob

    base = bumpy_blob(2)
    for i, s in enumerate((0.1, 0.3)):
        save_mesh(base.copy(bend(base.vertices, s)), tmp_path / f"blob{i}.off")
    ckpt = tmp_path / "m.ckpt"
    args = ["train", str(tmp_path), "--out", str(ckpt), "--k", "8", "--no-cache", "--validate-every", "0"]
    assert main([*args, "--epochs", "2"]) == 0
    captured = capsys.readouterr()
    assert "budget: 2 epochs, 4 steps" in captured.out
    assert "4/4" in captured.err  # the bar's total is the real budget: 2 epochs x 2 ordered pairs
    assert "4 steps, 2 full epochs" in captured.out
    state = read_checkpoint(ckpt)
    lrs = state["scheduler"]["_last_lr"]
    assert lrs[0] == pytest.approx(1e-3 * 0.02)  # the cosine reached its floor at the last step
