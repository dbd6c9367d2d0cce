"""Approximate geodesic distances with the heat method (potpourri3d): a solver prefactored once per
mesh (:class:`GeodesicSolver`), a cache of its rows (:class:`DistanceRows`) and a one-shot function."""

from __future__ import annotations

import numpy as np
import potpourri3d as pp3d

from .._util.checks import check_vertex_indices
from ..errors import ParameterError
from ..mesh import Mesh

#: Largest mesh for which :meth:`GeodesicSolver.distance_matrix` runs without ``force=True``.
FULL_MATRIX_LIMIT = 7000


class GeodesicSolver:
    """Heat-method geodesic distances (float64) on one mesh; build once, query many times.

    Vertices on another component than the source, and unreferenced ones, are at ``inf``.
    ``t_coef``: heat-method time step factor; ``use_robust``: intrinsic-Delaunay operators.
    Raises :class:`ParameterError` for ``t_coef <= 0``.
    """

    def __init__(self, mesh: Mesh, t_coef: float = 1.0, use_robust: bool = True) -> None:
        if t_coef <= 0:
            raise ParameterError(f"t_coef must be positive, got {t_coef}.")
        self.mesh = mesh
        self._solver = pp3d.MeshHeatMethodDistanceSolver(
            mesh.vertices, mesh.faces, t_coef=t_coef, use_robust=use_robust
        )
        labels = mesh.component_labels.copy()
        labels[np.setdiff1d(np.arange(mesh.n_vertices), np.unique(mesh.faces))] = -1
        self._labels = labels
        self._single = mesh.n_components == 1 and labels.min() >= 0

    def _cut(self, d: np.ndarray, sources: np.ndarray) -> np.ndarray:
        """``inf`` where no source's component reaches."""
        if not self._single:
            d[~np.isin(self._labels, self._labels[sources]) | (self._labels < 0)] = np.inf
        return d

    def distance(self, source: int) -> np.ndarray:
        """``(V,)`` geodesic distance from one vertex."""
        return self.distances([source])[0]

    def distance_to_set(self, sources) -> np.ndarray:
        """``(V,)`` distance to the nearest of several sources (one solve, not a minimum)."""
        s = check_vertex_indices(sources, self.mesh.n_vertices)
        d = np.asarray(self._solver.compute_distance_multisource(s.tolist()), dtype=np.float64)
        return self._cut(d, s)

    def distances(self, sources) -> np.ndarray:
        """``(S, V)``: row ``r`` holds distances from ``sources[r]``."""
        s = check_vertex_indices(sources, self.mesh.n_vertices)
        out = np.empty((len(s), self.mesh.n_vertices))
        for r, i in enumerate(s.tolist()):
            out[r] = self._solver.compute_distance(i)
            self._cut(out[r], np.array([i]))
        return out

    def distance_matrix(self, symmetrize: bool = True, force: bool = False) -> np.ndarray:
        """``(V, V)`` all-pairs distances (``symmetrize``: averaged with ``D.T``); raises
        :class:`ParameterError` above ``FULL_MATRIX_LIMIT`` vertices unless ``force``."""
        n = self.mesh.n_vertices
        if n > FULL_MATRIX_LIMIT and not force:
            raise ParameterError(
                f"a full distance matrix of {n} vertices needs {n * n * 8 / 1e9:.1f} GB. Fix: use "
                "`distances(rows)` for the rows you need, or pass force=True."
            )
        d = self.distances(np.arange(n))
        return 0.5 * (d + d.T) if symmetrize else d


class DistanceRows:
    """Geodesic distance rows of one mesh, each source solved once and kept (up to ``max_bytes``,
    None: no bound). ``solver``: built on first use when None; ``normalized=True``: rows are
    ``max(d, 0) / sqrt(area)``. Raises :class:`ParameterError` for a negative ``max_bytes``."""

    def __init__(
        self,
        mesh: Mesh,
        solver: GeodesicSolver | None = None,
        *,
        normalized: bool = False,
        max_bytes: int | None = None,
    ) -> None:
        if max_bytes is not None and max_bytes < 0:
            raise ParameterError(f"max_bytes must be None or >= 0, got {max_bytes}.")
        self.mesh = mesh
        self._solver = solver
        self.scale = 1.0 / np.sqrt(mesh.area) if normalized else None
        self.max_rows = None if max_bytes is None else int(max_bytes) // (8 * max(mesh.n_vertices, 1))
        self._rows: dict[int, np.ndarray] = {}

    @property
    def solver(self) -> GeodesicSolver:
        """The mesh's :class:`GeodesicSolver`, built (prefactored) on first use."""
        if self._solver is None:
            self._solver = GeodesicSolver(self.mesh)
        return self._solver

    def __call__(self, source: int) -> np.ndarray:
        """``(V,)`` distances from ``source``."""
        return self.distances([source])[0]

    def distances(self, sources) -> np.ndarray:
        """``(S, V)``: row ``r`` holds distances from ``sources[r]`` (kept rows are not solved again)."""
        s = check_vertex_indices(sources, self.mesh.n_vertices)
        missing = [i for i in s.tolist() if i not in self._rows]
        fresh = {}
        if missing:
            solved = self.solver.distances(missing)
            if self.scale is not None:
                solved = np.maximum(solved, 0.0) * self.scale
            fresh = dict(zip(missing, solved, strict=True))
        for i, row in fresh.items():
            if self.max_rows is not None and len(self._rows) >= self.max_rows:
                break
            self._rows[i] = row
        return np.stack([self._rows[i] if i in self._rows else fresh[i] for i in s.tolist()])


def geodesic_distances(mesh: Mesh, sources) -> np.ndarray:
    """``(S, V)`` heat-method distances from each source (one-shot; build a solver to reuse)."""
    return GeodesicSolver(mesh).distances(sources)
