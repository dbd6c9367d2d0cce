"""Spatial gradients (``torchfmap.nn.gradients``): the compressed-row product against scipy,
gradient features (gradcheck, independence of the tangent frame)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from torchfmap.errors import ParameterError
from torchfmap.nn import functional as F
from torchfmap.nn.data import collate_shapes
from torchfmap.nn.inputs import shape_arrays, shape_item
from torchfmap.nn.networks import SpatialGradientFeatures
from torchfmap.operators.gradient import gradient_operator
from torchfmap.operators.laplacian import normalize_area

from ..conftest import _batch, _grid, bumpy_blob


def test_spatial_gradient_in_any_edge_order_and_padded_batches_equals_the_sparse_matrix():
    """The compressed-row product equals the scipy operator for (a) the precomputed sorted
    edges with their transpose order, (b) the same edges shuffled without it (sorted on the
    call), (c) a padded batch of two meshes of different sizes; so do the gradients
    (``Gᵀ ∂``, checked against scipy's transpose)."""
    meshes = [bumpy_blob(1), _grid(6)]
    items = [shape_item(shape_arrays(m, 6, 4, 20), dtype=torch.float64) for m in meshes]
    batch = collate_shapes(items)
    V = batch.inputs.shape[1]
    g = torch.Generator().manual_seed(4)
    f = torch.randn(2, V, 3, dtype=torch.float64, generator=g, requires_grad=True)
    seed = torch.randn(2, V, 3, dtype=torch.float64, generator=g)
    gx, gy = F.spatial_gradient(f, batch.grad)
    ((gx + 2 * gy) * seed).sum().backward()
    for b, m in enumerate(meshes):
        ops = gradient_operator(normalize_area(m))  # shape_arrays works at unit area
        n = len(m.vertices)
        edges = (ops["grad_rows"], ops["grad_cols"])
        Gx, Gy = (sp.csr_matrix((ops[w], edges), shape=(n, n)) for w in ("grad_x", "grad_y"))
        fb = f[b, :n].detach().numpy()
        np.testing.assert_allclose(gx[b, :n].detach().numpy(), Gx @ fb, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(gy[b, :n].detach().numpy(), Gy @ fb, rtol=1e-12, atol=1e-12)
        if n < V:  # padded vertices get no gradient
            assert gx[b, n:].abs().max() == 0 and gy[b, n:].abs().max() == 0
        expect = Gx.T @ seed[b, :n].numpy() + 2 * (Gy.T @ seed[b, :n].numpy())
        np.testing.assert_allclose(f.grad[b, :n].numpy(), expect, rtol=1e-12, atol=1e-12)
        # shuffled edges, no transpose order: sorted on the call, same result
        perm = torch.randperm(len(ops["grad_rows"]), generator=g)
        keys = ("grad_rows", "grad_cols", "grad_x", "grad_y")
        shuffled = F.GradientBatch(*(torch.as_tensor(ops[k])[perm][None] for k in keys))
        fb_t = f[b : b + 1, :n].detach()
        sx, sy = F.spatial_gradient(fb_t, shuffled)
        torch.testing.assert_close(sx[0], gx[b, :n].detach(), rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(sy[0], gy[b, :n].detach(), rtol=1e-12, atol=1e-12)
        # the same edges shuffled but claimed sorted (order_t given): the data check sorts them
        claimed = shuffled._replace(order_t=torch.as_tensor(ops["grad_order_t"])[None])
        torch.testing.assert_close(F.spatial_gradient(fb_t, claimed).x[0], sx[0], rtol=1e-12, atol=1e-12)
    # operators indexing vertices the features do not have: refused by the function and the layer
    # (a data check, on by default for CPU inputs); shapes that do not fit: refused always
    short = f[:, :30].detach()
    with pytest.raises(ParameterError, match=r"outside \[0, 30\)"):
        F.spatial_gradient(short, batch.grad)
    with pytest.raises(ParameterError, match=r"outside \[0, 30\)"):
        SpatialGradientFeatures(3).double()(short, batch.grad)
    with pytest.raises(ParameterError, match="must all be"):
        F.spatial_gradient(f, batch.grad._replace(cols=batch.grad.cols[:, :-1]), check=False)


def test_gradient_features_gradcheck():
    shape = _batch(bumpy_blob(1))
    layer = SpatialGradientFeatures(3).double()
    x = torch.randn(1, shape.inputs.shape[1], 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda x, a, b: F.gradient_features(*F.spatial_gradient(x, shape.grad), a, b),
        (x, layer.A_re, layer.A_im),
    )
    assert torch.autograd.gradcheck(lambda x: layer(x, shape.grad), (x,))


def test_gradient_features_do_not_depend_on_the_tangent_frame():
    """Rotating every frame by its own angle multiplies g by a unit complex number."""
    shape = _batch(bumpy_blob(1))
    layer = SpatialGradientFeatures(4).double()
    x = torch.randn(1, shape.inputs.shape[1], 4, dtype=torch.float64)
    gx, gy = F.spatial_gradient(x, shape.grad)
    theta = torch.rand(1, x.shape[1], 1, dtype=torch.float64) * 6.28
    rx, ry = torch.cos(theta) * gx - torch.sin(theta) * gy, torch.sin(theta) * gx + torch.cos(theta) * gy
    torch.testing.assert_close(
        F.gradient_features(gx, gy, layer.A_re, layer.A_im),
        F.gradient_features(rx, ry, layer.A_re, layer.A_im),
    )
