"""The learned path's commands (``torchfmap.cli.train``): ``train`` (budgets, resume, init,
recipe files, devices, Ctrl-C, folders without pairs) and ``models``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from torchfmap import save_mesh
from torchfmap.cli import main
from torchfmap.errors import ParameterError
from torchfmap.nn.checkpoints import read_checkpoint

from ..conftest import _err, _identity_folder, bend, bumpy_blob


def test_train_command_writes_and_resumes_a_checkpoint(tiny_folder, tmp_path, capsys):
    ckpt = tmp_path / "model.ckpt"
    args = ["train", str(tiny_folder), "--out", str(ckpt), "--k", "8", "--no-cache"]
    assert main([*args, "--max-steps", "3"]) == 0  # without --quiet: the status lines
    first = read_checkpoint(ckpt)
    assert first["train_state"]["step"] == 3 and "6 ordered pairs" in capsys.readouterr().out
    assert main([*args, "--max-steps", "5", "--resume", "--quiet"]) == 0
    assert capsys.readouterr().out == ""
    second = read_checkpoint(ckpt)
    losses = [t["total"] for t in second["train_state"]["losses"]]
    assert second["train_state"]["step"] == 5 and len(losses) == 5 and np.isfinite(losses).all()
    assert losses[:3] == [t["total"] for t in first["train_state"]["losses"]]


def test_resume_refuses_another_recipe_and_save_refuses_a_wrong_config(tiny_folder, tmp_path, capsys):
    from torchfmap.nn import TrainConfig, build_model, save_checkpoint

    ckpt = tmp_path / "model.ckpt"
    args = ["train", str(tiny_folder), "--out", str(ckpt), "--k", "8", "--no-cache", "--quiet"]
    assert main([*args, "--max-steps", "1"]) == 0
    capsys.readouterr()
    bad = ["train", str(tiny_folder), "--out", str(ckpt), "--k", "10", "--no-cache", "--quiet", "--resume"]
    assert main([*bad, "--max-steps", "2"]) == 2
    assert "--k 10 (checkpoint: 8)" in capsys.readouterr().err
    assert main([*args, "--resume", "--max-steps", "2"]) == 0  # the same recipe continues
    net = build_model(TrainConfig(width=48))[0]
    with pytest.raises(ParameterError, match="width: config 32, network 48"):
        save_checkpoint(tmp_path / "x.ckpt", net, TrainConfig(width=32))
    assert not (tmp_path / "x.ckpt").exists()


def test_train_command_progress_counts_to_the_step_budget(tmp_path, capsys):
    from torchfmap import save_mesh
    from torchfmap.cli import main
    from torchfmap.nn.checkpoints import read_checkpoint

    from ..conftest import bend, bumpy_blob

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


def test_train_refuses_a_folder_without_pairs_a_file_and_a_missing_folder(tmp_path, capsys):
    one = tmp_path / "one"
    one.mkdir()
    save_mesh(bumpy_blob(2), one / "a.off")
    base = ["--out", str(tmp_path / "m.ckpt"), "--no-cache", "--quiet", "--max-steps", "1", "--k", "8"]
    assert main(["train", str(one), *base]) == 2
    assert "no pair of shapes to train on (1 mesh: a)" in _err(capsys)
    for target in (one / "a.off", tmp_path / "missing"):
        assert main(["train", str(target), *base]) == 2
        assert "is not a folder" in _err(capsys)


def test_ctrl_c_during_train_says_where_the_checkpoint_stands_and_exits_130(tmp_path, monkeypatch, capsys):
    from torchfmap.nn import Budget, Trainer

    folder = tmp_path / "two"
    folder.mkdir()
    x = bumpy_blob(2)
    for i, s in enumerate((0.1, 0.3)):
        save_mesh(x.copy(bend(x.vertices, s)), folder / f"b{i}.off")
    real = Trainer.fit

    def one_step_then_interrupt(self, progress=True):
        self.budget = Budget(steps=1)
        real(self, progress)  # writes the checkpoint at step 1
        raise KeyboardInterrupt

    monkeypatch.setattr(Trainer, "fit", one_step_then_interrupt)
    ckpt = tmp_path / "m.ckpt"
    args = ["train", str(folder), "--out", str(ckpt), "--no-cache", "--quiet", "--max-steps", "5", "--k", "8"]
    assert main(args) == 130
    err = _err(capsys)
    assert "interrupted" in err and "holds step 1" in err and "--resume" in err


def test_resume_with_a_spent_budget_is_refused(tmp_path, capsys):
    folder = _identity_folder(tmp_path)
    ckpt = tmp_path / "m.ckpt"
    args = ["train", str(folder), "--out", str(ckpt), "--no-cache", "--quiet", "--k", "8"]
    assert main([*args, "--max-steps", "2"]) == 0
    capsys.readouterr()
    assert main([*args, "--max-steps", "2", "--resume"]) == 2
    err = _err(capsys)
    assert "already spent its budget --max-steps 2 (done: 2 steps)" in err and "larger budget" in err


def test_init_and_resume_take_a_budget_given_now_whole(tmp_path, capsys):
    """One budget rule: a budget on the command line replaces the whole budget, with --init as
    with --resume (--init once kept the checkpoint's other limits, e.g. its minutes); without
    one --init starts the recipe's default budget and --resume keeps the run's."""
    folder = _identity_folder(tmp_path)
    base = ["train", str(folder), "--no-cache", "--quiet", "--validate-every", "0"]
    first = tmp_path / "first.ckpt"
    recipe = ["--k", "8", "--width", "8"]
    assert main([*base, "--out", str(first), *recipe, "--minutes", "80", "--max-steps", "1"]) == 0
    tuned = tmp_path / "tuned.ckpt"
    assert main([*base, "--out", str(tuned), "--init", str(first), "--epochs", "1"]) == 0
    config = read_checkpoint(tuned)["config"]
    assert (config["epochs"], config["minutes"], config["max_steps"]) == (1, 0.0, 0)
    assert config["width"] == 8 and config["k"] == 8  # --init keeps the recipe
    again = tmp_path / "again.ckpt"
    assert main([*base, "--out", str(again), "--init", str(first), "--max-steps", "1", "--k", "8"]) == 0
    assert read_checkpoint(again)["config"]["epochs"] is None
    assert main([*base, "--out", str(first), "--resume", "--max-steps", "2"]) == 0
    config = read_checkpoint(first)["config"]
    assert (config["epochs"], config["minutes"], config["max_steps"]) == (None, 0.0, 2)
    assert main([*base, "--out", str(tuned), "--init", str(first), "--resume"]) == 2
    assert "--init starts a new run" in capsys.readouterr().err


def test_a_recipe_file_trains_with_flags_overriding_it_and_a_checkpoint_gives_it_back(tmp_path, capsys):
    from torchfmap.nn import TrainConfig

    folder = _identity_folder(tmp_path)
    recipe = tmp_path / "recipe.json"
    TrainConfig(k=8, width=8, c_out=8, n_blocks=1, epochs=None, max_steps=3, lr=2e-3).to_json(recipe)
    ckpt = tmp_path / "m.ckpt"
    base = ["train", str(folder), "--no-cache", "--quiet", "--validate-every", "0", "--out", str(ckpt)]
    assert main([*base, "--config", str(recipe), "--max-steps", "2", "--width", "16"]) == 0
    saved = read_checkpoint(ckpt)
    assert saved["train_state"]["step"] == 2 and saved["config"]["lr"] == 2e-3
    assert saved["config"]["width"] == 16 and saved["config"]["n_blocks"] == 1
    capsys.readouterr()
    assert main(["models", "--recipe", str(ckpt)]) == 0
    back = tmp_path / "back.json"
    back.write_text(capsys.readouterr().out)
    assert TrainConfig.from_json(back) == TrainConfig(**saved["config"])
    again = tmp_path / "again.ckpt"
    assert main([*base[:-1], str(again), "--config", str(back)]) == 0  # reproduces the recipe
    assert read_checkpoint(again)["config"] == saved["config"]
    recipe.write_text('{"k": 8, "stages": 2}')
    assert main([*base, "--config", str(recipe)]) == 2
    err = _err(capsys)
    assert "the recipe file" in err and "keys 'stages'" in err and "Fix: use its fields only" in err


def test_device_cuda_without_cuda_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    folder = _identity_folder(tmp_path)
    args = ["train", str(folder), "--out", str(tmp_path / "m.ckpt"), "--no-cache", "--max-steps", "1"]
    assert main([*args, "--device", "cuda"]) == 2
    err = _err(capsys)
    assert "no CUDA device" in err and "Fix: --device cpu" in err and not (tmp_path / "m.ckpt").exists()
    assert main([*args, "--device", "auto", "--k", "8", "--validate-every", "0"]) == 0
    assert "on cpu; budget: 1 steps" in capsys.readouterr().out


def test_models_command_lists_the_shipped_models(capsys):
    assert main(["models"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("faust_r") and "command: torchfmap train" in out and "validation:" in out
    assert "torchfmap models --recipe faust_r" in out


def test_the_validation_loss_is_explained_against_the_untrained_network_and_an_unmoved_one_warned(
    tiny_folder, tmp_path, capsys
):
    """The summary says what the score is and the untrained reference (validated at step 0);
    with a learning rate of 1e-12 nothing moves, and a warning says so with the fix."""
    ckpt = tmp_path / "model.ckpt"
    args = ["train", str(tiny_folder), "--out", str(ckpt), "--k", "8", "--no-cache", "--max-steps", "2"]
    assert main([*args, "--validate-every", "1", "--validate-pairs", "2"]) == 0
    out = capsys.readouterr().out
    assert "best validation loss" in out and "the unsupervised loss on 2 fixed training pairs" in out
    assert "untrained" in out and "% lower)" in out
    scores = read_checkpoint(ckpt)["train_state"]["scores"]
    assert [step for step, _ in scores] == [0, 1, 2]  # the untrained network's score first
    assert main([*args, "--validate-every", "1", "--lr", "1e-12", "--out", str(tmp_path / "still.ckpt")]) == 0
    err = capsys.readouterr().err
    assert "lowered the validation loss only from" in err and "Fix: train longer" in err
    # a fine-tune starts from trained weights: its step-0 score is theirs, and a small gain no warning
    tuned = tmp_path / "tuned.ckpt"
    fine = [*args, "--validate-every", "1", "--lr", "1e-12", "--init", str(ckpt), "--out", str(tuned)]
    assert main(fine) == 0
    captured = capsys.readouterr()
    assert "the --init weights" in captured.out and "untrained" not in captured.out
    assert "lowered the validation loss only" not in captured.err


def test_a_checkpoint_exists_before_the_first_step(tmp_path, monkeypatch):
    """Interrupted before its first step, training has still left a whole, resumable checkpoint."""
    from torchfmap.nn import Trainer

    folder = tmp_path / "two"
    folder.mkdir()
    x = bumpy_blob(2)
    for i, s in enumerate((0.1, 0.3)):
        save_mesh(x.copy(bend(x.vertices, s)), folder / f"b{i}.off")

    def interrupt(self, batch):
        raise KeyboardInterrupt

    monkeypatch.setattr(Trainer, "step", interrupt)
    ckpt = tmp_path / "m.ckpt"
    args = ["train", str(folder), "--out", str(ckpt), "--no-cache", "--quiet", "--max-steps", "5", "--k", "8"]
    assert main(args) == 130
    assert read_checkpoint(ckpt)["train_state"]["step"] == 0
    monkeypatch.undo()
    assert main([*args, "--resume"]) == 0 and read_checkpoint(ckpt)["train_state"]["step"] == 5


def _two_blobs(folder):
    folder.mkdir()
    x = bumpy_blob(2)
    for i, s in enumerate((0.1, 0.3)):
        save_mesh(x.copy(bend(x.vertices, s)), folder / f"b{i}.off")
    return folder


@pytest.mark.slow
@pytest.mark.parametrize("when", ["first checkpoint", "mid-run"])
def test_sigkill_at_any_point_leaves_a_checkpoint_that_resumes(tmp_path, when):
    """A run killed (SIGKILL: no handler runs) as soon as its checkpoint exists, or after some
    steps: the file is whole, its lock is taken over, and --resume finishes the budget."""
    import signal
    import subprocess
    import sys
    import time

    from torchfmap.errors import TorchFmapError

    folder = _two_blobs(tmp_path / "two")
    ckpt = tmp_path / "m.ckpt"
    args = ["train", str(folder), "--out", str(ckpt), "--no-cache", "--quiet", "--k", "8"]
    args += ["--max-steps", "40"]
    proc = subprocess.Popen([sys.executable, "-m", "torchfmap", *args], stderr=subprocess.PIPE)

    def step() -> int:
        try:
            return read_checkpoint(ckpt)["train_state"]["step"]
        except (TorchFmapError, OSError):  # not there yet
            return -1

    deadline = time.monotonic() + 120
    least = 0 if when == "first checkpoint" else 2  # a checkpoint is saved every epoch (2 pairs)
    while step() < least and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    killed_at = step()  # whole: its checksum holds
    assert 0 <= killed_at < 40, proc.stderr.read().decode()[-500:]
    assert main([*args, "--resume"]) == 0
    assert read_checkpoint(ckpt)["train_state"]["step"] == 40 and not Path(f"{ckpt}.lock").exists()


def test_a_second_training_on_the_same_out_is_refused(tmp_path, capsys):
    """Two runs writing one checkpoint would take turns overwriting it: the second is refused
    while the first (a live process) holds the lock; a lock of a dead process is taken over."""
    import subprocess
    import sys

    folder = _two_blobs(tmp_path / "two")
    ckpt = tmp_path / "m.ckpt"
    lock = Path(f"{ckpt}.lock")
    args = ["train", str(folder), "--out", str(ckpt), "--no-cache", "--quiet", "--max-steps", "2", "--k", "8"]
    with subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"]) as other:
        lock.write_text(str(other.pid))
        assert main(args) == 2
        assert f"being written by another process (pid {other.pid}" in _err(capsys) and not ckpt.exists()
        other.kill()
    assert main(args) == 0 and ckpt.exists() and not lock.exists()
