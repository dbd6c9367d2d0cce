"""Pictures: colour transfer of a map, per-vertex errors, PCK curves (PNG; optional matplotlib, pyplot
untouched), a map to turn in a browser (:func:`save_transfer_html`, plotly); ``up``: the vertical axis."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import numpy as np

from ._util.checks import check_p2p
from ._util.files import atomic_write
from .errors import ParameterError, TorchFmapError
from .mesh import Mesh

Axis = Literal["x", "y", "z"]
#: Azimuths (degrees) of the two viewpoints: three-quarter front and three-quarter back.
VIEWS = (-60.0, 120.0)


def _figure(width: float, height: float):
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise TorchFmapError("plots need matplotlib. Fix: pip install 'torchfmap[plot]'.") from err
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: str | os.PathLike) -> Path:
    path = Path(path)
    fig.savefig(path, dpi=110)
    return path


def position_colors(mesh: Mesh) -> np.ndarray:
    """``(V, 3)`` RGB in ``[0, 1]`` from normalised coordinates."""
    v = mesh.vertices - mesh.vertices.min(axis=0)
    return v / np.maximum(v.max(axis=0), 1e-300)


def _z_up(vertices: np.ndarray, up: Axis) -> np.ndarray:
    """Coordinates permuted (a rotation) so that axis ``up`` becomes z."""
    order = {"x": (1, 2, 0), "y": (2, 0, 1), "z": (0, 1, 2)}
    if up not in order:
        raise ParameterError(f"up must be 'x', 'y' or 'z', got {up!r}.")
    return vertices[:, order[up]]


def _draw(ax, mesh: Mesh, face_colors: np.ndarray, title: str, up: Axis, azimuth: float) -> None:
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    v = _z_up(mesh.vertices, up)
    ax.add_collection3d(Poly3DCollection(v[mesh.faces], facecolors=face_colors, edgecolors="none"))
    lo, hi = v.min(axis=0), v.max(axis=0)
    for setter, a, b in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), lo, hi, strict=True):
        setter(a, b)
    ax.set_box_aspect(np.maximum(hi - lo, 1e-12 * (hi - lo).max()))  # true proportions, tight frame
    ax.view_init(elev=15.0, azim=azimuth)
    ax.set_axis_off()
    ax.set_title(title, fontsize=9)


def plot_color_transfer(
    mesh_x: Mesh, mesh_y: Mesh, p2p_yx: np.ndarray, path: str | os.PathLike, *, up: Axis = "z"
) -> Path:
    """Save a PNG of ``x`` coloured by position and ``y`` coloured through ``p2p_yx`` ``(V_y,)``."""
    p2p_yx = np.asarray(p2p_yx)
    if p2p_yx.shape != (mesh_y.n_vertices,):
        raise ParameterError(f"p2p_yx must have shape ({mesh_y.n_vertices},), got {p2p_yx.shape}.")
    colors = position_colors(mesh_x)
    fig = _figure(9, 8)
    rows = (
        (mesh_x, colors, f"source {mesh_x.name or 'x'}"),
        (mesh_y, colors[p2p_yx], f"target {mesh_y.name or 'y'}, colours carried by the map"),
    )
    for r, (mesh, col, title) in enumerate(rows):
        face = np.clip(col[mesh.faces].mean(axis=1), 0.0, 1.0)
        for c, azimuth in enumerate(VIEWS):
            ax = fig.add_subplot(2, 2, 2 * r + c + 1, projection="3d")
            _draw(ax, mesh, face, title if c == 0 else "(other side)", up, azimuth)
    return _save(fig, path)


def plot_errors(
    mesh: Mesh, errors: np.ndarray, path: str | os.PathLike, *, up: Axis = "z", title: str = ""
) -> Path:
    """Save a PNG of per-vertex ``errors`` ``(V,)`` drawn on ``mesh``, with a colour bar."""
    errors = np.asarray(errors, dtype=np.float64)
    if errors.shape != (mesh.n_vertices,) or not np.isfinite(errors).all():
        raise ParameterError(f"errors must be ({mesh.n_vertices},) finite values, got shape {errors.shape}.")
    fig = _figure(9, 4.5)  # first: without matplotlib this is the clear error
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    norm = Normalize(0.0, max(float(np.percentile(errors, 99)), 1e-12))
    cmap = colormaps["magma_r"]
    face = cmap(norm(errors[mesh.faces].mean(axis=1)))[:, :3]
    axes = [fig.add_subplot(1, 2, c + 1, projection="3d") for c in range(2)]
    for ax, azimuth, label in zip(axes, VIEWS, (title or mesh.name or "errors", "(other side)"), strict=True):
        _draw(ax, mesh, face, label, up, azimuth)
    fig.colorbar(ScalarMappable(norm, cmap), ax=axes, shrink=0.7, label="error (99th percentile at the top)")
    return _save(fig, path)


def plot_pck(
    curves: dict[str, tuple[np.ndarray, np.ndarray]], path: str | os.PathLike, title: str = ""
) -> Path:
    """PCK curves ``{label: (thresholds, accuracy)}`` in one PNG."""
    fig = _figure(6, 4.5)
    ax = fig.add_subplot(1, 1, 1)
    for label, (thr, acc) in curves.items():
        ax.plot(thr, 100 * np.asarray(acc), label=label)
    ax.set(xlabel="geodesic error / sqrt(area)", ylabel="% correspondences", ylim=(0, 100), title=title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


#: Attributes a :func:`save_transfer_html` page sets on ``<body>``: meshes drawn, and a script error.
HTML_DRAWN, HTML_ERROR = "data-torchfmap-drawn", "data-torchfmap-error"


def _mesh_trace(go, mesh: Mesh, colors: np.ndarray, scene: str, name: str):
    v, f = mesh.vertices, mesh.faces
    rgb = np.round(255 * np.clip(colors, 0.0, 1.0)).astype(int)
    return go.Mesh3d(
        x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2],
        vertexcolor=[f"rgb({r},{g},{b})" for r, g, b in rgb], flatshading=False, name=name,
        hoverinfo="name", scene=scene, lighting=dict(ambient=0.6, diffuse=0.6, specular=0.1),
    )  # fmt: skip


def save_transfer_html(
    mesh_x: Mesh, mesh_y: Mesh, p2p_yx: np.ndarray, path: str | os.PathLike, *, up: Axis = "z"
) -> Path:
    """:func:`plot_color_transfer` (``p2p_yx (V_y,)``) as a self-contained, rotatable HTML page written
    atomically; returns the path. Raises :class:`TorchFmapError` without plotly, :class:`ParameterError`
    for a bad ``p2p_yx`` or ``up``."""
    p2p_yx = check_p2p(p2p_yx, mesh_y.n_vertices, mesh_x.n_vertices, "p2p_yx")
    if up not in ("x", "y", "z"):
        raise ParameterError(f"up must be 'x', 'y' or 'z', got {up!r}.")
    try:
        import plotly.graph_objects as go
        from plotly.subplots import make_subplots
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise TorchFmapError(
            "--html / save_transfer_html need plotly. Fix: pip install 'torchfmap[html]'."
        ) from err
    colors = position_colors(mesh_x)
    names = (f"source {mesh_x.name or 'x'}", f"target {mesh_y.name or 'y'}: colours carried by the map")
    fig = make_subplots(rows=1, cols=2, specs=[[{"type": "scene"}, {"type": "scene"}]], subplot_titles=names)
    fig.add_trace(_mesh_trace(go, mesh_x, colors, "scene", names[0]), row=1, col=1)
    fig.add_trace(_mesh_trace(go, mesh_y, colors[p2p_yx], "scene2", names[1]), row=1, col=2)
    camera = dict(up={a: float(a == up) for a in "xyz"}, eye=dict(x=1.6, y=1.6, z=1.6))
    axis = dict(visible=False)
    for scene in ("scene", "scene2"):
        fig.layout[scene].update(aspectmode="data", camera=camera, xaxis=axis, yaxis=axis, zaxis=axis)
    fig.update_layout(margin=dict(l=0, r=0, t=40, b=0), showlegend=False)
    marker = (
        f"window.addEventListener('error', e => document.body.setAttribute('{HTML_ERROR}', e.message));"
        f"document.body.setAttribute('{HTML_DRAWN}', String(document.getElementById('{{plot_id}}')"
        "._fullData.length));"
    )
    html = fig.to_html(include_plotlyjs=True, full_html=True, post_script=marker, default_height="95vh")
    return atomic_write(path, lambda fh: fh.write(html.encode("utf-8")))
