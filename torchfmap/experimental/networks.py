"""Feature networks kept as baselines, outside the core learned path: :class:`FeatureNet` (compared with
:class:`~torchfmap.nn.networks.DiffusionNet`; usable by :class:`~torchfmap.nn.LearnedMatcher`)."""

from __future__ import annotations

import torch
from torch import nn

from .._util.torch_checks import check_finite, resolve_check
from ..nn import functional as F
from ..nn.functional import BasisBatch, GradientBatch
from ..nn.modules import SpectralDiffusion


class FeatureNet(nn.Module):
    """A :class:`~torchfmap.nn.networks.FeatureNetwork` without gradient features: a linear lift, ``n_blocks``
    residual blocks of [spectral diffusion in any basis, MLP on (x, diffused x)], a linear head. ``check``:
    refuse non-finite inputs (None: on CPU inputs only)."""

    def __init__(
        self, c_in: int, c_out: int = 64, width: int = 64, n_blocks: int = 3, check: bool | None = None
    ) -> None:
        super().__init__()
        self.init_kwargs = dict(c_in=c_in, c_out=c_out, width=width, n_blocks=n_blocks, check=check)
        self.check = check
        self.lift = nn.Linear(c_in, width)
        self.diffusions = nn.ModuleList(SpectralDiffusion(width) for _ in range(n_blocks))
        self.mlps = nn.ModuleList(
            nn.Sequential(nn.Linear(2 * width, width), nn.ReLU(), nn.Linear(width, width))
            for _ in range(n_blocks)
        )
        self.head = nn.Linear(width, c_out)

    def forward(
        self, inputs: torch.Tensor, basis: BasisBatch, grad: GradientBatch | None = None
    ) -> torch.Tensor:
        """``inputs (B, V, C_in)`` -> ``(B, V, C_out)``; with ``check``, ParameterError for non-finite."""
        basis = F.basis_like(basis, inputs)
        if resolve_check(self.check, inputs):
            check_finite(inputs, "FeatureNet inputs", "check the precomputed inputs.")
        h = self.lift(inputs)
        for diffuse, mlp in zip(self.diffusions, self.mlps, strict=True):
            h = h + mlp(torch.cat([h, diffuse(h, basis)], dim=-1))
        return self.head(h)
