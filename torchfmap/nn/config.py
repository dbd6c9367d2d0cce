"""The reference training recipe: its settings (:class:`TrainConfig`, saved in checkpoints), the
model it builds (:func:`build_model`) and its learning-rate schedule over the budget
(:class:`CosineBudget`)."""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field

import torch

from ..errors import ParameterError
from .modules import RegularizedFMSolver, UnsupervisedFMLoss
from .networks import DiffusionNet

#: Augmentations of XYZ inputs (:attr:`TrainConfig.augment`).
AUGMENTS = ("rigid", "scale", "none")


@dataclass
class TrainConfig:
    """The reference recipe (saved in checkpoints): data, network, solver, loss and optimiser.

    ``augment`` (XYZ inputs only): ``"rigid"`` a random rotation and scaling per step,
    ``"scale"`` a scaling only (for data sets whose shapes are aligned alike), ``"none"``.
    ``stages``: 1, or 2 for the self-seeded second stage (:mod:`torchfmap.nn.stages`) at
    ``stage_seeds`` farthest points, trained with stage 1 and run by inference.
    """

    k: int = 50
    k_net: int = 96
    n_wks: int = 32
    basis: str = "laplacian"
    inputs: str = "wks"
    width: int = 48
    c_out: int = 64
    n_blocks: int = 4
    dropout: float = 0.0
    gradients: bool = True
    lr: float = 1e-3
    clip_grad: float = 0.0
    epochs: int = 5
    minutes: float = 0.0
    max_steps: int = 0
    batch_size: int = 1
    w_lap: float = 1e-3
    seed: int = 0
    augment: str = "rigid"
    stages: int = 1
    stage_seeds: int = 40
    loss_weights: dict = field(
        default_factory=lambda: {"w_bij": 1.0, "w_orth": 1.0, "w_couple": 1.0, "n_samples": 1000, "tau": 0.07}
    )

    def dataset_kwargs(self) -> dict:
        """Keyword arguments of :class:`~torchfmap.nn.data.ShapeDataset` for this recipe."""
        return dict(k=self.k, n_wks=self.n_wks, k_net=self.k_net, basis=self.basis, inputs=self.inputs)


def network_kwargs(config: TrainConfig) -> dict:
    """The :class:`~torchfmap.nn.networks.DiffusionNet` arguments of the recipe ``config``."""
    c_in = config.n_wks if config.inputs == "wks" else 3
    return dict(
        c_in=c_in, c_out=config.c_out, width=config.width, n_blocks=config.n_blocks,
        dropout=config.dropout, gradients=config.gradients,
    )  # fmt: skip


def build_model(config: TrainConfig) -> tuple[DiffusionNet, RegularizedFMSolver, UnsupervisedFMLoss]:
    """``(network, solver, loss)`` of the recipe. The network's initial weights are drawn with
    torch's CPU generator seeded by ``config.seed`` inside ``torch.random.fork_rng``, so the same
    seed gives the same network and the caller's global RNG state is left as it was."""
    with torch.random.fork_rng(devices=[]):
        torch.default_generator.manual_seed(config.seed)
        net = DiffusionNet(**network_kwargs(config))
    return (net, *build_solver(config))


def build_solver(config: TrainConfig) -> tuple[RegularizedFMSolver, UnsupervisedFMLoss]:
    """``(solver, loss)`` of the recipe, without building a network (inference)."""
    return RegularizedFMSolver(w_lap=config.w_lap), UnsupervisedFMLoss(**config.loss_weights)


class CosineBudget:
    """Learning-rate factor for ``LambdaLR``: cosine from 1 to ``floor`` over the training budget.

    The budget is ``steps`` optimiser steps and/or ``minutes`` of training (0: not bounded by
    it; at least one must be set); the schedule follows whichever is further spent,
    ``frac = max(step / steps, seconds / (60 minutes))``, so it reaches ``floor`` exactly when
    training stops. Time is counted between its calls in this process; ``LambdaLR.state_dict``
    saves the time counted so far, and after ``load_state_dict`` in another process the clock
    continues from there (the gap between the runs is not counted); the step comes from the
    scheduler, which is saved with it.

    Raises:
        ParameterError: no budget, or a negative or non-finite one.
    """

    def __init__(self, minutes: float = 0.0, steps: int = 0, floor: float = 0.02) -> None:
        if not (math.isfinite(minutes) and minutes >= 0) or steps < 0:
            raise ParameterError(f"the budget must be finite and >= 0, got {minutes} minutes, {steps} steps.")
        if not minutes and not steps:
            raise ParameterError("the schedule needs a budget. Fix: minutes > 0 and/or steps > 0.")
        if not 0 <= floor <= 1:
            raise ParameterError(f"floor must be in [0, 1], got {floor}.")
        self.seconds, self.steps, self.floor = 60.0 * minutes, int(steps), floor
        self.counted, self.last, self.pid = 0.0, None, os.getpid()

    @property
    def budget(self) -> tuple[float, int, float]:
        """``(seconds, steps, floor)``: the budget (settable, e.g. after ``load_state_dict``)."""
        return self.seconds, self.steps, self.floor

    @budget.setter
    def budget(self, value: tuple[float, int, float]) -> None:
        self.seconds, self.steps, self.floor = value

    def set_clock(self, seconds: float) -> None:
        """Set the training time spent so far to ``seconds``; the next call adds none of its own.
        The ranks of a DDP run set one agreed clock before each step, so their learning rates,
        hence their weights, agree to the bit (each rank's own clock differs by microseconds)."""
        self.counted, self.last = float(seconds), None

    def fraction(self, step: int) -> float:
        """The part of the budget spent at ``step`` (and the time counted), in ``[0, 1]``."""
        by_time = self.counted / self.seconds if self.seconds else 0.0
        by_steps = step / self.steps if self.steps else 0.0
        return min(max(by_time, by_steps), 1.0)

    def __call__(self, step: int) -> float:
        now = time.perf_counter()
        if self.last is not None and self.pid == os.getpid():
            self.counted += now - self.last
        self.last, self.pid = now, os.getpid()
        frac = self.fraction(step)
        return self.floor + (1 - self.floor) * 0.5 * (1 + math.cos(math.pi * frac))


def CosineByTime(minutes: float, floor: float = 0.02) -> CosineBudget:
    """:class:`CosineBudget` over a time budget only (the name of earlier releases)."""
    return CosineBudget(minutes=minutes, floor=floor)
