"""The self-seeded second stage (``torchfmap.nn.stages``, ``seeds.consistent_seeds``): seeds only
where the map agrees both ways, bases that are B-orthonormal and start with the stage-1
eigenbasis, an exact map of a vertex-permuted copy through both stages, gradients through
stage 2 in training, and the checkpoint / CLI paths that run it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfmap import Mesh, prepare_shape, save_mesh
from torchfmap.cli import main
from torchfmap.errors import ParameterError
from torchfmap.nn.data import ShapeDataset, collate_pairs
from torchfmap.nn.modules import RegularizedFMSolver, UnsupervisedFMLoss
from torchfmap.nn.stages import StageTwo, stage_two_loss, two_stage_p2p
from torchfmap.nn.train import forward_pair, pair_loss
from torchfmap.seeds import consistent_seeds, farthest_point_sampling

from .conftest import bend, bumpy_blob


class InputsAsFeatures(torch.nn.Module):
    """A 'network' whose features are its inputs (WKS): exact on a vertex-permuted copy."""

    def __init__(self) -> None:
        super().__init__()
        self.scale = torch.nn.Parameter(torch.ones(()))

    def forward(self, inputs, basis, grad):
        return inputs * self.scale


@pytest.fixture(scope="module")
def permuted(tmp_path_factory):
    """A blob and a vertex-permuted copy on disk (``y`` vertex ``i`` is ``x`` vertex ``perm[i]``)."""
    folder = tmp_path_factory.mktemp("perm")
    x = bumpy_blob(2)
    perm = np.random.default_rng(0).permutation(x.n_vertices)
    y = Mesh(x.vertices[perm], np.argsort(perm)[x.faces])
    save_mesh(x, folder / "a0.off"), save_mesh(y, folder / "a1.off")
    return folder, x, y, perm


def test_consistent_seeds_keep_round_trips_and_drop_the_rest():
    x = bumpy_blob(2)
    shape = prepare_shape(x, 0)
    s = farthest_point_sampling(x, 12)
    ident = consistent_seeds(shape.distances, s, s, s)  # a map and its inverse that agree
    np.testing.assert_array_equal(ident, np.stack([s, s], axis=1))
    back = s.copy()
    back[3] = s[7]  # the round trip of seed 3 lands on another seed: far from it
    images = s.copy()
    images[5] = s[4]  # two seeds sent to one vertex: the second is dropped
    kept = consistent_seeds(shape.distances, s, images, back)
    assert 3 not in [list(s).index(v) for v in kept[:, 0]] and len(kept) == 10
    assert len(np.unique(kept[:, 1])) == len(kept)
    with pytest.raises(ParameterError, match="one length"):
        consistent_seeds(shape.distances, s, s[:3], s)


def test_stage_two_bases_are_orthonormal_and_start_with_the_eigenbasis():
    x = bumpy_blob(2)
    y = x.copy(bend(x.vertices, 0.3))
    sx, sy = prepare_shape(x, 20), prepare_shape(y, 20)
    seeds = np.stack([farthest_point_sampling(x, 10)] * 2, axis=1)
    bx, by = StageTwo.bases(sx, sy, seeds, sx.eigenbasis.values, sy.eigenbasis.values)
    assert bx.k == by.k == 30
    for b in (bx, by):
        gram = b.values.T @ (b.mass @ b.values)
        assert np.abs(gram - np.eye(b.k)).max() < 1e-8  # B-orthonormal (MGS twice, float64)
    # the eigen block comes first, unchanged up to orthonormalisation round-off
    np.testing.assert_allclose(np.abs(bx.values[:, :20]), np.abs(sx.eigenbasis.values), atol=1e-8)
    assert [c.seed for c in bx.columns if c.kept] == [c.seed for c in by.columns if c.kept]


def test_both_stages_map_a_permuted_copy_exactly(permuted):
    """Identical features on a permuted copy: stage 1 is the permutation, every seed is
    consistent, and stage 2, built at those seeds on both meshes, gives the permutation too."""
    folder, x, y, perm = permuted
    shapes = ShapeDataset([folder / "a0.off", folder / "a1.off"], False, k=16, n_wks=24, progress=False)
    sx, sy = (prepare_shape(shapes.mesh(i), 20) for i in (0, 1))
    stage = StageTwo(n_seeds=12)
    solver = RegularizedFMSolver(w_lap=1e-3)
    first, second, used = two_stage_p2p(InputsAsFeatures(), solver, shapes[0], shapes[1], sx, sy, stage)
    assert (first == perm).mean() > 0.99
    assert used == 12 and (second == perm).mean() > 0.99
    lm = np.array([[5, np.argsort(perm)[5]]])  # a user landmark is placed first
    seeds = stage.seeds(
        sx,
        np.eye(16),
        np.eye(16),
        shapes[0]["values"].double().numpy(),
        shapes[1]["values"].double().numpy(),
        lm,
    )
    np.testing.assert_array_equal(seeds[0], lm[0])


def test_training_differentiates_through_stage_two(permuted):
    folder, *_ = permuted
    shapes = ShapeDataset([folder / "a0.off", folder / "a1.off"], False, k=16, n_wks=24, progress=False)
    net, solver, loss_fn = (
        InputsAsFeatures(),
        RegularizedFMSolver(w_lap=1e-3),
        UnsupervisedFMLoss(n_samples=0),
    )
    batch = collate_pairs([(shapes[0], shapes[1])])
    stage = StageTwo(n_seeds=10)
    terms = pair_loss(net, solver, loss_fn, batch, stage=stage, mesh_of=shapes.mesh)
    assert {"stage2_total", "stage2_bij"} <= set(terms)
    out = forward_pair(net, solver, batch)
    first = loss_fn(out.C_xy, out.C_yx, out.feat_x, out.feat_y, batch["x"].basis, batch["y"].basis)
    torch.testing.assert_close(terms["total"], first["total"] + terms["stage2_total"])
    net.zero_grad()
    terms["stage2_total"].backward()
    assert net.scale.grad is not None and torch.isfinite(net.scale.grad)
    assert len(stage.shapes) == 2  # each shape prepared once, kept by the stage object
    two = collate_pairs([(shapes[0], shapes[1])] * 2)
    with pytest.raises(ParameterError, match="batches of one pair"):
        stage_two_loss(stage, solver, loss_fn, forward_pair(net, solver, two), two, shapes.mesh)


def test_cli_trains_and_runs_two_stages_and_takes_landmarks_with_a_checkpoint(permuted, tmp_path, capsys):
    folder, x, y, perm = permuted
    ckpt, tuned = tmp_path / "s2.ckpt", tmp_path / "tuned.ckpt"
    base = ["train", str(folder), "--k", "12", "--width", "8", "--c-out", "8", "--no-cache", "--quiet"]
    assert main([*base, "--out", str(ckpt), "--max-steps", "2", "--stages", "2"]) == 0
    assert (
        main(
            [
                "train",
                str(folder),
                "--out",
                str(tuned),
                "--init",
                str(ckpt),
                "--max-steps",
                "1",
                "--quiet",
                "--no-cache",
            ]
        )
        == 0
    )
    from torchfmap.nn.checkpoints import load_checkpoint

    _, config, _ = load_checkpoint(tuned)
    assert config.stages == 2 and config.width == 8  # --init keeps the recipe
    out = tmp_path / "m.txt"
    lm = tmp_path / "lm.txt"
    inv = np.argsort(perm)
    lm.write_text(f"5 {inv[5]}\n40 {inv[40]}\n")
    capsys.readouterr()
    pair = [str(folder / "a0.off"), str(folder / "a1.off")]
    assert main(["match", *pair, "--checkpoint", str(ckpt), "--out", str(out), "--landmarks", str(lm)]) == 0
    assert "seeded by the landmarks" in capsys.readouterr().out
    assert main(["train", str(folder), "--out", str(tuned), "--init", str(ckpt), "--resume", "--quiet"]) == 2
    assert "--init starts a new run" in capsys.readouterr().err
