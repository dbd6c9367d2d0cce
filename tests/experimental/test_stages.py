"""The self-seeded second stage (``torchfmap.experimental.stages``): bases that are B-orthonormal
and start with the stage-1 eigenbasis, an exact map of a vertex-permuted copy through both
stages, gradients through stage 2 in training as a plug-in loss of the core loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfmap import prepare_shape
from torchfmap.errors import ParameterError
from torchfmap.experimental.stages import StageTwo, StageTwoLoss, stage_two_loss, two_stage_p2p
from torchfmap.nn.data import ShapeDataset, collate_pairs
from torchfmap.nn.modules import RegularizedFMSolver, UnsupervisedFMLoss
from torchfmap.nn.train import ExtraLoss, forward_pair, pair_loss
from torchfmap.seeds import farthest_point_sampling

from ..conftest import bend, bumpy_blob


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


class InputsAsFeatures(torch.nn.Module):
    """A 'network' whose features are its inputs (WKS): exact on a vertex-permuted copy."""

    def __init__(self) -> None:
        super().__init__()
        self.scale = torch.nn.Parameter(torch.ones(()))

    def forward(self, inputs, basis, grad):
        return inputs * self.scale


def test_both_stages_map_a_permuted_copy_exactly(permuted_files):
    """Identical features on a permuted copy: stage 1 is the permutation, every seed is
    consistent, and stage 2, built at those seeds on both meshes, gives the permutation too."""
    folder, x, y, perm = permuted_files
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


def test_training_differentiates_through_stage_two(permuted_files):
    folder, *_ = permuted_files
    shapes = ShapeDataset([folder / "a0.off", folder / "a1.off"], False, k=16, n_wks=24, progress=False)
    net, solver, loss_fn = (
        InputsAsFeatures(),
        RegularizedFMSolver(w_lap=1e-3),
        UnsupervisedFMLoss(n_samples=0),
    )
    batch = collate_pairs([(shapes[0], shapes[1])])
    stage = StageTwo(n_seeds=10)
    plug_in = StageTwoLoss(shapes.mesh, stage)
    assert isinstance(plug_in, ExtraLoss)
    terms = pair_loss(net, solver, loss_fn, batch, extra_losses=[plug_in])
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


def test_too_few_consistent_seeds_add_nothing_and_the_trainer_takes_the_plug_in(permuted_files):
    """A step whose stage-1 map agrees at fewer than ``min_seeds`` seeds trains stage 1 alone
    (a zero term); the core loop trains with the plug-in without knowing what it is."""
    from torchfmap.nn import Budget, TrainConfig, Trainer

    folder, *_ = permuted_files
    config = TrainConfig(k=12, n_wks=8, k_net=16, width=8, c_out=8, n_blocks=1).with_budget(Budget(steps=2))
    files = [folder / "a0.off", folder / "a1.off"]
    shapes = ShapeDataset(files, False, **config.dataset_kwargs(), progress=False)
    net, solver = InputsAsFeatures(), RegularizedFMSolver(w_lap=1e-3)
    loss_fn = UnsupervisedFMLoss(n_samples=0)
    batch = collate_pairs([(shapes[0], shapes[1])])
    out = forward_pair(net, solver, batch)
    picky = StageTwoLoss(shapes.mesh, StageTwo(n_seeds=8, min_seeds=8))
    picky.stage.seeds = lambda *args, **kwargs: np.zeros((2, 2), dtype=np.int64)  # 2 < min_seeds
    assert picky(out, batch, solver=solver, loss_fn=loss_fn)["total"].item() == 0.0
    trainer = Trainer.from_config(config, shapes, device="cpu", extra_losses=[StageTwoLoss(shapes.mesh)])
    state = trainer.fit(progress=False)
    assert state.step == 2 and all("stage2_total" in t for t in state.losses)
