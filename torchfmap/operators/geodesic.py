"""Geodesic distances with the heat method (potpourri3d), with a reusable solver object.

The heat method (Crane et al. 2013) prefactors two sparse systems once; every further source
costs two back-substitutions. Distances are approximate (first order in the mean edge length);
``use_robust=True`` (default) uses the intrinsic Delaunay / tufted Laplacian, which is more
accurate on poor triangulations and works on non-manifold meshes.
"""

from __future__ import annotations

import numpy as np
import potpourri3d as pp3d

from .._util.checks import check_vertex_indices
from ..errors import ParameterError
from ..mesh import Mesh

#: Largest mesh for which :meth:`GeodesicSolver.distance_matrix` builds a full ``(V, V)`` matrix
#: without ``force=True`` (``V**2 * 8`` bytes: 400 MB at this size).
FULL_MATRIX_LIMIT = 7000


class GeodesicSolver:
    """Heat-method geodesic distances on one mesh; build once, query many times.

    Vertices on another connected component than the source (and unreferenced vertices) are at
    distance ``inf``: no path joins them.

    Args:
        mesh: the surface.
        t_coef: time step factor of the heat method (potpourri3d default 1.0).
        use_robust: intrinsic-Delaunay operators (recommended).

    Example:
        >>> solver = GeodesicSolver(mesh)
        >>> d = solver.distance(0)              # (V,) distances from vertex 0
        >>> D = solver.distances([0, 5, 9])     # (3, V): one row per source
    """

    def __init__(self, mesh: Mesh, t_coef: float = 1.0, use_robust: bool = True) -> None:
        if t_coef <= 0:
            raise ParameterError(f"t_coef must be positive, got {t_coef}.")
        self.mesh = mesh
        self._solver = pp3d.MeshHeatMethodDistanceSolver(
            mesh.vertices, mesh.faces, t_coef=t_coef, use_robust=use_robust
        )
        labels = mesh.component_labels.copy()
        labels[np.setdiff1d(np.arange(mesh.n_vertices), np.unique(mesh.faces))] = -1  # unreferenced
        self._labels = labels
        self._single = mesh.n_components == 1 and labels.min() >= 0

    def _cut(self, d: np.ndarray, sources: np.ndarray) -> np.ndarray:
        """``inf`` where no source's component reaches (the heat method returns a constant)."""
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
        s = check_vertex_indices(sources, self.mesh.n_vertices)  # checked once, not per row
        out = np.empty((len(s), self.mesh.n_vertices))
        for r, i in enumerate(s.tolist()):
            out[r] = self._solver.compute_distance(i)
            self._cut(out[r], np.array([i]))
        return out

    def distance_matrix(self, symmetrize: bool = True, force: bool = False) -> np.ndarray:
        """``(V, V)`` all-pairs distances; refuses meshes above ``FULL_MATRIX_LIMIT`` unless forced.

        The heat method is not exactly symmetric; ``symmetrize`` averages ``D`` and ``D.T``.
        """
        n = self.mesh.n_vertices
        if n > FULL_MATRIX_LIMIT and not force:
            raise ParameterError(
                f"a full distance matrix of {n} vertices needs {n * n * 8 / 1e9:.1f} GB. Fix: use "
                "`distances(rows)` for the rows you need, or pass force=True."
            )
        d = self.distances(np.arange(n))
        return 0.5 * (d + d.T) if symmetrize else d


class DistanceRows:
    """Geodesic distance rows of one mesh, each source solved once and kept for reuse.

    Rows are kept until ``max_bytes`` of them are held (None: no bound); beyond it they are
    computed but not kept. ``normalized=True`` gives ``max(d, 0) / sqrt(area)`` (units of the
    square root of the area), else the solver's distances unchanged.

    Args:
        mesh: the surface.
        solver: its :class:`GeodesicSolver` (built on first use when None).
        normalized: scale as above.
        max_bytes: bound on the kept rows (8 V bytes each).

    Raises:
        ParameterError: ``max_bytes`` negative.
    """

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
        """``(S, V)``: row ``r`` holds distances from ``sources[r]`` (kept rows are not solved
        again); the interface of :meth:`GeodesicSolver.distances`."""
        s = check_vertex_indices(sources, self.mesh.n_vertices)  # distinct, in range
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
