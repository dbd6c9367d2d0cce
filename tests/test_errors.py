"""The error hierarchy (``torchfmap.errors``)."""

from __future__ import annotations

import pytest

from torchfmap import (
    ConvergenceError,
    MeshError,
    MeshReport,
    MeshWarning,
    ParameterError,
    SeedError,
    TorchFmapError,
    validate_mesh,
)
from torchfmap.operators import check_vertex_indices


def test_error_hierarchy_and_mesh_report(sphere2):
    for cls in (MeshError, SeedError, ParameterError, ConvergenceError):
        assert issubclass(cls, TorchFmapError) and issubclass(cls, ValueError)
    assert issubclass(MeshWarning, UserWarning) and not issubclass(MeshWarning, TorchFmapError)
    with pytest.raises(TorchFmapError):
        check_vertex_indices([9], 5)
    report = validate_mesh(sphere2.vertices, sphere2.faces)
    assert isinstance(report, MeshReport)
    assert (report.n_vertices, report.n_faces) == (162, 320)
    assert report.n_components == 1 and report.n_boundary_edges == 0 and report.euler_characteristic == 2
