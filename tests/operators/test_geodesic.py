"""Geodesic distances (``torchfmap.operators.geodesic``): heat-method distances on the sphere, bad
sources, components, cached distance rows."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import GeodesicSolver, ParameterError, SeedError, geodesic_distances
from torchfmap.data import icosphere
from torchfmap.operators import geodesic

from ..conftest import bumpy_blob


def test_heat_geodesics_on_sphere(sphere4):
    solver = GeodesicSolver(sphere4)
    exact = np.arccos(np.clip(sphere4.vertices @ sphere4.vertices[0], -1, 1))
    d = solver.distance(0)
    assert d[0] == pytest.approx(0.0, abs=1e-6)
    assert np.abs(d - exact).max() < 0.03 * np.pi
    rows = solver.distances([0, 10, 20])
    assert rows.shape == (3, sphere4.n_vertices) and np.allclose(rows[0], d)
    nearest = solver.distance_to_set([0, 10, 20])
    assert np.abs(nearest - rows.min(axis=0)).max() < 0.03 * np.pi


def test_distance_matrix_small_and_guard(sphere4, monkeypatch):
    small = icosphere(1)
    D = GeodesicSolver(small).distance_matrix()
    assert D.shape == (42, 42) and np.allclose(D, D.T) and np.allclose(np.diag(D), 0, atol=1e-6)
    monkeypatch.setattr(geodesic, "FULL_MATRIX_LIMIT", 100)
    with pytest.raises(ParameterError, match=r"full distance matrix .* `distances\(rows\)`"):
        GeodesicSolver(sphere4).distance_matrix()


def test_geodesic_bad_sources(sphere4):
    solver = GeodesicSolver(icosphere(1))
    with pytest.raises(SeedError, match="out of range"):
        solver.distance(42)
    with pytest.raises(SeedError, match="duplicates"):
        solver.distances([1, 2, 1])
    with pytest.raises(SeedError, match="empty"):
        solver.distances([])
    with pytest.raises(SeedError, match="integer"):
        solver.distances([0.5])


def test_geodesic_distances_on_sphere(sphere3):
    """Unit sphere: d(p, q) = arccos(p·q). Heat method with t = h² is first order: error ≤ h_max
    (distances ≤ π, constant O(1))."""
    v = sphere3.vertices
    src = np.array([0, 100, 400])
    D = geodesic_distances(sphere3, src)
    assert D.shape == (3, sphere3.n_vertices)
    exact = np.arccos(np.clip(v[src] @ v.T, -1, 1))
    assert np.abs(D - exact).max() <= sphere3.edge_lengths.max()
    np.testing.assert_allclose(D[np.arange(3), src], 0.0, atol=1e-12)


def test_geodesic_distance_between_components_is_infinite():
    """No path joins two components: their distance is inf (it was a finite constant, on which
    errors and farthest-point seeds were silently built); FPS then seeds every component."""
    from torchfmap import GeodesicSolver, Mesh, farthest_point_sampling

    a = icosphere(1)
    b = a.copy(a.vertices + 5.0)
    two = Mesh(
        np.vstack([a.vertices, b.vertices]),
        np.vstack([a.faces, b.faces + a.n_vertices]),
        allow_components=True,
    )
    d = GeodesicSolver(two).distance(0)
    assert np.isinf(d[a.n_vertices :]).all() and np.isfinite(d[: a.n_vertices]).all()
    seeds = farthest_point_sampling(two, 2)
    assert len(set(two.component_labels[seeds].tolist())) == 2


def test_distance_rows_are_cached_and_in_sqrt_area_units():
    """Rows are geodesic distances divided by sqrt(area) (so a scaled copy gives the same
    rows), computed once per source."""
    from torchfmap.operators import DistanceRows

    x = bumpy_blob(3)
    rows, scaled = DistanceRows(x, normalized=True), DistanceRows(x.scaled(7.0), normalized=True)
    solved = []
    inner = rows.solver.distances
    rows.solver.distances = lambda sources: solved.extend(sources) or inner(sources)
    a = rows(5)
    np.testing.assert_array_equal(rows(5), a)
    assert solved == [5] and a[5] == 0 and (a >= 0).all()
    np.testing.assert_allclose(scaled.distances([5, 9]), rows.distances([5, 9]), rtol=1e-6, atol=1e-9)
    assert solved == [5, 9]


def test_distance_rows_budget_keeps_the_first_rows_and_equals_the_solver():
    """Unnormalised rows equal the solver's bit for bit; with a budget of two rows the third
    is solved on every request and the first two never again; a negative budget is refused."""
    from torchfmap import ParameterError
    from torchfmap.operators import DistanceRows, GeodesicSolver

    x = bumpy_blob(2)
    solver = GeodesicSolver(x)
    rows = DistanceRows(x, solver, max_bytes=2 * 8 * x.n_vertices)
    solved = []
    inner = solver.distances
    solver.distances = lambda sources: solved.extend(sources) or inner(sources)
    first = rows.distances([3, 7, 11])
    assert solved == [3, 7, 11]
    np.testing.assert_array_equal(first, inner([3, 7, 11]))
    np.testing.assert_array_equal(rows.distances([11, 7, 3]), first[[2, 1, 0]])
    assert solved == [3, 7, 11, 11]
    with pytest.raises(ParameterError, match="max_bytes"):
        DistanceRows(x, max_bytes=-1)
