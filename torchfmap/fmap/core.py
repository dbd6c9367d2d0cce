"""The regularised functional-map solve, written once for numpy arrays and torch tensors.

These functions take numpy arrays (the classical path, :mod:`torchfmap.fmap.solver`) or torch
tensors (the differentiable path, :mod:`torchfmap.nn`), with any number of leading batch
dimensions; torch tensors keep their autograd graph, dtype and device.
"""

from __future__ import annotations

import functools
import threading
from typing import Any

import numpy as np
import torch

from ..errors import ParameterError


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def _eye(n: int, like) -> Any:
    if _is_torch(like):
        return torch.eye(n, dtype=like.dtype, device=like.device)
    return np.eye(n, dtype=np.asarray(like).dtype)


def laplacian_mask(lam_x, lam_y, kind: str = "laplacian", gamma: float = 0.5, valid=None):
    """``(..., K_y, K_x)`` penalty on the rotated map, normalised to mean 1 per batch item.

    ``valid`` (optional ``(..., K_y, K_x)`` 0/1) marks the entries of padded batches that
    exist; the mean is taken over those only, so padding does not change the result.

    ``laplacian``: ``(λ_x,j - λ_y,i)²``; ``resolvent``: Ren et al. 2019's resolvent mask with
    exponent ``gamma`` on eigenvalues scaled by their common maximum. Negative round-off
    eigenvalues are clipped to 0.
    """
    lx = lam_x.clip(min=0) if _is_torch(lam_x) else np.maximum(lam_x, 0)
    ly = lam_y.clip(min=0) if _is_torch(lam_y) else np.maximum(lam_y, 0)
    lx, ly = lx[..., None, :], ly[..., :, None]
    if kind == "laplacian":
        mask = (lx - ly) ** 2
    elif kind == "resolvent":
        if _is_torch(lx):
            top = torch.maximum(lx.amax(dim=(-2, -1), keepdim=True), ly.amax(dim=(-2, -1), keepdim=True))
            scale = top.clip(min=1e-300)
        else:
            top = np.maximum(lx.max(axis=(-2, -1), keepdims=True), ly.max(axis=(-2, -1), keepdims=True))
            scale = np.maximum(top, 1e-300)
        gx, gy = (lx / scale) ** gamma, (ly / scale) ** gamma
        re = gy / (gy**2 + 1) - gx / (gx**2 + 1)
        im = 1 / (gy**2 + 1) - 1 / (gx**2 + 1)
        mask = re**2 + im**2
    else:
        raise ParameterError(f"unknown mask {kind!r}. Fix: 'laplacian' or 'resolvent'.")
    if valid is not None:
        mask = mask * valid
    if _is_torch(mask):
        count = (
            valid.sum(dim=(-2, -1), keepdim=True) if valid is not None else mask.shape[-1] * mask.shape[-2]
        )
        mean = mask.sum(dim=(-2, -1), keepdim=True) / count
        return mask / mean.clip(min=1e-300)
    count = valid.sum(axis=(-2, -1), keepdims=True) if valid is not None else mask.shape[-1] * mask.shape[-2]
    mean = mask.sum(axis=(-2, -1), keepdims=True) / count
    return mask / np.where(mean > 0, mean, 1.0)


def solve_rowwise(A_x, A_y, mask, w_desc: float, w_lap: float, valid=None):
    """Minimise ``w_desc ‖C A_x - A_y‖² + w_lap Σ_ij M_ij C_ij²`` exactly, one system per row.

    Shapes: ``A_x (..., K_x, D)``, ``A_y (..., K_y, D)``, ``mask (..., K_y, K_x)`` ->
    ``C (..., K_y, K_x)``. One batched ``linalg.solve`` over ``(..., K_y, K_x, K_x)``.
    ``valid`` (``(..., K_y, K_x)`` 0/1) marks existing entries of a padded batch: padded
    coefficients get a unit diagonal and a zero right-hand side, so they come out 0 and the
    valid block equals the unpadded solution.
    """
    G = w_desc * (A_x @ A_x.swapaxes(-1, -2))  # (..., Kx, Kx)
    rhs = w_desc * (A_y @ A_x.swapaxes(-1, -2))  # (..., Ky, Kx)
    diag = w_lap * mask  # (..., Ky, Kx): added to the diagonal of row i's system
    if valid is not None:
        diag = diag + (1 - valid)
        rhs = rhs * valid
    if _is_torch(G):
        return _rowwise_solve_function().apply(G, diag, rhs)
    eye = _eye(A_x.shape[-2], A_x)
    systems = G[..., None, :, :] + diag[..., :, :, None] * eye  # (..., Ky, Kx, Kx)
    return np.linalg.solve(systems, rhs[..., None])[..., 0]


#: Largest work tensor (bytes) that :func:`_scratch` keeps between calls.
SCRATCH_MAX_BYTES = 256 * 2**20
_SCRATCH = threading.local()


def _scratch(shape: tuple[int, ...], like):
    """A work tensor of ``shape`` for the row-wise systems, reused between calls on the CPU.

    The systems are only needed until LAPACK has copied them; on the CPU a fresh buffer of
    that size costs page faults on every call (about a quarter of the batched solve's time at
    B = 8, K = 100), so one buffer per thread and dtype, of at most :data:`SCRATCH_MAX_BYTES`,
    is kept. CUDA tensors come from torch's caching allocator instead.
    """
    n = 1
    for d in shape:
        n *= d
    if like.device.type != "cpu" or n * like.element_size() > SCRATCH_MAX_BYTES:
        return torch.empty(shape, dtype=like.dtype, device=like.device)
    cache = getattr(_SCRATCH, "buffers", None)
    if cache is None:
        cache = _SCRATCH.buffers = {}
    buf = cache.get(like.dtype)
    if buf is None or buf.numel() < n:
        buf = cache[like.dtype] = torch.empty(n, dtype=like.dtype)
    return buf[:n].view(shape)


@functools.cache
def _rowwise_solve_function():
    """The torch autograd Function of the row-wise solve (built lazily: torch is optional here)."""

    class RowwiseSolve(torch.autograd.Function):
        """``c_i = (G + diag(d_i))⁻¹ r_i`` for every row ``i``; shapes ``G (..., Kx, Kx)``,
        ``d, r (..., Ky, Kx)`` -> ``c (..., Ky, Kx)``.

        Forward: one batched LU of the ``(..., Ky, Kx, Kx)`` systems. Backward reuses the LU
        factors (``u_i = S_i⁻ᵀ ∂c_i``) and returns ``∂G = -Σ_i u_i c_iᵀ``, ``∂d_i = -u_i ∘ c_i``,
        ``∂r_i = u_i`` without building a ``(..., Ky, Kx, Kx)`` gradient (autograd through
        ``torch.linalg.solve`` did, at about twice the cost). Under
        ``create_graph=True`` (higher derivatives) the backward is recomputed with
        differentiable dense solves.
        """

        @staticmethod
        def forward(ctx, G, diag, rhs):
            shape = (*G.shape[:-2], diag.shape[-2], *G.shape[-2:])
            systems = _scratch(shape, G)
            systems.copy_(G.unsqueeze(-3).expand(shape))
            systems.diagonal(dim1=-2, dim2=-1).add_(diag)
            # LAPACK works column-major: factorising the transposed view Sᵀ makes its working
            # copy a plain memcpy; S x = r is then solved as (Sᵀ)ᵀ x = r (adjoint=True), exact
            # whether or not round-off left S slightly unsymmetric
            LU, pivots, _ = torch.linalg.lu_factor_ex(systems.mT)
            c = torch.linalg.lu_solve(LU, pivots, rhs[..., None], adjoint=True)[..., 0]
            ctx.save_for_backward(G, diag, rhs, LU, pivots, c)
            return c

        @staticmethod
        def backward(ctx, grad_c):
            G, diag, rhs, LU, pivots, c = ctx.saved_tensors
            if torch.is_grad_enabled():  # create_graph: a backward that is itself differentiable
                systems = G.unsqueeze(-3) + torch.diag_embed(diag)
                c = torch.linalg.solve(systems, rhs[..., None])[..., 0]
                u = torch.linalg.solve(systems.transpose(-1, -2), grad_c[..., None])[..., 0]
            else:
                u = torch.linalg.lu_solve(LU, pivots, grad_c[..., None])[..., 0]  # Sᵀ u = ∂c
            return -(u.transpose(-1, -2) @ c), -(u * c), u

    return RowwiseSolve


def rotate_and_solve(
    A_x,
    A_y,
    lam_x,
    U_x,
    lam_y,
    U_y,
    *,
    w_desc: float = 1.0,
    w_lap: float = 1e-3,
    mask: str = "laplacian",
    valid=None,
):
    """``C_xy (..., K_y, K_x)`` in any B-orthonormal basis from its spectral frames.

    ``W_x = U_x diag(lam_x) U_xᵀ``: rotating ``A`` by ``U`` makes the Laplacian term
    ``‖C W_x - W_y C‖²`` a diagonal mask, so :func:`solve_rowwise` is exact.
    """
    A_xr = U_x.swapaxes(-1, -2) @ A_x
    A_yr = U_y.swapaxes(-1, -2) @ A_y
    Cr = solve_rowwise(A_xr, A_yr, laplacian_mask(lam_x, lam_y, mask, valid=valid), w_desc, w_lap, valid)
    return U_y @ Cr @ U_x.swapaxes(-1, -2)
