"""The device names of the learned path: ``'cpu'``, ``'cuda'`` (``'cuda:N'``) or ``'auto'``."""

from __future__ import annotations

import torch

from ..errors import ParameterError

#: The device names :func:`resolve_device` accepts (``'cuda:N'`` too).
DEVICE_NAMES = ("auto", "cpu", "cuda")


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    """The ``torch.device`` of ``device`` (``'auto'`` or None: CUDA when available, else the CPU). Raises
    :class:`ParameterError`: an unknown name, or CUDA asked for where torch sees none (or not that many)."""
    if device is None or (isinstance(device, str) and device == "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError):
        raise ParameterError(
            f"unknown device {device!r}. Fix: one of {', '.join(DEVICE_NAMES)} (or 'cuda:N')."
        ) from None
    if resolved.type not in ("cpu", "cuda", "meta"):
        raise ParameterError(
            f"device {device!r} is not supported by torchfmap's learned path. Fix: one of "
            f"{', '.join(DEVICE_NAMES)}."
        )
    if resolved.type == "cuda":
        if not torch.cuda.is_available():
            raise ParameterError(
                f"device {device!r} asked for, but torch sees no CUDA device (torch "
                f"{torch.__version__}, built {'with' if torch.version.cuda else 'without'} CUDA). Fix: "
                "--device cpu (or 'auto': CUDA when available), or install a CUDA build of torch on a "
                "machine with a GPU."
            )
        if resolved.index is not None and resolved.index >= torch.cuda.device_count():
            raise ParameterError(
                f"device {device!r} asked for, but torch sees {torch.cuda.device_count()} CUDA "
                f"device(s). Fix: cuda:0 .. cuda:{torch.cuda.device_count() - 1}, or 'cuda'."
            )
    return resolved
