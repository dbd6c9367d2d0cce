"""Augmentation of XYZ inputs during training: random rigid motions and scalings
(:func:`random_rigid`), and the rule of which one training applies (:func:`augmentation`)."""

from __future__ import annotations

import torch

from ..errors import ParameterError
from .config import AUGMENTS
from .inputs import has_coordinates


def random_rigid(
    xyz: torch.Tensor, generator: torch.Generator, scale=(0.9, 1.1), rotation: str = "any"
) -> torch.Tensor:
    """Augmentation for XYZ inputs, ``(B, V, 3)``: a random rotation and a uniform scaling in
    ``scale`` per shape. ``rotation``: ``"any"`` uniform on SO(3), ``"up"`` a uniform angle about
    the ``y`` axis (shapes standing alike, facing anywhere), ``"none"``.

    Drawn (in float64) from ``generator`` on its device, then cast to ``xyz``'s dtype and device.

    Raises:
        ParameterError: no ``torch.Generator``, or an unknown ``rotation``.
    """
    if not isinstance(generator, torch.Generator):
        raise ParameterError(
            f"random_rigid draws from a torch.Generator, got {type(generator).__name__}. Fix: pass one, "
            "e.g. torch.Generator().manual_seed(0)."
        )
    if rotation not in ("any", "up", "none"):
        raise ParameterError(f"rotation must be 'any', 'up' or 'none', got {rotation!r}.")
    B, device = xyz.shape[0], generator.device
    f64 = dict(dtype=torch.float64, device=device)
    if rotation == "any":
        q, r = torch.linalg.qr(torch.randn(B, 3, 3, generator=generator, **f64))
        q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1))[:, None, :]
        # proper rotations only (reflections change the shape): flip the first column where det < 0
        flip = torch.where(torch.linalg.det(q) < 0, -1.0, 1.0).to(q)
        q = torch.cat([q[:, :, :1] * flip[:, None, None], q[:, :, 1:]], dim=-1)
    elif rotation == "up":
        q = yaw_matrices(torch.empty(B, **f64).uniform_(0, 2 * torch.pi, generator=generator))
    else:
        q = torch.eye(3, **f64).expand(B, 3, 3)
    s = torch.empty(B, 1, 1, **f64).uniform_(*scale, generator=generator)
    return xyz @ (s * q).to(xyz)


def yaw_matrices(angles: torch.Tensor) -> torch.Tensor:
    """``(B, 3, 3)`` rotations by ``angles (B,)`` (radians) about the ``y`` axis, in their dtype
    and device, to multiply row vectors on the right (``xyz @ R``)."""
    c, s, zero, one = torch.cos(angles), torch.sin(angles), torch.zeros_like(angles), torch.ones_like(angles)
    return torch.stack([c, zero, s, zero, one, zero, -s, zero, c], dim=-1).reshape(-1, 3, 3)


def augmentation(augment: str, inputs: str | None) -> str:
    """The one rule of which augmentation training applies (:class:`~torchfmap.nn.trainer.Trainer`,
    from :attr:`TrainConfig.augment <torchfmap.nn.TrainConfig>`): ``augment`` for inputs with
    coordinates (``'xyz'``, ``'wks+xyz'``), ``"none"`` for any other (``'wks'``, or None when the
    data's inputs are unknown): the setting moves coordinates, and WKS is invariant to rigid
    motions and scale.

    Raises:
        ParameterError: an unknown augmentation.
    """
    if augment not in AUGMENTS:
        raise ParameterError(f"augment must be one of {AUGMENTS}, got {augment!r}.")
    return augment if has_coordinates(inputs) else "none"


def augment_batch(batch: dict, augment: str, generator: torch.Generator) -> dict:
    """``batch`` (:func:`~torchfmap.nn.data.collate_pairs`) with the coordinates of both sides'
    inputs (their last three channels) moved by :func:`random_rigid` (``augment``: ``"rigid"``
    any rotation, ``"up"`` a rotation about the ``y`` axis, ``"scale"`` none, each with a
    scaling, as :func:`augmentation` resolved it; ``"none"``: the batch itself)."""
    if augment == "none":
        return batch
    rotation = {"rigid": "any", "up": "up", "scale": "none"}[augment]
    moved = [
        batch[s]._replace(
            inputs=move_xyz(batch[s].inputs, lambda xyz: random_rigid(xyz, generator, rotation=rotation))
        )
        for s in "xy"
    ]
    return {**batch, "x": moved[0], "y": moved[1]}


def move_xyz(inputs: torch.Tensor, move) -> torch.Tensor:
    """``inputs`` ``(..., C)`` with their coordinates, the last three channels, replaced by
    ``move(coordinates)`` (the other channels, e.g. WKS, unchanged)."""
    return torch.cat([inputs[..., :-3], move(inputs[..., -3:])], dim=-1)
