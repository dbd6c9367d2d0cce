"""Checks of torch inputs (as :mod:`torchfmap._util.checks` is for numpy ones). Shape checks read only
metadata and always run; data checks read values (a host sync on an accelerator) and run when the
``check`` argument says so (:func:`resolve_check`: ``None`` means on for CPU tensors only)."""

from __future__ import annotations

from ..errors import ParameterError
from .lazy import torch


def resolve_check(check: bool | None, tensor: torch.Tensor) -> bool:
    """The data-check switch: ``check`` itself, or for ``None`` whether ``tensor`` is on the CPU;
    :class:`ParameterError` if ``check`` is neither None nor a bool."""
    if check is None:
        return tensor.device.type == "cpu"
    if not isinstance(check, bool):
        raise ParameterError(f"check must be None, True or False, got {check!r}.")
    return check


def check_batched(f: torch.Tensor, batch: int, vertices: int, name: str) -> None:
    """``f`` is ``(batch, vertices, D)`` (shape check)."""
    if f.dim() != 3 or f.shape[0] != batch or f.shape[1] != vertices:
        raise ParameterError(
            f"{name} must be (B, V, D) = ({batch}, {vertices}, D), got {tuple(f.shape)}. Fix: one row "
            "per (padded) vertex, the same batch size as the basis."
        )


def check_finite(t: torch.Tensor, name: str, fix: str) -> None:
    """``t`` holds no NaN or inf (data check: syncs)."""
    if not bool(torch.isfinite(t).all()):
        raise ParameterError(f"{name} contain NaN or inf. Fix: {fix}")


def check_index_range(index: torch.Tensor, n: int, name: str, fix: str) -> None:
    """Every entry of the integer tensor ``index`` is in ``[0, n)`` (data check: syncs)."""
    if index.numel() == 0:
        return
    lo, hi = int(index.min()), int(index.max())
    if lo < 0 or hi >= n:
        raise ParameterError(f"{name} holds indices in [{lo}, {hi}], outside [0, {n}). Fix: {fix}")


def check_lengths(lengths: torch.Tensor | None, batch: int, vertices: int, name: str, check: bool) -> None:
    """``lengths (batch,)`` integer vertex counts (shape check); with ``check``, each in
    ``[1, vertices]`` (data check)."""
    if lengths is None:
        return
    if lengths.shape != (batch,) or lengths.dtype.is_floating_point or lengths.dtype == torch.bool:
        raise ParameterError(
            f"{name} must be ({batch},) integer vertex counts, got {tuple(lengths.shape)} {lengths.dtype}. "
            "Fix: pass BasisBatch.lengths (collate_shapes builds it)."
        )
    if check and lengths.numel():
        lo, hi = int(lengths.min()), int(lengths.max())
        if lo < 1 or hi > vertices:
            raise ParameterError(
                f"{name} holds vertex counts in [{lo}, {hi}], outside [1, {vertices}] (V = {vertices}). "
                "Fix: lengths[b] is the number of real vertices of shape b."
            )
