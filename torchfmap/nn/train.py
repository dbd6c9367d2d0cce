"""The losses of training (:func:`pair_loss`), its score (:func:`unsupervised_score`), :class:`TrainState`."""

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
    """Result of :func:`forward_pair`: ``feat_x``, ``feat_y (B, V, D)``, ``C_xy (B, K_y, K_x)``, ``C_yx``."""

    feat_x: torch.Tensor
    feat_y: torch.Tensor
    C_xy: torch.Tensor
    C_yx: torch.Tensor | None


@runtime_checkable
class ExtraLoss(Protocol):
    """A plug-in loss term of the ``Trainer``'s ``extra_losses``, called as ``extra(out, batch, solver=,
    loss_fn=, generator=)``: it returns tensors with ``'total'`` (added to the batch's total), logged as
    ``<name>_<term>``."""

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
    """The terms ``loss_fn(C_xy, C_yx, feat_x, feat_y, basis_x, basis_y, generator=generator)`` of a
    collated batch (None: a zero total), plus each of ``extra_losses`` as ``<name>_<term>`` (its ``'total'``
    added)."""
    out = forward_pair(net, solver, batch)
    if loss_fn is None:
        terms = {"total": out.feat_x.new_zeros(())}
    else:
        x, y = batch["x"].basis, batch["y"].basis
        terms = loss_fn(out.C_xy, out.C_yx, out.feat_x, out.feat_y, x, y, generator=generator)
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
    """``score(net) -> float``: the mean unsupervised loss (full soft maps, eval mode) on ``pairs``,
    augmented once as training would (draws from ``seed``); lower is better. Raises
    :class:`ParameterError`: an unknown ``augment``."""
    full = copy.deepcopy(loss_fn)
    full.n_samples = 0
    augment = augmentation(augment, getattr(shapes, "inputs", None))
    draws = torch.Generator().manual_seed(seed)
    batches = [augment_batch(collate_pairs([(shapes[a], shapes[b])]), augment, draws) for a, b in pairs]

    def value(net, batch: dict) -> torch.Tensor:
        return pair_loss(net, solver, full, batch, extra_losses=extra_losses)["total"]

    return batch_score(batches, value, device)


def batch_score(batches: list[dict], value, device: str | torch.device = "cpu"):
    """``score(net) -> float``: the mean of ``value(net, batch)`` (a scalar tensor) over collated
    ``batches`` moved to ``device``, in eval mode without gradients; lower is better."""

    @torch.no_grad()
    def score(net) -> float:
        net.eval()
        total = 0.0
        for batch in batches:
            batch = {**batch, "x": batch["x"].to(device), "y": batch["y"].to(device)}
            total += float(value(net, batch))
        return total / max(len(batches), 1)

    return score


@dataclass
class TrainState:
    """A run's record: step, epochs, batches of this epoch, draws' state, seconds, losses, times, scores."""

    step: int = 0
    epoch: int = 0
    batch: int = 0
    draws: list | None = None
    seconds: float = 0.0
    losses: list = field(default_factory=list)
    epoch_seconds: list = field(default_factory=list)
    scores: list = field(default_factory=list)
    best_score: float = math.inf
