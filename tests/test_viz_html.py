"""``save_transfer_html`` and ``torchfmap match --html``: a self-contained page (no network at
view time) that a real headless browser (Chromium) loads without script errors and draws both
meshes on (a screenshot that is not blank, coloured on both halves)."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest

from torchfmap import ParameterError
from torchfmap.cli import main
from torchfmap.data import demo_pair_paths
from torchfmap.io import load_mesh

pytest.importorskip("plotly")
from torchfmap.viz import HTML_DRAWN, HTML_ERROR, save_transfer_html  # noqa: E402

CHROMIUM = next(
    (shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None
)
#: Chromium with software WebGL (no GPU, no sandbox in containers), a fixed window and time.
FLAGS = [
    "--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--window-size=1000,500", "--virtual-time-budget=8000",
]  # fmt: skip


@pytest.fixture(scope="module")
def demo_page(tmp_path_factory):
    a, b, _ = demo_pair_paths()
    x, y = load_mesh(a), load_mesh(b)
    p2p = np.random.default_rng(0).integers(0, x.n_vertices, y.n_vertices)
    return save_transfer_html(x, y, p2p, tmp_path_factory.mktemp("html") / "map.html"), x, y


def test_the_page_is_self_contained(demo_page):
    text = demo_page[0].read_text(encoding="utf-8")
    assert re.search(r"<script[^>]*\bsrc=", text) is None  # no script fetched at view time
    assert "Plotly.newPlot" in text and HTML_DRAWN in text


def test_bad_maps_are_refused(demo_page, tmp_path):
    _, x, y = demo_page
    with pytest.raises(ParameterError, match="integers"):
        save_transfer_html(x, y, np.zeros(3, dtype=int), tmp_path / "a.html")
    with pytest.raises(ParameterError, match="outside"):
        save_transfer_html(x, y, np.full(y.n_vertices, x.n_vertices), tmp_path / "a.html")
    with pytest.raises(ParameterError, match="up must be"):
        save_transfer_html(x, y, np.zeros(y.n_vertices, dtype=int), tmp_path / "a.html", up="w")
    assert not (tmp_path / "a.html").exists()


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium (Debian: apt install chromium)")
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


def test_match_html_writes_the_page(tmp_path, capsys):
    a, b, _ = demo_pair_paths()
    out, html = tmp_path / "map.txt", tmp_path / "map.html"
    assert main(["match", str(a), str(b), "--out", str(out), "--html", str(html)]) == 0
    assert "browser page" in capsys.readouterr().out and html.stat().st_size > 0
    assert main(["match", str(a), str(b), "--out", str(out), "--html", str(tmp_path / "no" / "m.html")]) == 2
    assert "--html" in capsys.readouterr().err
