"""Augmentation (``torchfmap.nn.augment``): which one ``train`` applies to which inputs, and the
recipe's values as the loop's defaults."""

from __future__ import annotations

import inspect

import pytest
import torch

from torchfmap.errors import ParameterError
from torchfmap.nn import RegularizedFMSolver, TrainConfig, build_solver, train
from torchfmap.nn.augment import augmentation, random_rigid


def test_the_default_augmentation_is_the_recipes_for_xyz_and_none_for_wks():
    assert augmentation(None, "xyz") == TrainConfig.augment == "rigid"
    assert augmentation(None, "wks") == augmentation(None, None) == "none"
    assert augmentation(True, "xyz") == "rigid" and augmentation(False, "wks") == "none"
    assert augmentation("scale", "xyz") == "scale" and augmentation("rigid", None) == "rigid"


def test_augmenting_features_that_are_not_coordinates_is_refused():
    """A rotation of WKS channels is meaningless (and was a shape error deep in the loop)."""
    with pytest.raises(ParameterError, match="moves XYZ inputs.*'wks'"):
        augmentation("rigid", "wks")
    with pytest.raises(ParameterError, match="augment must be one of"):
        augmentation("shear", "xyz")


def test_random_rigid_needs_a_generator():
    with pytest.raises(ParameterError, match="torch.Generator"):
        random_rigid(torch.zeros(1, 4, 3), 0)


def test_the_loops_defaults_are_the_recipes():
    """One set of defaults: ``train``'s budget, batch, clipping and seed are ``TrainConfig``'s,
    and the recipe's solver is what ``train`` and ``evaluate`` solve with when given none."""
    recipe = TrainConfig()
    params = inspect.signature(train).parameters
    for name in ("epochs", "minutes", "max_steps", "batch_size", "clip_grad", "seed"):
        assert params[name].default == getattr(recipe, name), name
    assert params["augment"].default is None  # resolved by the data's inputs (above)


class _Built(Exception):
    pass


def test_train_and_evaluate_solve_with_the_recipes_solver_when_given_none(monkeypatch):
    """Without a solver both loops ask the recipe for one (``build_solver(TrainConfig())``, the
    ``w_lap`` the shipped models were trained with), not the layer's classical default."""
    import importlib

    inference = importlib.import_module("torchfmap.nn.inference")
    training = importlib.import_module("torchfmap.nn.train")  # torchfmap.nn.train is the function

    from ..conftest import TinyNet

    asked = []

    def recipe_solver(config):
        asked.append(config)
        raise _Built

    for module in (training, inference):
        monkeypatch.setattr(module, "build_solver", recipe_solver)
    with pytest.raises(_Built):
        train(TinyNet(6), None, None, None, progress=False)
    with pytest.raises(_Built):
        inference.evaluate(TinyNet(6), None, [], [])
    assert asked == [TrainConfig(), TrainConfig()]
    assert build_solver(TrainConfig())[0].w_lap == TrainConfig.w_lap != RegularizedFMSolver().w_lap
