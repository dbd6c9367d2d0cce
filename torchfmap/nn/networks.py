"""Feature networks: the protocol :class:`FeatureNetwork` (``net(inputs (B, V, C_in), basis, grad)`` ->
``(B, V, D)`` in ``inputs``' dtype and device; :func:`check_network`, :func:`features`) and the reference
:class:`DiffusionNet`. Checkpoints rebuild a network from its class and ``init_kwargs`` (plain values)."""

from __future__ import annotations

import inspect
from typing import TYPE_CHECKING, Protocol

import torch
from torch import nn

from .._util.torch_checks import check_finite, resolve_check
from ..errors import ParameterError
from . import functional as F
from .functional import BasisBatch, GradientBatch
from .modules import SpectralDiffusion

if TYPE_CHECKING:  # annotations only: data sits beside this module
    from .data import ShapeBatch


class FeatureNetwork(Protocol):
    """``(inputs (B, V, C_in), basis BasisBatch, grad GradientBatch) -> features (B, V, D)`` (static type)."""

    def __call__(self, inputs: torch.Tensor, basis: BasisBatch, grad: GradientBatch) -> torch.Tensor: ...


def check_network(net) -> None:
    """Refuse (:class:`ParameterError`) a non-module or a ``forward`` not taking ``(inputs, basis, grad)``."""
    if not isinstance(net, nn.Module):
        raise ParameterError(
            f"a feature network must be a torch.nn.Module, got {type(net).__name__}. Fix: subclass "
            "torch.nn.Module with forward(inputs, basis, grad) -> (B, V, D)."
        )
    try:
        inspect.signature(net.forward).bind(None, None, None)
    except TypeError as err:
        raise ParameterError(
            f"{type(net).__name__}.forward must take (inputs, basis, grad) ({err}). Fix: add the "
            "missing arguments (a network may ignore grad: forward(self, inputs, basis, grad=None))."
        ) from None


def features(net, shape: ShapeBatch) -> torch.Tensor:
    """The features ``(B, V, D)`` of a :class:`~torchfmap.nn.data.ShapeBatch`, :class:`ParameterError`
    unless ``(B, V, D)`` in the dtype and on the device of ``shape.inputs``."""
    out, inputs = net(shape.inputs, shape.net_basis, shape.grad), shape.inputs
    fits = isinstance(out, torch.Tensor) and out.dim() == 3 and out.shape[:2] == inputs.shape[:2]
    if not (fits and out.dtype == inputs.dtype and out.device == inputs.device):
        got = (
            f"{tuple(out.shape)} {out.dtype} on {out.device}" if isinstance(out, torch.Tensor) else type(out)
        )
        raise ParameterError(
            f"the network returned {got}; a feature network returns (B, V, D) = ({inputs.shape[0]}, "
            f"{inputs.shape[1]}, D) in {inputs.dtype} on {inputs.device}, like its inputs. Fix: one "
            "feature row per (padded) input vertex, in the inputs' dtype."
        )
    return out


class SpatialGradientFeatures(nn.Module):
    """Learned rotation-invariant gradient features ``(B, V, C) -> (B, V, C)``, mixing ``A_re + i A_im``."""

    def __init__(self, channels: int, check: bool | None = None) -> None:
        super().__init__()
        self.check = check
        self.A_re = nn.Parameter(torch.empty(channels, channels))
        self.A_im = nn.Parameter(torch.empty(channels, channels))
        for p in (self.A_re, self.A_im):
            nn.init.kaiming_uniform_(p, a=5**0.5)

    def forward(self, x: torch.Tensor, grad: GradientBatch) -> torch.Tensor:
        """``x (B, V, C) -> (B, V, C)``."""
        gx, gy = F.spatial_gradient(x, grad, check=self.check)
        return F.gradient_features(gx, gy, self.A_re, self.A_im)


class DiffusionNetBlock(nn.Module):
    """``x + MLP([x, diffuse(x), gradient_features(diffuse(x))])``, ``(B, V, C) -> (B, V, C)``."""

    def __init__(
        self, width: int, dropout: float = 0.5, gradients: bool = True, check: bool | None = None
    ) -> None:
        super().__init__()
        self.diffusion = SpectralDiffusion(width)
        self.gradient = SpatialGradientFeatures(width, check) if gradients else None
        n_in = 3 * width if gradients else 2 * width
        self.mlp = nn.Sequential(
            nn.Linear(n_in, width), nn.ReLU(), nn.Dropout(dropout), nn.Linear(width, width)
        )

    def forward(self, x: torch.Tensor, basis: BasisBatch, grad: GradientBatch) -> torch.Tensor:
        """``x (B, V, width) -> (B, V, width)``."""
        diffused = self.diffusion(x, basis)
        parts = [x, diffused]
        if self.gradient is not None:
            parts.append(self.gradient(diffused, grad))
        return x + self.mlp(torch.cat(parts, dim=-1))


class DiffusionNet(nn.Module):
    """Reference feature network: lift to ``width``, ``n_blocks`` :class:`DiffusionNetBlock`, head to
    ``c_out``. Invariant to rigid motions with WKS inputs; gradient features (``gradients``) tell
    reflections apart. ``init_kwargs``: the constructor arguments."""

    def __init__(
        self,
        c_in: int,
        c_out: int = 64,
        width: int = 64,
        n_blocks: int = 4,
        dropout: float = 0.5,
        gradients: bool = True,
        check: bool | None = None,
    ) -> None:
        super().__init__()
        self.init_kwargs = dict(c_in=c_in, c_out=c_out, width=width, n_blocks=n_blocks, dropout=dropout)
        self.init_kwargs.update(gradients=gradients, check=check)
        if min(c_in, c_out, width, n_blocks) < 1 or not 0 <= dropout < 1:
            raise ParameterError(
                f"DiffusionNet needs c_in, c_out, width, n_blocks >= 1 and 0 <= dropout < 1; got "
                f"{c_in}, {c_out}, {width}, {n_blocks}, {dropout}."
            )
        self.lift = nn.Linear(c_in, width)
        self.check = check
        self.blocks = nn.ModuleList(
            DiffusionNetBlock(width, dropout, gradients, check) for _ in range(n_blocks)
        )
        self.head = nn.Linear(width, c_out)

    def forward(self, inputs: torch.Tensor, basis: BasisBatch, grad: GradientBatch) -> torch.Tensor:
        """``(B, V, C_in) -> (B, V, c_out)`` same dtype; :class:`ParameterError` if non-finite (``check``)."""
        if resolve_check(self.check, inputs):
            check_finite(inputs, "DiffusionNet inputs", "check the precomputed inputs (WKS, XYZ).")
        basis = F.basis_like(basis, inputs)
        h = self.lift(inputs)
        for block in self.blocks:
            h = block(h, basis, grad)
        return self.head(h)
