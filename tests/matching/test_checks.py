"""Checks of match's arguments (``torchfmap.matching.checks``): given bases of meshes of different
sizes, as ``torchfmap basis SRC TGT --landmarks`` writes them for any real pair."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import Mesh, ParameterError, match, prepare_shape
from torchfmap.matching.checks import check_meshes
from torchfmap.matching.solve import match_bases
from torchfmap.seeds import farthest_point_sampling

from ..conftest import bumpy_blob


def test_given_bases_of_meshes_of_different_sizes_solve_and_refine():
    """The pair (642 and 162 vertices) built together at corresponding landmarks, given back to
    match: solved in them (no comparison of per-vertex arrays of different lengths)."""
    x, y = bumpy_blob(3), bumpy_blob(2)  # one shape at two resolutions: vertex i of y is vertex i of x
    lm_y = farthest_point_sampling(y, 6)
    landmarks = np.stack([lm_y, lm_y], axis=1)
    sx, sy = prepare_shape(x, 0), prepare_shape(y, 0)
    bx, by, _ = match_bases(sx, sy, "diffusion", 12, landmarks)
    result = match(x, y, bases=(bx, by), refine="icp")
    assert result.p2p_yx.shape == (y.n_vertices,) and result.kind == "diffusion"
    assert result.p2p_yx.max() < x.n_vertices


def test_what_is_not_a_mesh_is_named_with_how_to_make_one(tmp_path):
    x = bumpy_blob(1)
    with pytest.raises(ParameterError, match=r"mesh_x is a str, not a torchfmap Mesh.*load_mesh\('a.off'\)"):
        match("a.off", x)
    with pytest.raises(ParameterError, match=r"mesh_y is a PosixPath.*load_mesh"):
        check_meshes(x, tmp_path / "b.off")
    soup = type("Trimeshish", (), {"vertices": x.vertices, "faces": x.faces})()
    with pytest.raises(ParameterError, match=r"Mesh\(m.vertices, m.faces\)"):
        check_meshes(soup, x)
    with pytest.raises(ParameterError, match=r"is a ndarray.*Mesh\(vertices \(V, 3\), faces"):
        check_meshes(x.vertices, x)
    check_meshes(x, Mesh(x.vertices, x.faces))  # meshes pass


def _cut(mesh: Mesh, axis: int = 2) -> Mesh:
    """The faces of ``mesh`` above the plane through its centroid (a part, vertices re-indexed)."""
    keep = mesh.vertices[mesh.faces].mean(axis=1)[:, axis] > mesh.vertices[:, axis].mean()
    part, _ = Mesh(mesh.vertices, mesh.faces[keep], allow_unreferenced=True).referenced()
    return part


def test_a_part_matched_to_a_whole_shape_is_warned_with_the_fix():
    import warnings

    from torchfmap.errors import MapWarning
    from torchfmap.matching.checks import boundary_length, warn_if_partial

    whole, part = bumpy_blob(2), _cut(bumpy_blob(2))
    assert boundary_length(whole) == 0 and boundary_length(part) > 1.0
    assert boundary_length(part.scaled(30.0)) == pytest.approx(boundary_length(part))  # scale-free
    with pytest.warns(MapWarning, match=r"mesh_y looks partial: its boundary is .* ratio 0\.\d+.*landmarks"):
        match(whole, part, k=8)
    with pytest.warns(MapWarning, match="mesh_x looks partial"):
        warn_if_partial(part, whole)
    with warnings.catch_warnings():
        warnings.simplefilter("error", MapWarning)
        warn_if_partial(whole, whole.scaled(3.0))  # whole shapes, any units: no word
        warn_if_partial(part, _cut(bumpy_blob(2), axis=1))  # two parts: no word either
