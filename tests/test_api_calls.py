"""Direct calls of public functions that the rest of the suite only reaches through other entry
points (so that ``test_api_coverage`` can ask every public *function* to be called by a test)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfmap import ParameterError, curvature, save_mesh
from torchfmap.seeds import gaussian_curvature, mean_curvature

from .conftest import bend, bumpy_blob


def test_curvature_names_its_kinds():
    mesh = bumpy_blob(2)
    np.testing.assert_array_equal(curvature(mesh, "mean"), mean_curvature(mesh))
    np.testing.assert_array_equal(curvature(mesh, "abs_mean"), np.abs(mean_curvature(mesh)))
    np.testing.assert_array_equal(curvature(mesh, "gaussian"), gaussian_curvature(mesh))
    with pytest.raises(ParameterError, match="unknown curvature kind"):
        curvature(mesh, "max")


def test_register_kind_adds_a_kind_and_refuses_a_nameless_one():
    from dataclasses import replace

    from torchfmap.bases import KINDS, get_kind, register_kind

    copy = replace(KINDS["harmonic"], name="harmonic_copy")
    try:
        assert register_kind(copy) is copy and get_kind("harmonic_copy") is copy
    finally:
        KINDS.pop("harmonic_copy", None)
    with pytest.raises(ParameterError, match="non-empty string name"):
        register_kind(object())


def test_vertex_mask_marks_the_real_vertices():
    from torchfmap.nn.functional import vertex_mask

    mask = vertex_mask(torch.tensor([2, 4]), 4)
    assert mask.tolist() == [[True, True, False, False], [True, True, True, True]]
    assert vertex_mask(None, 4) is None


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
