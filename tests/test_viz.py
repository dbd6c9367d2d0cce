"""Pictures and pages (``torchfmap.viz``): PNGs are written without touching the user's matplotlib
state; the up axis is a rotation (no mirror image); a self-contained HTML page that a real
headless browser (Chromium) draws; bad inputs are refused."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from torchfmap import ParameterError
from torchfmap.data import demo_pair, demo_pair_paths
from torchfmap.io import load_mesh
from torchfmap.viz import (
    HTML_DRAWN,
    HTML_ERROR,
    _z_up,
    plot_color_transfer,
    plot_errors,
    plot_pck,
    save_transfer_html,
)

from .conftest import requires_matplotlib, requires_plotly

PNG = b"\x89PNG\r\n\x1a\n"


@requires_matplotlib
def test_pictures_are_pngs_and_leave_pyplot_alone(tmp_path):
    import matplotlib

    backend = matplotlib.get_backend()
    had_pyplot = "matplotlib.pyplot" in sys.modules
    x, y, y_to_x = demo_pair()
    paths = [
        plot_color_transfer(x, y, y_to_x, tmp_path / "a.png", up="y"),
        plot_errors(y, np.linalg.norm(y.vertices, axis=1), tmp_path / "b.png", title="radius"),
        plot_pck({"all": (np.linspace(0, 0.25, 5), np.linspace(0, 1, 5))}, tmp_path / "c.png"),
    ]
    for path in paths:
        assert path.read_bytes()[:8] == PNG and path.stat().st_size > 1000
    assert matplotlib.get_backend() == backend
    assert ("matplotlib.pyplot" in sys.modules) == had_pyplot


@pytest.mark.parametrize("up", ["x", "y", "z"])
@requires_matplotlib
def test_up_axis_is_a_rotation_onto_z(up):
    """The permutation is cyclic (determinant +1): a left paw stays a left paw in the picture."""
    eye = np.eye(3)
    M = _z_up(eye, up)  # rows: the images of the unit vectors
    assert round(np.linalg.det(M)) == 1
    assert np.array_equal(_z_up(eye[None, "xyz".index(up)], up)[0], [0.0, 0.0, 1.0])


@requires_matplotlib
def test_bad_picture_inputs_are_refused(tmp_path):
    x, y, y_to_x = demo_pair()
    with pytest.raises(ParameterError, match="p2p_yx"):
        plot_color_transfer(x, y, y_to_x[:-1], tmp_path / "a.png")
    with pytest.raises(ParameterError, match="up must be"):
        plot_color_transfer(x, y, y_to_x, tmp_path / "a.png", up="w")
    with pytest.raises(ParameterError, match="finite"):
        plot_errors(y, np.full(y.n_vertices, np.nan), tmp_path / "b.png")


@pytest.fixture(scope="module")
def demo_page(tmp_path_factory):
    a, b, _ = demo_pair_paths()
    x, y = load_mesh(a), load_mesh(b)
    p2p = np.random.default_rng(0).integers(0, x.n_vertices, y.n_vertices)
    return save_transfer_html(x, y, p2p, tmp_path_factory.mktemp("html") / "map.html"), x, y


@requires_plotly
def test_the_page_is_self_contained(demo_page):
    text = demo_page[0].read_text(encoding="utf-8")
    assert re.search(r"<script[^>]*\bsrc=", text) is None  # no script fetched at view time
    assert "Plotly.newPlot" in text and HTML_DRAWN in text


@requires_plotly
def test_bad_maps_are_refused(demo_page, tmp_path):
    _, x, y = demo_page
    with pytest.raises(ParameterError, match="integers"):
        save_transfer_html(x, y, np.zeros(3, dtype=int), tmp_path / "a.html")
    with pytest.raises(ParameterError, match="outside"):
        save_transfer_html(x, y, np.full(y.n_vertices, x.n_vertices), tmp_path / "a.html")
    with pytest.raises(ParameterError, match="up must be"):
        save_transfer_html(x, y, np.zeros(y.n_vertices, dtype=int), tmp_path / "a.html", up="w")
    assert not (tmp_path / "a.html").exists()


CHROMIUM = next(
    (shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None
)


#: Chromium with software WebGL (no GPU, no sandbox in containers), a fixed window and time.
FLAGS = [
    "--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--window-size=1000,500", "--virtual-time-budget=8000",
]  # fmt: skip


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium (Debian: apt install chromium)")
@requires_plotly
def test_chromium_loads_the_page_and_draws_both_meshes(demo_page, tmp_path):
    page = demo_page[0]
    dom = subprocess.run(
        [CHROMIUM, *FLAGS, "--dump-dom", page.as_uri()], capture_output=True, text=True, timeout=120
    ).stdout
    assert f'{HTML_DRAWN}="2"' in dom, "plotly did not draw the two meshes"
    assert HTML_ERROR + '="' not in dom, "a script error was raised on the page"
    shot = tmp_path / "shot.png"
    subprocess.run(
        [CHROMIUM, *FLAGS, f"--screenshot={shot}", page.as_uri()], capture_output=True, timeout=120
    )
    from matplotlib.image import imread

    rgb = imread(shot)[..., :3]
    coloured = (rgb.max(axis=-1) - rgb.min(axis=-1)) > 0.15  # a mesh's colours, not white or grey
    half = rgb.shape[1] // 2
    # each mesh fills a visible part of its half of the window (a blank page has no such pixels)
    assert coloured[:, :half].mean() > 0.01 and coloured[:, half:].mean() > 0.01
