"""Feature networks: the plug-in protocol and the reference DiffusionNet-style network.

**Protocol** (:class:`FeatureNetwork`). Training, evaluation, test-time adaptation and the CLI
call a feature network as ``net(inputs, basis, grad) -> features``:

- ``inputs (B, V, C_in)``: per-vertex input features (WKS or XYZ, see
  :class:`~torchfmap.nn.data.ShapeDataset`), zero on padded vertices;
- ``basis``: a :class:`~torchfmap.nn.functional.BasisBatch` ``(B, V, K_net)``, any
  B-orthonormal basis (for spectral diffusion; by default the Laplacian eigenbasis);
- ``grad``: a :class:`~torchfmap.nn.functional.GradientBatch`, the cached tangent-frame
  gradient operators (a network may ignore it);
- returns ``features (B, V, D)`` in the dtype and on the device of ``inputs``.

Any ``torch.nn.Module`` with that ``forward`` plugs in (see ``tests/test_nn_networks.py``).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from torch import nn

from ..errors import ParameterError
from . import functional as F
from .functional import BasisBatch, GradientBatch
from .modules import SpectralDiffusion


@runtime_checkable
class FeatureNetwork(Protocol):
    """``(inputs (B, V, C_in), basis BasisBatch, grad GradientBatch) -> features (B, V, D)``."""

    def __call__(self, inputs: torch.Tensor, basis: BasisBatch, grad: GradientBatch) -> torch.Tensor: ...


class SpatialGradientFeatures(nn.Module):
    """Learned rotation-invariant gradient features: ``(B, V, C) -> (B, V, C)``.

    Holds the complex mixing ``A = A_re + i A_im (C, C)`` and calls
    :func:`~torchfmap.nn.functional.spatial_gradient` and
    :func:`~torchfmap.nn.functional.gradient_features`.
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.A_re = nn.Parameter(torch.empty(channels, channels))
        self.A_im = nn.Parameter(torch.empty(channels, channels))
        for p in (self.A_re, self.A_im):
            nn.init.kaiming_uniform_(p, a=5**0.5)

    def forward(self, x: torch.Tensor, grad: GradientBatch) -> torch.Tensor:
        """``x (B, V, C) -> (B, V, C)``."""
        gx, gy = F.spatial_gradient(x, grad)
        return F.gradient_features(gx, gy, self.A_re, self.A_im)


class DiffusionNetBlock(nn.Module):
    """``x + MLP([x, diffuse(x), gradient_features(diffuse(x))])``, ``(B, V, C) -> (B, V, C)``."""

    def __init__(self, width: int, dropout: float = 0.5, gradients: bool = True) -> None:
        super().__init__()
        self.diffusion = SpectralDiffusion(width)
        self.gradient = SpatialGradientFeatures(width) if gradients else None
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
    """Reference feature network (DiffusionNet: learned diffusion, gradient features, MLPs).

    ``forward(inputs (B, V, C_in), basis, grad) -> (B, V, c_out)``: a linear lift to ``width``
    channels, ``n_blocks`` :class:`DiffusionNetBlock`, a linear head. With intrinsic inputs
    (WKS) the output is invariant to rigid motions of the mesh; the gradient features make it
    sensitive to reflections (left/right). ``gradients=False`` drops them (diffusion + MLPs).
    """

    def __init__(
        self,
        c_in: int,
        c_out: int = 64,
        width: int = 64,
        n_blocks: int = 4,
        dropout: float = 0.5,
        gradients: bool = True,
    ) -> None:
        super().__init__()
        if min(c_in, c_out, width, n_blocks) < 1 or not 0 <= dropout < 1:
            raise ParameterError(
                f"DiffusionNet needs c_in, c_out, width, n_blocks >= 1 and 0 <= dropout < 1; got "
                f"{c_in}, {c_out}, {width}, {n_blocks}, {dropout}."
            )
        self.lift = nn.Linear(c_in, width)
        self.blocks = nn.ModuleList(DiffusionNetBlock(width, dropout, gradients) for _ in range(n_blocks))
        self.head = nn.Linear(width, c_out)

    def forward(self, inputs: torch.Tensor, basis: BasisBatch, grad: GradientBatch) -> torch.Tensor:
        """``inputs (B, V, C_in)`` -> features ``(B, V, c_out)`` in ``inputs``' dtype; ``basis``
        a :class:`BasisBatch` (or a module with ``.batch()``), cast to that dtype."""
        basis = F.basis_like(basis, inputs)
        h = self.lift(inputs)
        for block in self.blocks:
            h = block(h, basis, grad)
        return self.head(h)
