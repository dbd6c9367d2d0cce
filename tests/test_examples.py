"""The numbered examples in ``examples/`` run on the shipped demo pair with their smallest
settings and do what their docstrings promise: maps and files written, errors finite and far
below a random map's, the training checkpoint whole and resumable, the layers indifferent to
a mesh's units.

The demo pair is a bumpy blob and its bent, vertex-shuffled copy (2562 vertices, edges about
0.03 sqrt(area) long): a map right up to local slips is within a few edges of the truth, while
a random map (the identity of the shuffled copy) is off by about the mean geodesic distance,
0.4. "Far below" is under a quarter of that."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from torchfmap import load_mesh, save_mesh
from torchfmap.data import demo_pair_paths
from torchfmap.evaluate.scores import evaluate_map, gt_from_map
from torchfmap.io import read_map
from torchfmap.nn import Budget, LearnedMatcher, ShapeDataset, TrainConfig, Trainer, check_network
from torchfmap.nn.checkpoints import read_checkpoint

from .conftest import bend, bumpy_blob

#: Every example runs end to end (a docs command): behind the slow marker, which CI also runs.
pytestmark = pytest.mark.slow

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
TINY = TrainConfig(k=8, n_wks=6, k_net=16, width=8, c_out=8, n_blocks=1)


def example(name: str):
    """The example module ``examples/<name>.py`` (numbered names are not importable as such)."""
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run(name: str, *argv) -> dict:
    return example(name).main([str(a) for a in argv])


@pytest.fixture(scope="module")
def random_error() -> float:
    """The mean error of a random map on the demo pair: the identity of the shuffled copy."""
    x_path, y_path, gt_path = demo_pair_paths()
    x, y = load_mesh(x_path), load_mesh(y_path)
    report, _ = evaluate_map(x, y, np.arange(y.n_vertices), gt_from_map(read_map(gt_path)), max_points=200)
    assert report.mean_error > 0.3  # the copy is shuffled: the identity is no map
    return report.mean_error


def test_the_training_examples_take_the_train_commands_flags():
    """One name per setting: every flag of the training examples that ``torchfmap train`` also
    has is spelled as there (``--max-steps``, not ``--steps``), checked on their source."""
    from torchfmap.cli import build_parser

    train = next(
        a.choices["train"]
        for a in build_parser()._actions
        if getattr(a, "choices", None) and "train" in a.choices
    )
    flags = {s for action in train._actions for s in action.option_strings}
    concepts = {"steps": "--max-steps", "minutes": "--minutes", "epochs": "--epochs", "resume": "--resume"}
    for name in ("04_train", "05_custom_loop"):
        own = set(re.findall(r'add_argument\(\s*"(--[\w-]+)"', (EXAMPLES / f"{name}.py").read_text()))
        for word, flag in concepts.items():
            spelled = {f for f in own if word in f}
            assert spelled <= {flag}, (name, spelled)
            assert flag in flags
    assert "--max-steps" in set(re.findall(r'"(--[\w-]+)"', (EXAMPLES / "04_train.py").read_text()))


def test_every_example_is_numbered_documented_and_tested():
    files = sorted(p.name for p in EXAMPLES.glob("*.py"))
    assert files and all(re.fullmatch(r"\d\d_[a-z_]+\.py", f) for f in files), files
    tested = set(re.findall(r'run\("(\d\d_[a-z_]+)"', Path(__file__).read_text()))
    assert tested == {f[:-3] for f in files}, "an example that no test runs, or a test of a missing one"
    for name in files:
        module = example(name[:-3])
        assert f"python examples/{name}" in module.__doc__, f"{name}: its docstring says how to run it"
        assert callable(module.main)


def test_01_match(tmp_path, random_error, capsys):
    out = run("01_match", "--k", 30, "--out", tmp_path / "map.txt")
    errors = out["errors"]
    assert set(errors) == {"no landmarks", "no landmarks + zoomout", "6 landmarks", "6 landmarks + zoomout"}
    assert all(np.isfinite(e) and e < random_error / 4 for e in errors.values()), errors
    # the guard's report: the held-out landmark figures of the 6-landmark refinement are printed
    printed = capsys.readouterr().out
    assert re.search(r"held-out landmark error \d\.\d{4} -> \d\.\d{4}", printed), printed
    p2p = read_map(out["out"])  # one line per vertex of y, each a vertex of x
    assert p2p.shape == (2562,) and p2p.min() >= 0 and p2p.max() < 2562


def test_02_feature_aware_bases(tmp_path, random_error, monkeypatch):
    png = tmp_path / "bases.png"
    out = run("02_feature_aware_bases", "--seeds", 8, "--k", 30, "--png", png)
    assert out["unity"] < 1e-8 and out["orthonormality"] < 1e-8  # closed forms, to round-off
    support = list(out["support"].values())  # small to large times: wider kernels
    assert support == sorted(support) and support[0] < 0.5 < support[-1]
    assert set(out["errors"]) == {"diffusion", "laplacian"}
    assert all(e < random_error / 4 for e in out["errors"].values()), out["errors"]
    mpl = importlib.util.find_spec("matplotlib") is not None
    assert (out["png"] == png and png.stat().st_size > 0) if mpl else out["png"] is None
    # without matplotlib the figure is skipped with a message, not an error
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    mesh = load_mesh(demo_pair_paths()[0])
    draw = example("02_feature_aware_bases").draw
    assert draw(mesh, {"f": mesh.vertices[:, 0]}, [0], tmp_path / "no.png") is False
    assert not (tmp_path / "no.png").exists()


def test_03_learned_match(tmp_path, random_error):
    out = run("03_learned_match", "--device", "cpu", "--out", tmp_path / "map.txt")
    raw, zoomout = out["errors"]["raw"], out["errors"]["zoomout"]
    assert zoomout < raw and zoomout < random_error / 4  # a human model on blobs: ZoomOut does the work
    assert {"prepare", "network+fmap", "p2p"} <= set(out["timings"]["raw"])
    assert "refine" in out["timings"]["zoomout"]
    assert read_map(out["out"]).shape == (2562,)


def test_04_train_on_the_demo(tmp_path, random_error):
    ckpt = tmp_path / "model.ckpt"
    out = run("04_train", "--max-steps", 3, "--device", "cpu", "--out", ckpt)  # the reference recipe
    assert out["steps"] == 3 and out["error_after"] < random_error / 4
    assert np.isfinite(out["error_before"]) and out["best_score"] < out["score_untrained"]
    matcher = LearnedMatcher.from_checkpoint(ckpt, device="cpu")  # it loads as a shipped model does
    assert matcher.config == TrainConfig().with_budget(Budget(steps=3))


def _blob_folder(folder: Path) -> list[Path]:
    mesh = bumpy_blob(2)
    folder.mkdir()
    files = [
        save_mesh(mesh, folder / "a0.off"),
        save_mesh(mesh.copy(bend(mesh.vertices, 0.3)), folder / "a1.off"),
    ]
    (folder / "test_pairs.txt").write_text("a0 a1\n")
    (folder / "corres").mkdir()
    ids = "\n".join(str(i + 1) for i in range(mesh.n_vertices))
    for name in ("a0", "a1"):
        (folder / "corres" / f"{name}.vts").write_text(ids + "\n")
    return files


def test_04_train_leaves_a_whole_resumable_checkpoint(tmp_path):
    """The training example once overwrote the checkpoint the loop had written with the last
    weights alone: the best weights, optimiser and schedule were lost and ``--resume`` failed.
    Here on a folder of the user's (ground truth from ``corres/`` and ``test_pairs.txt``)."""
    files = _blob_folder(tmp_path / "data")
    recipe = tmp_path / "recipe.json"
    TINY.to_json(recipe)
    out = tmp_path / "out" / "m.ckpt"
    run("04_train", tmp_path / "data", "--epochs", 2, "--device", "cpu", "--out", out,
        "--validate-every", 1, "--config", recipe)  # fmt: skip
    ckpt = read_checkpoint(out)
    assert {"optimizer", "scheduler", "best_state_dict", "error_before", "error_after"} <= set(ckpt)
    assert ckpt["best_state_dict"] is not None and ckpt["train_state"]["step"] == 4
    assert np.isfinite(ckpt["error_before"]) and np.isfinite(ckpt["error_after"])
    shapes = ShapeDataset(files, False, **TINY.dataset_kwargs(), progress=False)
    resumed = Trainer.from_config(TINY.with_budget(Budget(epochs=3)), shapes, device="cpu", checkpoint=out)
    assert resumed.resume() and resumed.fit(progress=False).step == 6
    # the example's own --resume: the budget is the whole run's, so one more epoch (two steps)
    again = run("04_train", tmp_path / "data", "--epochs", 3, "--resume", "--device", "cpu", "--out", out,
                "--config", recipe)  # fmt: skip
    assert again["steps"] == 6 and read_checkpoint(out)["train_state"]["step"] == 6


def test_05_custom_loop_trains_and_ignores_the_units():
    out = run("05_custom_loop", "--max-steps", 3)
    assert out["mass"] == pytest.approx(1.0, rel=1e-5)  # the layers' unit-area frame (float32 sum)
    assert all(np.isfinite(out["losses"])) and out["error_after"] < out["error_before"]
    # the demo in other units: the same arrays to float64 round-off, so the same float32 run
    scaled = run("05_custom_loop", "--max-steps", 3, "--scale", 1000)
    np.testing.assert_allclose(scaled["losses"], out["losses"], rtol=1e-3)
    assert scaled["error_after"] == pytest.approx(out["error_after"], rel=1e-2)
    check_network(example("05_custom_loop").OwnNet(16))  # a network of your own follows the protocol
