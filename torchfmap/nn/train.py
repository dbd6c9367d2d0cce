"""The losses of training, one pair batch at a time: a network's features and maps of a
collated batch (:func:`forward_pair`), their loss terms with any plug-in terms added
(:func:`pair_loss`, :class:`ExtraLoss`), the unsupervised validation score
(:func:`unsupervised_score`) and what a run records (:class:`TrainState`).

The loop itself is :class:`~torchfmap.nn.trainer.Trainer`; :mod:`torchfmap.nn.config` holds the
reference recipe, :mod:`torchfmap.nn.checkpoints` the checkpoint files.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple, Protocol, runtime_checkable

import torch

from .augment import augment_batch, augmentation
from .data import ShapeDataset, collate_pairs
from .modules import UnsupervisedFMLoss
from .networks import features


class PairForward(NamedTuple):
    """Result of :func:`forward_pair`: features ``(B, V_x, D)``, ``(B, V_y, D)`` and both maps
    ``C_xy (B, K_y, K_x)``, ``C_yx (B, K_x, K_y)`` (None from a one-direction solver)."""

    feat_x: torch.Tensor
    feat_y: torch.Tensor
    C_xy: torch.Tensor
    C_yx: torch.Tensor | None


@runtime_checkable
class ExtraLoss(Protocol):
    """A plug-in loss term of training (``Trainer(..., extra_losses=[...])``), e.g.
    :class:`torchfmap.experimental.stages.StageTwoLoss`.

    Called once per batch with the batch's forward pass as
    ``extra(out: PairForward, batch, solver=..., loss_fn=..., generator=...)``; returns a dict of
    tensors with ``'total'``, logged as ``<name>_<term>`` and whose ``'total'`` is added to the
    batch's total. ``name`` prefixes its terms.
    """

    name: str

    def __call__(self, out: PairForward, batch: dict, *, solver, loss_fn, generator) -> dict: ...


def forward_pair(net, solver, batch: dict) -> PairForward:
    """Features and both maps of a collated batch (:func:`~torchfmap.nn.data.collate_pairs`)."""
    x, y = batch["x"], batch["y"]
    feat_x, feat_y = features(net, x), features(net, y)
    C_xy, C_yx = solver(feat_x, feat_y, x.basis, y.basis)
    return PairForward(feat_x, feat_y, C_xy, C_yx)


def pair_loss(
    net,
    solver,
    loss_fn,
    batch: dict,
    generator: torch.Generator | None = None,
    extra_losses: Sequence[ExtraLoss] = (),
) -> dict[str, torch.Tensor]:
    """The loss terms of a collated batch:
    ``loss_fn(C_xy, C_yx, feat_x, feat_y, basis_x, basis_y, generator=generator)``, then each
    plug-in of ``extra_losses`` (:class:`ExtraLoss`) on the same forward pass: its terms are
    added as ``<name>_<term>`` and its ``'total'`` to ``'total'``."""
    out = forward_pair(net, solver, batch)
    terms = loss_fn(
        out.C_xy, out.C_yx, out.feat_x, out.feat_y, batch["x"].basis, batch["y"].basis, generator=generator
    )
    for extra in extra_losses:
        more = extra(out, batch, solver=solver, loss_fn=loss_fn, generator=generator)
        named = {f"{extra.name}_{n}": v for n, v in more.items()}
        terms = {**terms, **named, "total": terms["total"] + more["total"]}
    return terms


def unsupervised_score(
    shapes: ShapeDataset,
    pairs,
    solver,
    loss_fn: UnsupervisedFMLoss,
    device: str | torch.device = "cpu",
    extra_losses: Sequence[ExtraLoss] = (),
    augment: str = "none",
    seed: int = 0,
):
    """``score(net) -> float``: the mean unsupervised loss (plug-in terms included) on ``pairs``
    with full (not sampled) soft maps, in eval mode, for the trainer's ``validate`` (lower is
    better; no ground truth). Batches are moved to ``device``.

    ``augment``: the recipe's augmentation (:attr:`TrainConfig.augment
    <torchfmap.nn.TrainConfig>`), resolved for the shapes' inputs by the training's rule
    (:func:`~torchfmap.nn.augment.augmentation`) and applied to the validation pairs once, with
    draws from ``seed``: the score measures the pairs as training sees them (a network trained
    facing anywhere is scored on turned pairs, not only on the pairs as stored), and every call
    scores the same inputs.

    Raises:
        ParameterError: an unknown ``augment``.
    """
    full = copy.deepcopy(loss_fn)
    full.n_samples = 0
    augment = augmentation(augment, getattr(shapes, "inputs", None))
    draws = torch.Generator().manual_seed(seed)
    batches = [augment_batch(collate_pairs([(shapes[a], shapes[b])]), augment, draws) for a, b in pairs]

    @torch.no_grad()
    def score(net) -> float:
        net.eval()
        total = 0.0
        for batch in batches:
            batch = {**batch, "x": batch["x"].to(device), "y": batch["y"].to(device)}
            total += float(pair_loss(net, solver, full, batch, extra_losses=extra_losses)["total"])
        return total / max(len(batches), 1)

    return score


@dataclass
class TrainState:
    """What a run records and checkpoints: per-step losses, full epochs, the batches done of the
    current epoch, seconds of training, per-epoch times, validation scores ``(step, score)``,
    the best score, and the state of the random draws (augmentation, loss sampling) where the
    run stands, so that a run resumed mid-epoch goes on as the uninterrupted run would."""

    step: int = 0
    epoch: int = 0
    batch: int = 0
    draws: list | None = None
    seconds: float = 0.0
    losses: list = field(default_factory=list)
    epoch_seconds: list = field(default_factory=list)
    scores: list = field(default_factory=list)
    best_score: float = math.inf
