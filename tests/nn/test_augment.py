"""Augmentation (``torchfmap.nn.augment``): the one rule of which augmentation training applies
to which inputs, and the moves themselves."""

from __future__ import annotations

import pytest
import torch

from torchfmap.errors import ParameterError
from torchfmap.nn import TrainConfig
from torchfmap.nn.augment import augment_batch, augmentation, random_rigid
from torchfmap.nn.data import ShapeBatch


def test_the_recipes_augmentation_moves_xyz_inputs_only():
    """WKS is invariant to rigid motions and scale: the recipe's setting concerns coordinates."""
    assert augmentation(TrainConfig.augment, "xyz") == "rigid"
    assert augmentation("scale", "xyz") == "scale" and augmentation("none", "xyz") == "none"
    assert augmentation("rigid", "wks") == augmentation("scale", None) == "none"
    with pytest.raises(ParameterError, match="augment must be one of"):
        augmentation("shear", "xyz")


def test_random_rigid_needs_a_generator():
    with pytest.raises(ParameterError, match="torch.Generator"):
        random_rigid(torch.zeros(1, 4, 3), 0)


def test_augment_batch_rotates_and_scales_both_sides_or_nothing():
    xyz = torch.randn(2, 5, 3, generator=torch.Generator().manual_seed(1))
    side = ShapeBatch(*[None] * len(ShapeBatch._fields))._replace(inputs=xyz)
    batch = {"x": side, "y": side, "index": [(0, 1), (1, 0)]}
    assert augment_batch(batch, "none", torch.Generator()) is batch
    moved = augment_batch(batch, "rigid", torch.Generator().manual_seed(0))
    assert moved["index"] == batch["index"] and not torch.allclose(moved["x"].inputs, xyz)
    # a rotation and a scaling in [0.9, 1.1]: the pairwise distances scale by one factor per shape
    d0, d1 = torch.cdist(xyz, xyz), torch.cdist(moved["x"].inputs, moved["x"].inputs)
    ratio = d1[d0 > 0] / d0[d0 > 0]
    assert 0.9 - 1e-6 <= ratio.min() and ratio.max() <= 1.1 + 1e-6
    scaled = augment_batch(batch, "scale", torch.Generator().manual_seed(0))["y"].inputs
    factor = scaled / xyz  # a scaling only: one factor per shape
    assert torch.allclose(factor, factor[:, :1, :1].expand_as(factor), rtol=1e-5)


def test_up_rotation_turns_about_y_only_and_scales():
    """augment='up' (SMAL: animals standing alike, facing anywhere): y @ T keeps the y axis, the
    x-z plane is rotated (angles spread over the circle) and scaled by s in [0.9, 1.1]."""
    xyz = torch.randn(64, 20, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    moved = random_rigid(xyz, torch.Generator().manual_seed(0), rotation="up")
    T = torch.linalg.lstsq(xyz, moved).solution  # (64, 3, 3) = s * R_y(angle)
    s = T[:, 1, 1]
    assert ((s >= 0.9) & (s <= 1.1)).all()
    torch.testing.assert_close(T[:, 1, [0, 2]], torch.zeros(64, 2, dtype=T.dtype), atol=1e-12, rtol=0)
    torch.testing.assert_close(T[:, [0, 2], 1], torch.zeros(64, 2, dtype=T.dtype), atol=1e-12, rtol=0)
    R = T / s[:, None, None]
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(64, dtype=T.dtype), atol=1e-12, rtol=0)
    angles = torch.atan2(R[:, 0, 2], R[:, 0, 0])
    assert (angles < -2).any() and (angles > 2).any()  # both facings, not a small jitter
    assert augmentation("up", "xyz") == "up" and augmentation("up", "wks") == "none"
    with pytest.raises(ParameterError, match="rotation must be"):
        random_rigid(xyz, torch.Generator(), rotation="tilt")


def test_wks_and_xyz_inputs_move_their_coordinates_only():
    """inputs='wks+xyz': the WKS channels first, the coordinates last; augmentation moves the
    coordinates (a rigid motion and scaling: distances scale by one factor) and keeps the WKS."""
    assert augmentation("up", "wks+xyz") == "up"
    g = torch.Generator().manual_seed(3)
    wks, xyz = torch.randn(2, 6, 4, generator=g), torch.randn(2, 6, 3, generator=g)
    side = ShapeBatch(*[None] * len(ShapeBatch._fields))._replace(inputs=torch.cat([wks, xyz], -1))
    moved = augment_batch({"x": side, "y": side}, "rigid", torch.Generator().manual_seed(0))["x"].inputs
    assert torch.equal(moved[..., :4], wks)
    d0, d1 = torch.cdist(xyz, xyz), torch.cdist(moved[..., 4:], moved[..., 4:])
    ratio = d1[d0 > 0] / d0[d0 > 0]
    assert 0.9 - 1e-6 <= ratio.min() and ratio.max() <= 1.1 + 1e-6 and not torch.allclose(moved[..., 4:], xyz)
