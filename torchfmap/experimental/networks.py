"""Feature networks kept as baselines of experiments, outside the core learned path.

:class:`FeatureNet` is the first learned path's network (spectral diffusion and MLPs, no
gradient features; ``python -m bench speed --case train_recipe`` compares it with the recipe's
:class:`~torchfmap.nn.networks.DiffusionNet`). It follows the
:class:`~torchfmap.nn.networks.FeatureNetwork` protocol, so training, checkpoints and
:class:`~torchfmap.nn.LearnedMatcher` take it as any user network.
"""

from __future__ import annotations

import torch
from torch import nn

from .._util.torch_checks import check_finite, resolve_check
from ..nn import functional as F
from ..nn.functional import BasisBatch, GradientBatch
from ..nn.modules import SpectralDiffusion


class FeatureNet(nn.Module):
    """The first learned path's network (kept as a baseline: ``python -m bench speed --case
    train_recipe``): spectral
    diffusion in any basis and MLPs, no gradient features.

    ``forward(inputs (B, V, C_in), basis, grad=None) -> (B, V, C_out)`` (the
    :class:`FeatureNetwork` protocol; ``grad`` is ignored): a linear lift, ``n_blocks`` residual
    blocks of [learned spectral diffusion, MLP on (x, diffused x)], a linear head. ``check``:
    refuse non-finite inputs (a data check; None: on CPU inputs only). ``init_kwargs`` holds the
    constructor arguments.
    """

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
        """``inputs (B, V, C_in)`` -> features ``(B, V, C_out)`` in ``inputs``' dtype.

        Raises:
            ParameterError: with ``check``, non-finite inputs.
        """
        basis = F.basis_like(basis, inputs)
        if resolve_check(self.check, inputs):
            check_finite(inputs, "FeatureNet inputs", "check the precomputed inputs.")
        h = self.lift(inputs)
        for diffuse, mlp in zip(self.diffusions, self.mlps, strict=True):
            h = h + mlp(torch.cat([h, diffuse(h, basis)], dim=-1))
        return self.head(h)
