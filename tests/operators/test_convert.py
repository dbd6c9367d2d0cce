"""scipy <-> torch sparse matrices (``torchfmap.operators.convert``)."""

from __future__ import annotations

import numpy as np
import torch

from torchfmap.operators import laplacian, scipy_to_torch, torch_to_scipy


def test_scipy_torch_round_trip(blob):
    L, _ = laplacian(blob)
    t = scipy_to_torch(L)
    assert t.dtype == torch.float64 and t.is_sparse
    assert abs(torch_to_scipy(t) - L).max() == 0
    x = np.random.default_rng(0).normal(size=blob.n_vertices)
    assert np.allclose((t @ torch.from_numpy(x)).numpy(), L @ x)
    t32 = scipy_to_torch(L, dtype=torch.float32, layout=torch.sparse_csr)
    assert t32.dtype == torch.float32 and t32.layout == torch.sparse_csr
    assert abs(torch_to_scipy(t32) - L).max() < 1e-4 * abs(L).max()
    assert abs(torch_to_scipy(t.to_dense()) - L).max() == 0
