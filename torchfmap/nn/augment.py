"""Augmentation of XYZ inputs in training (:func:`random_rigid`, :func:`augmentation`)."""

from __future__ import annotations

import torch

from ..errors import ParameterError
from .config import AUGMENTS
from .inputs import has_coordinates


def random_rigid(
    xyz: torch.Tensor, generator: torch.Generator, scale=(0.9, 1.1), rotation: str = "any"
) -> torch.Tensor:
    """``xyz (B, V, 3)`` randomly rotated (``rotation``: ``"any"``, ``"up"`` about ``y``, or ``"none"``)
    and scaled in ``scale``, drawn in float64 from ``generator``. Raises :class:`ParameterError`: no
    ``torch.Generator``, or an unknown ``rotation``."""
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
    """``(B, 3, 3)`` rotations by ``angles (B,)`` radians about ``y``, for ``xyz @ R``."""
    c, s, zero, one = torch.cos(angles), torch.sin(angles), torch.zeros_like(angles), torch.ones_like(angles)
    return torch.stack([c, zero, s, zero, one, zero, -s, zero, c], dim=-1).reshape(-1, 3, 3)


def augmentation(augment: str, inputs: str | None) -> str:
    """The augmentation training applies: ``augment`` for inputs with coordinates, else ``"none"``. Raises
    :class:`ParameterError`: an unknown augmentation."""
    if augment not in AUGMENTS:
        raise ParameterError(f"augment must be one of {AUGMENTS}, got {augment!r}.")
    return augment if has_coordinates(inputs) else "none"


def augment_batch(batch: dict, augment: str, generator: torch.Generator) -> dict:
    """``batch`` with both sides' coordinates moved by :func:`random_rigid` as ``augment`` says."""
    if augment == "none":
        return batch
    rotation = {"rigid": "any", "up": "up", "scale": "none"}[augment]

    def move(xyz: torch.Tensor) -> torch.Tensor:
        return random_rigid(xyz, generator, rotation=rotation)

    x, y = (batch[s]._replace(inputs=move_xyz(batch[s].inputs, move)) for s in "xy")
    return {**batch, "x": x, "y": y}


def move_xyz(inputs: torch.Tensor, move) -> torch.Tensor:
    """``inputs (..., C)`` with their last three channels replaced by ``move(coordinates)``."""
    return torch.cat([inputs[..., :-3], move(inputs[..., -3:])], dim=-1)
