"""Tangent-frame gradients in torch (:func:`spatial_gradient`), also in :mod:`torchfmap.nn.functional`."""

from __future__ import annotations

import warnings
from typing import NamedTuple

import torch

from .._util.torch_checks import check_index_range, resolve_check
from ..errors import ParameterError


class GradientBatch(NamedTuple):
    """Padded vertex gradient operators (:func:`torchfmap.operators.gradient_operator`): with
    ``rows, cols (B, E)`` int64 and ``weight_x, weight_y (B, E)`` (0 when padded), ``(∇f)_v = Σ_{rows == v}
    weight · f[cols]``. With ``order_t (B, E)`` (the per-shape permutation sorting edges by ``(col, row)``)
    the edges must be sorted by ``(row, col)``, else every call sorts."""

    rows: torch.Tensor
    cols: torch.Tensor
    weight_x: torch.Tensor
    weight_y: torch.Tensor
    order_t: torch.Tensor | None = None

    def to(self, *args, **kwargs) -> GradientBatch:
        """Weights follow ``.to(dtype/device)``; indices only move device."""
        moved = [t.to(*args, **kwargs) for t in (self.weight_x, self.weight_y)]
        device = moved[0].device
        order_t = None if self.order_t is None else self.order_t.to(device)
        return GradientBatch(self.rows.to(device), self.cols.to(device), *moved, order_t)


class TangentGradient(NamedTuple):
    """Result of :func:`spatial_gradient`: the ``e1`` and ``e2`` components, ``(B, V, C)`` each."""

    x: torch.Tensor
    y: torch.Tensor


def _csr(crow: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, n: int) -> torch.Tensor:
    with warnings.catch_warnings():  # "sparse CSR support is in beta": the product used here is not
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(crow, cols, values, (n, n))


def _row_pointers(sorted_index: torch.Tensor, n: int) -> torch.Tensor:
    """CSR row pointers ``(n + 1,)`` of ascending row indices (a search, no host sync)."""
    return torch.searchsorted(sorted_index, torch.arange(n + 1, device=sorted_index.device))


class _SparsePairProduct(torch.autograd.Function):
    """``(Gx f, Gy f)`` for CSR ``Gx, Gy``; backward by the prebuilt transposes."""

    @staticmethod
    def forward(ctx, f, Gx, Gy, GxT, GyT):
        ctx.transposes = (GxT, GyT)
        return Gx @ f, Gy @ f

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, dgx, dgy):
        GxT, GyT = ctx.transposes
        return GxT @ dgx + GyT @ dgy, None, None, None, None


def spatial_gradient(f: torch.Tensor, grad: GradientBatch, *, check: bool | None = None) -> TangentGradient:
    """Tangent-frame gradient ``(B, V, C) -> TangentGradient((B, V, C), (B, V, C))`` (one block-diagonal CSR
    product, in ``f``'s dtype and device). ``check``: indices in ``[0, V)`` and the ``order_t`` sort.

    Raises:
        ParameterError: shapes that do not fit; with ``check``, vertex indices out of range."""
    E = grad.rows.shape[-1]
    if f.dim() != 3 or grad.rows.dim() != 2 or grad.rows.shape[0] != f.shape[0]:
        raise ParameterError(
            f"features must be (B, V, C) with B={grad.rows.shape[0]} (the operators' batch), got "
            f"{tuple(f.shape)}. Fix: collate features and operators of the same shapes."
        )
    parts = [grad.cols, grad.weight_x, grad.weight_y] + ([] if grad.order_t is None else [grad.order_t])
    if any(t.shape != grad.rows.shape for t in parts):
        raise ParameterError(
            f"the gradient operator's rows, cols, weights and order_t must all be (B, E) = "
            f"{tuple(grad.rows.shape)}, got {[tuple(t.shape) for t in parts]}. Fix: collate_shapes "
            "builds them."
        )
    check = resolve_check(check, f)
    B, V, C = f.shape
    if check:
        fix = "use the operators precomputed for these meshes."
        check_index_range(grad.rows, V, "the gradient operator's rows", fix)
        check_index_range(grad.cols, V, "the gradient operator's cols", fix)
    N = B * V
    offset = V * torch.arange(B, device=f.device)[:, None]  # shape b's vertices are rows bV..bV+V-1
    rows, cols = ((index.to(f.device) + offset).reshape(-1) for index in (grad.rows, grad.cols))
    wx, wy = (w.to(dtype=f.dtype, device=f.device).reshape(-1) for w in (grad.weight_x, grad.weight_y))
    order_t = None
    if grad.order_t is not None:  # per-shape (col, row) orders; the blocks follow each other
        order_t = (grad.order_t.to(f.device) + E * torch.arange(B, device=f.device)[:, None]).reshape(-1)
    key = rows * N + cols
    by_row_sorted = order_t is not None  # the documented contract; verified under check
    if check and key.numel() > 1:
        by_row_sorted = bool((key[1:] >= key[:-1]).all())
    if not by_row_sorted:
        by_row = torch.argsort(key)
        rows, cols, wx, wy, order_t = rows[by_row], cols[by_row], wx[by_row], wy[by_row], None
    if order_t is None:
        order_t = torch.argsort(cols * N + rows)
    rows_t, cols_t = rows[order_t], cols[order_t]
    crow, ccol = _row_pointers(rows, N), _row_pointers(cols_t, N)
    Gx, Gy = (_csr(crow, cols, w, N) for w in (wx, wy))
    GxT, GyT = (_csr(ccol, rows_t, w[order_t], N) for w in (wx, wy))
    gx, gy = _SparsePairProduct.apply(f.reshape(N, C), Gx, Gy, GxT, GyT)
    return TangentGradient(gx.reshape(B, V, C), gy.reshape(B, V, C))


def gradient_features(
    gx: torch.Tensor, gy: torch.Tensor, A_re: torch.Tensor, A_im: torch.Tensor
) -> torch.Tensor:
    """``tanh(Re(conj(g) ⊙ (A g)))`` ``(B, V, C)`` for ``g = gx + i gy`` and ``A = A_re + i A_im (C, C)``:
    frame-independent; ``A_im`` tells left from right."""
    if gx.shape != gy.shape or A_re.shape != A_im.shape or A_re.shape != (gx.shape[-1], gx.shape[-1]):
        raise ParameterError(
            f"gradients must have equal shapes (B, V, C) and A_re, A_im be (C, C); got {tuple(gx.shape)}, "
            f"{tuple(gy.shape)}, {tuple(A_re.shape)}, {tuple(A_im.shape)}."
        )
    b_re, b_im = gx @ A_re.T - gy @ A_im.T, gy @ A_re.T + gx @ A_im.T
    return torch.tanh(gx * b_re + gy * b_im)
