"""Baseline networks of experiments (``torchfmap.experimental.networks``): FeatureNet follows the
feature-network protocol, trains through the unsupervised loss and refuses non-finite inputs
under the data check."""

from __future__ import annotations

import pytest
import torch

from torchfmap import ParameterError
from torchfmap.experimental.networks import FeatureNet
from torchfmap.nn import RegularizedFMSolver, UnsupervisedFMLoss, check_network, collate_shapes, features
from torchfmap.nn.inputs import shape_arrays, shape_item

from ..conftest import _grid, as_batch, bumpy_blob


def test_feature_net_follows_the_protocol_on_a_padded_batch():
    """Called with ``(inputs, basis, grad)`` on two shapes of 42 and 36 vertices, it returns
    ``(B, V, C)`` in the inputs' dtype, as :func:`~torchfmap.nn.features` checks."""
    items = [
        shape_item(shape_arrays(m, 6, 6, 20, k_net=8), dtype=torch.float64) for m in (bumpy_blob(1), _grid(6))
    ]
    batch = collate_shapes(items)
    for dtype in (torch.float64, torch.float32):
        torch.manual_seed(0)
        net = FeatureNet(6, 5, width=8, n_blocks=1).to(dtype).eval()
        check_network(net)
        shape = batch.to(dtype)
        out = net(shape.inputs, shape.net_basis, shape.grad)
        assert out.shape == (2, 42, 5) and out.dtype == dtype
        torch.testing.assert_close(features(net, shape), out, rtol=0, atol=0)


def test_feature_net_and_unsupervised_loss_backward(nn_setting):
    x, y, dx, dy, eig, stack = nn_setting
    tx, ty = as_batch(*eig)
    net = FeatureNet(5, 8, width=16, n_blocks=2).double()
    fx, fy = net(torch.tensor(dx)[None], tx), net(torch.tensor(dy)[None], ty)
    C_xy, C_yx = RegularizedFMSolver()(fx, fy, tx, ty)
    terms = UnsupervisedFMLoss(w_lap=1.0)(C_xy, C_yx, fx, fy, tx, ty)
    terms["total"].backward()
    grads = [p.grad for p in net.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert set(terms) == {"bij", "orth", "lap", "couple", "total"}


def test_feature_net_data_check_follows_the_switch(nn_setting):
    x, y, dx, dy, eig, stack = nn_setting
    tx, _ = as_batch(*eig)
    bad = torch.tensor(dx)[None].clone()
    bad[0, 3, 1] = float("nan")
    with pytest.raises(ParameterError, match="NaN or inf"):
        FeatureNet(5, 4).double()(bad, tx)
    assert FeatureNet(5, 4, check=False).double()(bad, tx).shape == (1, x.n_vertices, 4)
