"""The public torchfmap.nn API: checkpoints, training, inference and the matcher import from
the package itself (the README's imports), and are the objects their modules define."""

from __future__ import annotations

import importlib

import pytest

import torchfmap.nn as tnn
from torchfmap.nn import (
    CheckpointMatcher,
    TrainConfig,
    TrainState,
    build_model,
    build_solver,
    load_checkpoint,
    match_with_network,
    shipped_models,
    train,
    train_recipe,
)

HOMES = {
    "checkpoints": ("load_checkpoint", "save_checkpoint", "read_checkpoint"),
    "config": ("TrainConfig", "build_model", "build_solver", "CosineBudget"),
    "train": ("train", "train_recipe", "TrainState"),
    "inference": (
        "CheckpointMatcher",
        "match_with_network",
        "predict_p2p",
        "adapt",
        "refine_p2p",
        "evaluate",
    ),
    "shipped": ("shipped_models",),
}


def test_public_names_are_their_modules_objects():
    for module, names in HOMES.items():
        home = importlib.import_module(f"torchfmap.nn.{module}")
        for name in names:
            assert getattr(tnn, name) is getattr(home, name), name
            assert name in tnn.__all__, name


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
    assert callable(match_with_network) and CheckpointMatcher("faust_r").checkpoint == "faust_r"


def test_renamed_names_still_work_with_a_deprecation_warning():
    """One name per concept: the batched solve is ``solve_fmap`` as in the classical path; the
    old name warns and gives the same function."""
    import torchfmap.nn.functional as F

    with pytest.warns(DeprecationWarning, match="solve_fmap"):
        old = F.fmap_solve
    assert old is F.solve_fmap
    with pytest.raises(AttributeError):
        F.no_such_name  # noqa: B018


def test_the_learned_path_names_its_refinement_as_match_does():
    """``refine='zoomout'`` / None, as in ``torchfmap.match`` (True / False: the older form);
    other refinements are refused before any work."""
    from torchfmap.data import demo_pair_paths
    from torchfmap.errors import ParameterError
    from torchfmap.io import load_mesh
    from torchfmap.nn import CheckpointMatcher, load_checkpoint, match_with_network

    net, config, _ = load_checkpoint("faust_r")
    x, y = (load_mesh(p) for p in demo_pair_paths()[:2])
    with pytest.raises(ParameterError, match="refines by ZoomOut only"):
        match_with_network(net, config, x, y, refine="icp")
    with pytest.raises(ParameterError, match="refines by ZoomOut only"):
        CheckpointMatcher("faust_r", refine="seeded")
    assert CheckpointMatcher("faust_r", refine="zoomout").refine is True
    assert CheckpointMatcher("faust_r").refine is False
