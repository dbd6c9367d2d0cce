"""The reference training recipe: its settings (:class:`TrainConfig`, saved in checkpoints), the
model it builds (:func:`build_model`) and its time-budget learning-rate schedule
(:class:`CosineByTime`)."""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field

import torch

from ..errors import ParameterError
from .modules import RegularizedFMSolver, UnsupervisedFMLoss
from .networks import DiffusionNet


@dataclass
class TrainConfig:
    """The reference recipe (saved in checkpoints): data, network, solver, loss and optimiser."""

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
    batch_size: int = 1
    w_lap: float = 1e-3
    seed: int = 0
    loss_weights: dict = field(
        default_factory=lambda: {"w_bij": 1.0, "w_orth": 1.0, "w_couple": 1.0, "n_samples": 1000, "tau": 0.07}
    )

    def dataset_kwargs(self) -> dict:
        """Keyword arguments of :class:`~torchfmap.nn.data.ShapeDataset` for this recipe."""
        return dict(k=self.k, n_wks=self.n_wks, k_net=self.k_net, basis=self.basis, inputs=self.inputs)


def build_model(config: TrainConfig) -> tuple[DiffusionNet, RegularizedFMSolver, UnsupervisedFMLoss]:
    """``(network, solver, loss)`` of the recipe. The network's initial weights are drawn with
    torch's CPU generator seeded by ``config.seed`` inside ``torch.random.fork_rng``, so the same
    seed gives the same network and the caller's global RNG state is left as it was."""
    c_in = config.n_wks if config.inputs == "wks" else 3
    with torch.random.fork_rng(devices=[]):
        torch.default_generator.manual_seed(config.seed)
        net = DiffusionNet(
            c_in, config.c_out, config.width, config.n_blocks, config.dropout, config.gradients
        )
    return net, RegularizedFMSolver(w_lap=config.w_lap), UnsupervisedFMLoss(**config.loss_weights)


class CosineByTime:
    """Learning-rate factor for ``LambdaLR``: cosine from 1 to ``floor`` over a time budget.

    Counts the time between its calls in this process; ``LambdaLR.state_dict`` saves the time
    counted so far, and after ``load_state_dict`` in another process the clock continues from
    there (the gap between the runs is not counted).
    """

    def __init__(self, minutes: float, floor: float = 0.02) -> None:
        if minutes <= 0:
            raise ParameterError(f"the time budget must be positive, got {minutes} minutes.")
        self.seconds, self.floor = 60.0 * minutes, floor
        self.counted, self.last, self.pid = 0.0, None, os.getpid()

    def __call__(self, step: int) -> float:
        now = time.perf_counter()
        if self.last is not None and self.pid == os.getpid():
            self.counted += now - self.last
        self.last, self.pid = now, os.getpid()
        frac = min(self.counted / self.seconds, 1.0)
        return self.floor + (1 - self.floor) * 0.5 * (1 + math.cos(math.pi * frac))
