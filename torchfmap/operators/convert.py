"""Conversion between scipy sparse matrices and torch sparse tensors (float64 kept by default)."""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp

from .._util.lazy import torch


def scipy_to_torch(
    matrix: sp.spmatrix | sp.sparray,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
    layout: torch.layout | None = None,
) -> torch.Tensor:
    """A scipy sparse ``(M, N)`` matrix as a coalesced torch sparse tensor of ``layout``
    ``torch.sparse_coo`` (default) or ``torch.sparse_csr`` (else ValueError); ``dtype``: the matrix's own
    by default."""
    layout = torch.sparse_coo if layout is None else layout
    coo = sp.coo_matrix(matrix)
    coo.sum_duplicates()
    values = torch.from_numpy(np.ascontiguousarray(coo.data))
    if dtype is not None:
        values = values.to(dtype)
    indices = torch.from_numpy(np.vstack([coo.row, coo.col]).astype(np.int64))
    out = torch.sparse_coo_tensor(
        indices, values, coo.shape, device=device, check_invariants=False
    ).coalesce()
    if layout == torch.sparse_csr:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
            return out.to_sparse_csr()
    if layout != torch.sparse_coo:
        raise ValueError(f"layout must be torch.sparse_coo or torch.sparse_csr, got {layout}.")
    return out


def torch_to_scipy(tensor: torch.Tensor) -> sp.csr_matrix:
    """A torch sparse (COO or CSR) or dense 2-D tensor as a scipy CSR matrix (dtype kept)."""
    t = tensor.detach().cpu()
    if t.layout == torch.strided:
        return sp.csr_matrix(t.numpy())
    coo = t.to_sparse_coo().coalesce() if t.layout != torch.sparse_coo else t.coalesce()
    idx = coo.indices().numpy()
    return sp.csr_matrix((coo.values().numpy(), (idx[0], idx[1])), shape=tuple(coo.shape))
