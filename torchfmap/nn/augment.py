"""Augmentation of XYZ inputs during training: random rigid motions and scalings
(:func:`random_rigid`), and the rule of which one :func:`~torchfmap.nn.train` applies
(:func:`augmentation`)."""

from __future__ import annotations

import torch

from ..errors import ParameterError
from .config import AUGMENTS, TrainConfig


def random_rigid(
    xyz: torch.Tensor, generator: torch.Generator, scale=(0.9, 1.1), rotate: bool = True
) -> torch.Tensor:
    """Augmentation for XYZ inputs: a random rotation (uniform on SO(3); none with
    ``rotate=False``) and a uniform scaling in ``scale`` per shape, ``(B, V, 3)``.

    Drawn (in float64) from ``generator`` on its device, then cast to ``xyz``'s dtype and device.
    """
    if not isinstance(generator, torch.Generator):
        raise ParameterError(
            f"random_rigid draws from a torch.Generator, got {type(generator).__name__}. Fix: pass one, "
            "e.g. torch.Generator().manual_seed(0)."
        )
    B, device = xyz.shape[0], generator.device
    q, r = torch.linalg.qr(torch.randn(B, 3, 3, generator=generator, dtype=torch.float64, device=device))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1))[:, None, :]
    # proper rotations only (reflections change the shape): flip the first column where det < 0
    flip = torch.where(torch.linalg.det(q) < 0, -1.0, 1.0).to(q)
    q = torch.cat([q[:, :, :1] * flip[:, None, None], q[:, :, 1:]], dim=-1)
    s = torch.empty(B, 1, 1, dtype=torch.float64, device=device).uniform_(*scale, generator=generator)
    if not rotate:
        q = torch.eye(3, dtype=torch.float64, device=device).expand(B, 3, 3)
    return xyz @ (s * q).to(xyz)


def augmentation(augment, inputs) -> str:
    """The augmentation :func:`~torchfmap.nn.train` applies to a dataset whose inputs are
    ``inputs`` (``'xyz'``, ``'wks'``, or None when unknown): None gives the recipe's
    (:class:`~torchfmap.nn.TrainConfig`) for XYZ inputs and ``"none"`` for others (WKS is
    invariant to rigid motions and scale); True / False are ``"rigid"`` / ``"none"``.

    Raises:
        ParameterError: an unknown augmentation, or one asked of inputs that are not XYZ.
    """
    if augment is None:
        return TrainConfig.augment if inputs == "xyz" else "none"
    augment = {True: "rigid", False: "none"}.get(augment, augment)
    if augment not in AUGMENTS:
        raise ParameterError(f"augment must be one of {AUGMENTS} or a bool, got {augment!r}.")
    if augment != "none" and inputs not in ("xyz", None):
        raise ParameterError(
            f"augment={augment!r} moves XYZ inputs, but the data's inputs are {inputs!r}. Fix: "
            "augment='none', or ShapeDataset(..., inputs='xyz')."
        )
    return augment


def recipe_augmentation(config: TrainConfig) -> str:
    """The augmentation a recipe trains with: ``config.augment`` for XYZ inputs, none for WKS
    (the recipe's setting concerns coordinates only; :func:`~torchfmap.nn.train_recipe`)."""
    return augmentation(config.augment if config.inputs == "xyz" else "none", config.inputs)
