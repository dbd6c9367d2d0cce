"""Mesh validation (``torchfmap.mesh_checks.validate_mesh``): the report, degenerate faces, holes
reported not raised."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import MeshError, validate_mesh

from .conftest import TET_F, TET_V


def test_valid_tetrahedron_report():
    rep = validate_mesh(TET_V, TET_F)
    assert (rep.n_vertices, rep.n_faces, rep.n_components) == (4, 4, 1)
    assert rep.is_closed and rep.n_boundary_loops == 0
    assert rep.euler_characteristic == 2


def test_degenerate_zero_area_face():
    v = np.vstack([TET_V, [0.5, 0.5, 0.0]])  # vertex 4 on the edge 1-2
    f = np.vstack([TET_F, [1, 2, 4]])
    with pytest.raises(MeshError, match=r"1 degenerate faces .*faces \[4\]"):
        validate_mesh(v, f, allow_nonmanifold=True)


def test_holes_reported_not_raised(sphere2):
    # remove the faces around vertex 0: one hole
    ring = np.flatnonzero((sphere2.faces == 0).any(axis=1))
    holed = sphere2.without_faces(ring)
    rep = validate_mesh(holed.vertices, holed.faces, allow_unreferenced=True)
    assert rep.n_boundary_loops == 1 and not rep.is_closed
    assert rep.n_boundary_edges == len(ring)
    # two separate holes
    far = int(np.argmin(sphere2.vertices @ sphere2.vertices[0]))
    ring2 = np.flatnonzero((sphere2.faces == far).any(axis=1))
    rep2 = sphere2.without_faces(np.concatenate([ring, ring2])).report
    assert rep2.n_boundary_loops == 2
