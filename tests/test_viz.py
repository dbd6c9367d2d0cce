"""Pictures: PNGs are written without touching the user's matplotlib state; the up axis is a
rotation (no mirror image); bad inputs are refused."""

from __future__ import annotations

import sys

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from torchfmap import ParameterError  # noqa: E402
from torchfmap.data import demo_pair  # noqa: E402
from torchfmap.viz import _z_up, plot_color_transfer, plot_errors, plot_pck  # noqa: E402

PNG = b"\x89PNG\r\n\x1a\n"


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
def test_up_axis_is_a_rotation_onto_z(up):
    """The permutation is cyclic (determinant +1): a left paw stays a left paw in the picture."""
    eye = np.eye(3)
    M = _z_up(eye, up)  # rows: the images of the unit vectors
    assert round(np.linalg.det(M)) == 1
    assert np.array_equal(_z_up(eye[None, "xyz".index(up)], up)[0], [0.0, 0.0, 1.0])


def test_bad_picture_inputs_are_refused(tmp_path):
    x, y, y_to_x = demo_pair()
    with pytest.raises(ParameterError, match="p2p_yx"):
        plot_color_transfer(x, y, y_to_x[:-1], tmp_path / "a.png")
    with pytest.raises(ParameterError, match="up must be"):
        plot_color_transfer(x, y, y_to_x, tmp_path / "a.png", up="w")
    with pytest.raises(ParameterError, match="finite"):
        plot_errors(y, np.full(y.n_vertices, np.nan), tmp_path / "b.png")
