"""Pretrained models shipped in the package (``torchfmap/nn/models/*.ckpt``), resolved by name.

``torchfmap match --checkpoint faust_r``, ``torchfmap eval --checkpoint``,
:meth:`~torchfmap.nn.LearnedMatcher.from_checkpoint` and
:func:`~torchfmap.nn.checkpoints.load_checkpoint` take a shipped name wherever they take a path; a file of
that name in the working directory wins over the shipped model. Each shipped checkpoint holds
its ``provenance`` (command, data, commit, validation score); ``torchfmap models`` lists them.
Nothing is downloaded: the files are in the package.
"""

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
    """The checkpoint file of ``spec``: an existing path, else a shipped model's name.

    Raises:
        ParameterError: neither an existing file nor a shipped name (the names are listed).
    """
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
