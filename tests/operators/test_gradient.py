"""The intrinsic gradient operator (``torchfmap.operators.gradient``), exact on linear functions."""

from __future__ import annotations

import numpy as np
import torch

from torchfmap.nn import functional as F
from torchfmap.operators.gradient import gradient_operator, tangent_frames

from ..conftest import _grid


def test_gradient_is_exact_for_linear_functions_on_a_plane():
    """On a flat mesh with normal +z the frames are (x, y) and every face gradient of a linear
    function is exact, so the vertex gradient is exact to round-off."""
    mesh = _grid()
    ops = gradient_operator(mesh)
    grad = F.GradientBatch(
        *(torch.as_tensor(ops[k])[None] for k in ("grad_rows", "grad_cols", "grad_x", "grad_y"))
    )
    f = torch.as_tensor(mesh.vertices @ np.array([0.7, -2.0, 5.0]))[None, :, None]
    out = F.spatial_gradient(f, grad)
    assert isinstance(out, F.TangentGradient) and out.x is out[0]
    gx, gy = out
    torch.testing.assert_close(gx, torch.full_like(gx, 0.7), rtol=0, atol=1e-12)
    torch.testing.assert_close(gy, torch.full_like(gy, -2.0), rtol=0, atol=1e-12)


def test_tangent_frames_are_right_handed_orthonormal_with_the_vertex_normal(blob):
    frames = tangent_frames(blob)  # (V, 3, 3): e1, e2, n
    eye = np.broadcast_to(np.eye(3), frames.shape)
    np.testing.assert_allclose(frames @ frames.transpose(0, 2, 1), eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(frames), 1.0, atol=1e-12)
    np.testing.assert_allclose(frames[:, 2], blob.vertex_normals, atol=1e-12)
