"""Shipped pretrained models (``torchfmap/nn/models/*.ckpt``), taken by name for a checkpoint path."""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import ParameterError

#: Folder of the shipped checkpoints.
MODELS_DIR = Path(__file__).parent / "models"


def shipped_models() -> dict[str, Path]:
    """Shipped model name -> checkpoint path, sorted by name."""
    return {p.name.removesuffix(".ckpt"): p for p in sorted(MODELS_DIR.glob("*.ckpt"))}


def resolve_checkpoint(spec: str | os.PathLike) -> Path:
    """The checkpoint file of ``spec``: an existing path, else a shipped model's name. Raises
    :class:`ParameterError`: neither (the shipped names are listed)."""
    path = Path(spec)
    if path.is_file():
        return path
    shipped = shipped_models()
    if str(spec) in shipped:
        return shipped[str(spec)]
    names = ", ".join(shipped) or "none"
    raise ParameterError(
        f"no checkpoint file {str(spec)!r} and no shipped model of that name (shipped: {names}). Fix: "
        "pass the path of a file written by `torchfmap train`, or a shipped name (`torchfmap models`)."
    )
