"""Which torch device the learned path runs on: the one reading of ``device=`` / ``--device``.

Operators and eigenbases stay float64 on the CPU (as they are prepared); the network, the
functional-map solver and the point-map search run on the device this resolves.
"""

from __future__ import annotations

import torch

from ..errors import ParameterError


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    """The :class:`torch.device` of ``device``: ``'auto'`` (or None) is CUDA when available,
    else the CPU; ``'cpu'``, ``'cuda'``, ``'cuda:N'`` or a :class:`torch.device` as given.

    Raises:
        ParameterError: an unknown device name, or CUDA asked for where torch has none (the
            message names the fix: ``cpu`` or ``auto``).
    """
    if device is None or (isinstance(device, str) and device == "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError):
        raise ParameterError(
            f"unknown device {device!r}. Fix: 'cpu', 'cuda', 'cuda:N' or 'auto'."
        ) from None
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise ParameterError(
            f"device {device!r} asked for, but torch sees no CUDA device here. Fix: device 'cpu' "
            "(or 'auto', which takes CUDA only where there is one)."
        )
    return resolved
