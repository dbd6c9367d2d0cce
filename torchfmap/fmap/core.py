"""The functional-map core in torch, shared by :mod:`torchfmap.fmap.solver` and :mod:`torchfmap.nn`:
any leading batch dimensions, the input's dtype and device, autograd kept."""

from __future__ import annotations

import functools
from typing import Literal, NamedTuple

import numpy as np

from .._util.lazy import torch
from .._util.torch_checks import resolve_check
from ..errors import ParameterError

#: The Laplacian-commutativity masks (:func:`laplacian_mask`'s ``mask``).
Mask = Literal["laplacian", "resolvent"]


def as_tensor(x, dtype: torch.dtype | None = None) -> torch.Tensor:
    """A torch view of a numpy array (float64 by default) or the tensor itself, unchanged."""
    if isinstance(x, torch.Tensor):
        return x
    return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float64)).to(dtype or torch.float64)


class SpectralFrame(NamedTuple):
    """``W = U diag(lam) Uᵀ``: eigenvalues ``lam (..., K)`` ascending, orthogonal ``U (..., K, K)``."""

    lam: torch.Tensor
    U: torch.Tensor


def spectral_frame(W: torch.Tensor) -> SpectralFrame:
    """:class:`SpectralFrame` ``(lam (..., K) ascending, U (..., K, K))`` of projected Laplacians
    ``W (..., K, K)`` (symmetrised), in ``W``'s dtype and device; ``U = I`` for an eigenbasis's
    (diagonal, ascending) ``W``."""
    if W.shape[-1] != W.shape[-2]:
        raise ParameterError(f"W must be square (..., K, K), got {tuple(W.shape)}.")
    W = 0.5 * (W + W.transpose(-1, -2))
    lam = torch.diagonal(W, dim1=-2, dim2=-1)
    off = torch.linalg.matrix_norm(W - torch.diag_embed(lam))
    tol = torch.finfo(W.dtype).eps ** 0.5 * torch.linalg.matrix_norm(W)
    if W.numel() and bool((off <= tol).all()) and bool((lam[..., 1:] >= lam[..., :-1]).all()):
        eye = torch.eye(W.shape[-1], dtype=W.dtype, device=W.device).expand(W.shape)
        return SpectralFrame(lam.clone(), eye.clone())
    return SpectralFrame(*torch.linalg.eigh(W))


def laplacian_mask(
    lam_x: torch.Tensor,
    lam_y: torch.Tensor,
    mask: Mask = "laplacian",
    gamma: float = 0.5,
    valid: torch.Tensor | None = None,
) -> torch.Tensor:
    """``(..., K_y, K_x)`` penalty on the rotated map, mean 1 per batch item, from eigenvalues
    ``lam_x (..., K_x)``, ``lam_y (..., K_y)``: ``mask='laplacian'``: ``(λ_x,j - λ_y,i)²``;
    ``'resolvent'``: Ren et al. 2019's (exponent ``gamma``). ``valid``: optional ``(..., K_y,
    K_x)`` 0/1 of a padded batch. Raises ParameterError for an unknown ``mask``."""
    lx = lam_x.clip(min=0)[..., None, :]
    ly = lam_y.clip(min=0)[..., :, None]
    if mask == "laplacian":
        penalty = (lx - ly) ** 2
    elif mask == "resolvent":
        top = torch.maximum(lx.amax(dim=(-2, -1), keepdim=True), ly.amax(dim=(-2, -1), keepdim=True))
        scale = top.clip(min=torch.finfo(top.dtype).tiny)
        gx, gy = (lx / scale) ** gamma, (ly / scale) ** gamma
        re = gy / (gy**2 + 1) - gx / (gx**2 + 1)
        im = 1 / (gy**2 + 1) - 1 / (gx**2 + 1)
        penalty = re**2 + im**2
    else:
        raise ParameterError(f"unknown mask {mask!r}. Fix: 'laplacian' or 'resolvent'.")
    if valid is not None:
        penalty = penalty * valid
        count = valid.sum(dim=(-2, -1), keepdim=True)
    else:
        count = penalty.shape[-1] * penalty.shape[-2]
    mean = penalty.sum(dim=(-2, -1), keepdim=True) / count
    return penalty / torch.where(mean > 0, mean, torch.ones_like(mean))


def solve_rowwise(
    A_x: torch.Tensor,
    A_y: torch.Tensor,
    mask: torch.Tensor,
    w_desc: float,
    w_lap: float,
    valid: torch.Tensor | None = None,
    prior: torch.Tensor | None = None,
    w_prior: float = 0.0,
    *,
    check: bool | None = None,
) -> torch.Tensor:
    """``C (..., K_y, K_x)`` minimising ``w_desc ‖C A_x - A_y‖² + w_lap Σ_ij M_ij C_ij² + w_prior
    ‖C - P‖²`` exactly (one system per row, differentiable); ``A_x (..., K_x, D)``, ``A_y (..., K_y,
    D)``, ``mask``, ``valid`` (0/1 of a padded batch) and ``prior`` ``(..., K_y, K_x)``. ``check``:
    refuse overflowing Gram matrices and singular systems (None: on CPU only).

    Raises:
        ParameterError: not float32/float64; with ``check``, overflow or a singular system.
    """
    if A_x.dtype not in (torch.float32, torch.float64):
        raise ParameterError(
            f"the functional-map solve needs float32 or float64, got {A_x.dtype}. Fix: cast the "
            "features first, e.g. feats.float() (half precision has too few digits for the LU)."
        )
    check = resolve_check(check, A_x)
    G = w_desc * (A_x @ A_x.transpose(-1, -2))  # (..., Kx, Kx)
    rhs = w_desc * (A_y @ A_x.transpose(-1, -2))  # (..., Ky, Kx)
    if check and not bool(torch.isfinite(G).all() & torch.isfinite(rhs).all()):
        raise ParameterError(
            f"the descriptor Gram matrix overflows {A_x.dtype} (features too large). Fix: normalise "
            "the features (e.g. to unit norm per vertex) or solve in float64."
        )
    diag = w_lap * mask  # (..., Ky, Kx): row i's diagonal
    if prior is not None and w_prior:
        diag = diag + w_prior
        rhs = rhs + w_prior * prior
    if valid is not None:
        diag = diag + (1 - valid)
        rhs = rhs * valid
    return _rowwise_solve().apply(G, diag, rhs, check)


@functools.cache
def _singular_reason(G: torch.Tensor, diag: torch.Tensor) -> str:
    """Why the row-wise systems ``G + diag(d_i)`` are singular, and the fix, in words."""
    if not bool(G.abs().amax() > 0):
        return (
            "the descriptor term is zero (the descriptors, or the bases they are projected on, are "
            "zero: e.g. a basis of zero mass). Fix: check the bases' mass and the descriptors."
        )
    if not bool(diag.abs().amax() > 0):
        return "the descriptors span too little and the Laplacian term is off (w_lap = 0). Fix: w_lap > 0."
    return "the descriptors span too little for this basis size. Fix: more descriptors or a smaller k."


def _rowwise_solve():
    """The autograd Function of :func:`solve_rowwise`, defined on first use (lazy torch)."""

    class _RowwiseSolve(torch.autograd.Function):
        """``c_i = (G + diag(d_i))⁻¹ r_i`` per row; ``G (..., Kx, Kx)``, ``d, r (..., Ky, Kx)``. The
        backward reuses the LU; under ``create_graph=True`` it uses differentiable dense solves."""

        @staticmethod
        def forward(ctx, G, diag, rhs, check):
            shape = (*G.shape[:-2], diag.shape[-2], *G.shape[-2:])
            systems = G.unsqueeze(-3).expand(shape).contiguous()
            systems.diagonal(dim1=-2, dim2=-1).add_(diag)
            # Sᵀ is LAPACK's column-major layout: LU in place, then S x = r as (Sᵀ)ᵀ x = r (adjoint)
            LU = systems.mT
            pivots = torch.empty(shape[:-1], dtype=torch.int32, device=G.device)
            info = torch.empty(shape[:-2], dtype=torch.int32, device=G.device)
            torch.linalg.lu_factor_ex(LU, out=(LU, pivots, info))
            if check and bool((info > 0).any()):
                raise ParameterError(f"the functional-map systems are singular: {_singular_reason(G, diag)}")
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
            return -(u.transpose(-1, -2) @ c), -(u * c), u, None

    return _RowwiseSolve


def rotate_and_solve(
    A_x: torch.Tensor,
    A_y: torch.Tensor,
    lam_x: torch.Tensor,
    U_x: torch.Tensor,
    lam_y: torch.Tensor,
    U_y: torch.Tensor,
    *,
    w_desc: float,
    w_lap: float,
    mask: Mask = "laplacian",
    valid: torch.Tensor | None = None,
    prior: torch.Tensor | None = None,
    w_prior: float = 0.0,
    check: bool | None = None,
) -> torch.Tensor:
    """``C_xy (..., K_y, K_x)`` solved by :func:`solve_rowwise` in the frames ``lam_x, U_x, lam_y,
    U_y`` (:func:`spectral_frame`); ``A_x, A_y`` and ``prior`` unrotated, the rest as there."""
    A_xr = U_x.transpose(-1, -2) @ A_x
    A_yr = U_y.transpose(-1, -2) @ A_y
    Pr = None if prior is None else U_y.transpose(-1, -2) @ prior @ U_x
    weights = laplacian_mask(lam_x, lam_y, mask, valid=valid)
    Cr = solve_rowwise(A_xr, A_yr, weights, w_desc, w_lap, valid, Pr, w_prior, check=check)
    return U_y @ Cr @ U_x.transpose(-1, -2)
