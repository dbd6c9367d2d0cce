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

Any ``torch.nn.Module`` with that ``forward`` plugs in (see ``tests/nn/test_networks.py``);
the code that takes networks refuses other objects (:func:`check_network`) and outputs of
another shape, dtype or device (:func:`features`).

**Checkpoints** record the network's class (``module:qualname``) and its constructor
arguments, so :func:`~torchfmap.nn.checkpoints.load_checkpoint` can rebuild it. A network gives
its arguments as an ``init_kwargs`` dict attribute (plain values only: numbers, strings, bools,
None, lists, tuples and dicts of those), as :class:`DiffusionNet` does,
or the caller passes ``net_kwargs`` to :func:`~torchfmap.nn.checkpoints.save_checkpoint`.
"""

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
    """``(inputs (B, V, C_in), basis BasisBatch, grad GradientBatch) -> features (B, V, D)``.

    A static type only; :func:`check_network` is the runtime check.
    """

    def __call__(self, inputs: torch.Tensor, basis: BasisBatch, grad: GradientBatch) -> torch.Tensor: ...


def check_network(net) -> None:
    """Refuse an object that cannot be a :class:`FeatureNetwork`: not a ``torch.nn.Module``, or
    whose ``forward`` does not take ``(inputs, basis, grad)``.

    Raises:
        ParameterError: naming what is wrong.
    """
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
    """The network's features of a :class:`~torchfmap.nn.data.ShapeBatch`: ``(B, V, D)``.

    Calls ``net(shape.inputs, shape.net_basis, shape.grad)``.

    Raises:
        ParameterError: the output is not a ``(B, V, D)`` tensor in the dtype and on the device
            of ``shape.inputs``.
    """
    out = net(shape.inputs, shape.net_basis, shape.grad)
    inputs = shape.inputs
    if (
        not isinstance(out, torch.Tensor)
        or out.dim() != 3
        or out.shape[:2] != inputs.shape[:2]
        or out.dtype != inputs.dtype
        or out.device != inputs.device
    ):
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
    """Learned rotation-invariant gradient features: ``(B, V, C) -> (B, V, C)``.

    Holds the complex mixing ``A = A_re + i A_im (C, C)`` and the ``check`` setting and calls
    :func:`~torchfmap.nn.functional.spatial_gradient` and
    :func:`~torchfmap.nn.functional.gradient_features`.
    """

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
    """Reference feature network (DiffusionNet: learned diffusion, gradient features, MLPs).

    ``forward(inputs (B, V, C_in), basis, grad) -> (B, V, c_out)``: a linear lift to ``width``
    channels, ``n_blocks`` :class:`DiffusionNetBlock`, a linear head. With intrinsic inputs
    (WKS) the output is invariant to rigid motions of the mesh; the gradient features make it
    sensitive to reflections (left/right). ``gradients=False`` drops them (diffusion + MLPs).
    ``check``: the data checks of the gradient operators (None: on CPU inputs only).
    ``init_kwargs`` holds the constructor arguments (recorded in checkpoints).
    """

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
        self.init_kwargs = dict(
            c_in=c_in,
            c_out=c_out,
            width=width,
            n_blocks=n_blocks,
            dropout=dropout,
            gradients=gradients,
            check=check,
        )
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
        """``inputs (B, V, C_in)`` -> features ``(B, V, c_out)`` in ``inputs``' dtype; ``basis``
        a :class:`BasisBatch` (or a module with ``.batch()``), cast to that dtype.

        Raises:
            ParameterError: with the data check (``check``; None: CPU inputs), non-finite inputs.
        """
        if resolve_check(self.check, inputs):
            check_finite(inputs, "DiffusionNet inputs", "check the precomputed inputs (WKS, XYZ).")
        basis = F.basis_like(basis, inputs)
        h = self.lift(inputs)
        for block in self.blocks:
            h = block(h, basis, grad)
        return self.head(h)
