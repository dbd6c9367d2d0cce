"""Supervised training on parts (``torchfmap.nn.parts``): the ground truth carried through the cut to
every whole, the part's inputs as inference takes them, the loss in closed form, a short run lowering
it, and the errors of bad settings (the ``train --parts`` command included)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from torchfmap import save_mesh
from torchfmap.cli import main
from torchfmap.descriptors import shot
from torchfmap.errors import ParameterError
from torchfmap.matching.partial import SHOT_RADIUS
from torchfmap.mesh import Mesh
from torchfmap.nn import Trainer
from torchfmap.nn.checkpoints import read_checkpoint
from torchfmap.nn.config import TrainConfig, build_model, build_solver
from torchfmap.nn.data import ShapeDataset
from torchfmap.nn.parts import PartLoss, PartPairs, part_score
from torchfmap.nn.train import PairForward, forward_pair
from torchfmap.operators.geodesic import geodesic_distances

from ..conftest import _err, bend, bumpy_blob

TINY = TrainConfig(k=8, n_wks=6, k_net=16, width=8, c_out=8, n_blocks=1, inputs="shot", lr=3e-3)


def _folder(folder: Path) -> Path:
    """Three bent blobs; the third with its vertices shuffled, each with its 1-based ``.vts`` file."""
    mesh = bumpy_blob(3)
    (folder / "corres").mkdir(parents=True)
    order = np.random.default_rng(3).permutation(mesh.n_vertices)  # new vertex i is old order[i]
    back = np.argsort(order)
    shapes = [
        (mesh.vertices, mesh.faces, np.arange(mesh.n_vertices)),
        (bend(mesh.vertices, 0.3), mesh.faces, np.arange(mesh.n_vertices)),
        (bend(mesh.vertices, -0.3)[order], back[mesh.faces], back),
    ]
    for i, (v, f, vts) in enumerate(shapes):
        save_mesh(Mesh(v, f), folder / f"blob{i}.off")
        np.savetxt(folder / "corres" / f"blob{i}.vts", vts + 1, fmt="%d")
    return folder


@pytest.fixture(scope="module")
def parts(tmp_path_factory):
    folder = _folder(tmp_path_factory.mktemp("parts"))
    shapes = ShapeDataset(folder, False, **TINY.dataset_kwargs(), progress=False)
    return folder, shapes, PartPairs(shapes, folder / "corres", 2, truth_rows=200, progress=False)


def test_the_ground_truth_goes_through_the_cut_to_every_whole(parts):
    folder, shapes, data = parts
    vts = [np.loadtxt(folder / "corres" / f"blob{i}.vts", dtype=np.int64) - 1 for i in range(3)]
    assert len(data.parts) == 6 and len(data) == 18  # every part against every whole, its own too
    seen = set()
    for k in range(len(data)):
        whole, part, truth = data[k]
        p, j = data.pairs[k]
        i = data.whole_of[p]
        template, _ = data.truth[p]
        rows, dist = truth["rows"].numpy(), truth["dist"].numpy()
        on_whole = data.part_vertices[p][rows]  # the part's vertices on its own whole
        np.testing.assert_array_equal(on_whole, vts[i][data.template_rows[template]])
        target = vts[j][data.template_rows[template]]  # their true matches on whole j
        assert dist.shape == (len(rows), whole["values"].shape[0])
        np.testing.assert_array_equal(dist[np.arange(len(rows)), target], 0.0)
        mesh_j = shapes.mesh(j)
        exact = geodesic_distances(mesh_j, target[:3]) / np.sqrt(mesh_j.area)
        np.testing.assert_allclose(dist[:3], exact, rtol=1e-5, atol=1e-6)  # float32 rows
        seen.add((i, j))
    assert len(seen) == 9


def test_a_part_reads_shot_at_its_wholes_radius_as_inference_does(parts):
    _, shapes, data = parts
    part, i = data.parts[0], data.whole_of[0]
    mesh = Mesh(part["vertices"].numpy(), part["faces"].numpy())
    radius = SHOT_RADIUS * np.sqrt(shapes.mesh(i).area)
    assert mesh.area < 0.95 * shapes.mesh(i).area  # a real cut, whose own radius differs
    np.testing.assert_allclose(part["inputs"].numpy(), shot(mesh, radius), rtol=1e-5, atol=1e-6)


def test_the_part_loss_is_the_expected_error_of_the_soft_map():
    # one-hot features: the soft map puts e^(1/tau) on the true match and 1 on each other vertex
    V, tau = 6, 0.25
    feat_x = torch.eye(V, dtype=torch.float64)[None]
    truth_rows, matches = torch.tensor([[1, 3]]), torch.tensor([4, 0])
    feat_y = torch.zeros(1, 5, V, dtype=torch.float64)
    feat_y[0, truth_rows[0], matches] = 1.0
    dist = torch.rand(1, 2, V, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    dist[0, torch.arange(2), matches] = 0.0
    out = PairForward(feat_x, feat_y, None, None)

    class Basis:
        lengths = None

    batch = {"x": type("X", (), {"basis": Basis()})(), "truth": {"rows": truth_rows, "dist": dist}}
    terms = PartLoss(tau=tau, weight=2.0)(out, batch)
    expected = (dist.sum(-1) / (np.exp(1 / tau) + V - 1)).mean()
    torch.testing.assert_close(terms["error"], expected)
    torch.testing.assert_close(terms["total"], 2 * expected)


def test_training_on_parts_lowers_the_error_of_the_part_maps(parts):
    _, shapes, data = parts
    config = TinyParts = TINY.updated({"parts": 2, "epochs": 4})
    assert TinyParts.parts == 2
    solver = build_solver(config)[0]
    score = part_score(data, range(len(data)), PartLoss(), solver)
    trainer = Trainer.from_config(config, shapes, data, device="cpu", validate=score)
    assert trainer.loss_fn is None and isinstance(trainer.extra_losses[0], PartLoss)
    state = trainer.fit(progress=False)
    first, last = state.scores[0][1], state.scores[-1][1]
    assert state.step == 4 * len(data) and last < first
    assert all(np.isfinite(t["part_error"]) for t in state.losses)


def test_bad_part_settings_are_refused(parts, tmp_path):
    folder, shapes, data = parts
    with pytest.raises(ParameterError, match="n_cuts"):
        PartPairs(shapes, folder / "corres", 0)
    with pytest.raises(ParameterError, match="ratios"):
        PartPairs(shapes, folder / "corres", 1, ratios=(0.5, 1.2))
    with pytest.raises(ParameterError, match=r"no ground truth .*blob0\.vts"):
        PartPairs(shapes, tmp_path, 1)
    with pytest.raises(ParameterError, match="parts must be >= 0"):
        TrainConfig().updated({"parts": -1})
    with pytest.raises(ParameterError, match="tau"):
        PartLoss(tau=0.0)
    with pytest.raises(ParameterError, match="truth"):
        PartLoss()(PairForward(torch.zeros(1, 2, 3), torch.zeros(1, 2, 3), None, None), {})
    net = build_model(TINY)[0]
    with pytest.raises(ParameterError, match="nothing to train"):
        Trainer(net, data, None, torch.optim.Adam(net.parameters()), config=TINY)


def test_train_parts_command_records_the_recipe_and_names_missing_ground_truth(parts, tmp_path, capsys):
    folder, _, _ = parts
    ckpt = tmp_path / "parts.ckpt"
    args = ["train", str(folder), "--out", str(ckpt), "--k", "8", "--k-net", "16", "--n-wks", "6"]
    args += ["--width", "8", "--c-out", "8", "--inputs", "shot", "--no-cache", "--validate-every", "2"]
    assert main([*args, "--parts", "1", "--max-steps", "3"]) == 0
    out = capsys.readouterr().out
    assert "9 (part, whole) pairs" in out and "part error" in out
    saved = read_checkpoint(ckpt)
    assert saved["config"]["parts"] == 1 and saved["train_state"]["step"] == 3
    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("blob0.off", "blob1.off"):
        (bare / name).write_bytes((folder / name).read_bytes())
    assert main(["train", str(bare), "--out", str(tmp_path / "b.ckpt"), "--parts", "1", "--no-cache",
                 "--k", "8", "--k-net", "16", "--max-steps", "1", "--quiet"]) == 2  # fmt: skip
    assert "corres/" in _err(capsys) and not (tmp_path / "b.ckpt").exists()


def test_padded_truth_rows_add_nothing_to_a_batch(parts):
    _, _, data = parts
    net, solver = build_model(TINY)[0].eval(), build_solver(TINY)[0]
    rows = [len(data.truth[p][0]) for p, _ in data.pairs]  # truth rows of each pair's part
    a, b = 0, next(k for k in range(len(data)) if rows[k] != rows[0] and data.pairs[k][1] != data.pairs[0][1])
    loss = PartLoss()
    sizes, sums = [], []
    with torch.no_grad():
        for k in (a, b):
            batch = data.collate([data[k]])
            sizes.append(batch["truth"]["rows"].shape[1])
            sums.append(float(loss(forward_pair(net, solver, batch), batch)["error"]) * sizes[-1])
        both = data.collate([data[a], data[b]])
        error = float(loss(forward_pair(net, solver, both), both)["error"])
    assert sizes[0] != sizes[1] and both["truth"]["dist"].shape[1] == max(sizes)
    # the batch mean counts the padded rows as zeros: (sum a + sum b) / (2 P_max)
    np.testing.assert_allclose(error, sum(sums) / (2 * max(sizes)), rtol=1e-5)


def test_train_threads_bound_the_run_and_are_given_back(parts, tmp_path, monkeypatch):
    import torchfmap.cli.train as cli_train

    folder, _, _ = parts
    seen, before = [], torch.get_num_threads()
    real = cli_train._train

    def spy(args):
        seen.append(torch.get_num_threads())
        return real(args)

    monkeypatch.setattr(cli_train, "_train", spy)
    args = ["train", str(folder), "--out", str(tmp_path / "t.ckpt"), "--k", "8", "--k-net", "16"]
    assert main([*args, "--no-cache", "--max-steps", "1", "--threads", "1", "--quiet"]) == 0
    assert seen == [1] and torch.get_num_threads() == before
