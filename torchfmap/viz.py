"""Pictures a person would rather look at than read: colour transfer of a map, PCK curves (PNG).

matplotlib is an optional dependency (``pip install torchfmap[plot]``); it is imported here
only, with the headless ``Agg`` backend.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .errors import TorchFmapError
from .mesh import Mesh


def _pyplot():
    try:
        import matplotlib
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise TorchFmapError("plots need matplotlib. Fix: pip install 'torchfmap[plot]'.") from err
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def position_colors(mesh: Mesh) -> np.ndarray:
    """``(V, 3)`` RGB in ``[0, 1]`` from normalised coordinates (a smooth, injective-ish code)."""
    v = mesh.vertices - mesh.vertices.min(axis=0)
    return v / np.maximum(v.max(axis=0), 1e-300)


def _draw(ax, mesh: Mesh, colors: np.ndarray, title: str) -> None:
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    tri = mesh.vertices[mesh.faces]
    face_colors = colors[mesh.faces].mean(axis=1)
    ax.add_collection3d(Poly3DCollection(tri, facecolors=face_colors, edgecolors="none"))
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    center, radius = (lo + hi) / 2, (hi - lo).max() / 2
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), center, strict=True):
        setter(c - radius, c + radius)
    ax.set_axis_off()
    ax.set_title(title)


def plot_color_transfer(mesh_x: Mesh, mesh_y: Mesh, p2p_yx: np.ndarray, path: str | os.PathLike) -> Path:
    """Colour ``x`` by position and carry the colours to ``y`` through ``p2p_yx``; save a PNG."""
    plt = _pyplot()
    colors = position_colors(mesh_x)
    fig = plt.figure(figsize=(10, 5))
    for i, (mesh, col, title) in enumerate(
        (
            (mesh_x, colors, f"source {mesh_x.name or ''}"),
            (mesh_y, colors[np.asarray(p2p_yx)], "target (mapped)"),
        )
    ):
        _draw(fig.add_subplot(1, 2, i + 1, projection="3d"), mesh, col, title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_pck(
    curves: dict[str, tuple[np.ndarray, np.ndarray]], path: str | os.PathLike, title: str = ""
) -> Path:
    """PCK curves ``{label: (thresholds, accuracy)}`` in one PNG."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4.5))
    for label, (thr, acc) in curves.items():
        ax.plot(thr, 100 * np.asarray(acc), label=label)
    ax.set_xlabel("geodesic error / sqrt(area)")
    ax.set_ylabel("% correspondences")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
