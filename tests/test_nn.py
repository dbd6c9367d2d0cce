"""The public ``torchfmap.nn`` API (the package's ``__init__``): checkpoints, training, inference
and the matcher import from the package itself (the README's imports), and are the objects their
modules define."""

from __future__ import annotations

import importlib

import torchfmap.nn as tnn

HOMES = {
    "checkpoints": ("load_checkpoint", "save_checkpoint", "read_checkpoint", "read_recipe"),
    "config": ("TrainConfig", "Budget", "build_model", "build_solver", "CosineBudget"),
    "train": ("TrainState", "unsupervised_score"),
    "trainer": ("Trainer",),
    "devices": ("resolve_device",),
    "inference": ("LearnedMatcher",),
    "item_inference": ("predict_p2p", "adapt", "evaluate"),
    "shipped": ("shipped_models",),
}


def test_public_names_are_their_modules_objects():
    for module, names in HOMES.items():
        home = importlib.import_module(f"torchfmap.nn.{module}")
        for name in names:
            assert getattr(tnn, name) is getattr(home, name), name
            assert name in tnn.__all__, name
