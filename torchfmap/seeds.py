"""Seed points: curvature, curvature features, farthest-point sampling, coverage growth, seed pairs.
All are deterministic (ties go to the lowest index)."""

from __future__ import annotations

from typing import Literal

import numpy as np
import scipy.sparse as sp

from ._util.checks import (
    check_count,
    check_landmark_pairs,
    check_seeds_cover_components,
    check_vertex_indices,
)
from .errors import ParameterError
from .mesh import Mesh
from .operators.geodesic import DistanceRows, GeodesicSolver
from .operators.heat import heat_kernels
from .operators.laplacian import Operators, laplacian, mass_matrix

__all__ = [
    "consistent_seeds", "check_seeds_cover_components", "corresponding_seeds", "coverage_seeds",
    "curvature", "curvature_features", "farthest_point_sampling", "gaussian_curvature",
    "heat_support_radius", "max_curvature_vertex", "mean_curvature",
]  # fmt: skip

CurvatureMeasure = Literal["mean", "gaussian", "abs_mean"]


def mean_curvature(mesh: Mesh, operators: Operators | None = None) -> np.ndarray:
    """``(V,)`` signed mean curvature ``H`` (``L x = 2 H n B``, outward normals); 0 on the boundary."""
    L, B = operators if operators is not None else laplacian(mesh, "cotan", "voronoi")
    mass = np.asarray(B.sum(axis=1)).ravel()
    hn = (L @ mesh.vertices) / np.maximum(mass, 1e-300)[:, None]
    h = 0.5 * np.einsum("ij,ij->i", hn, mesh.vertex_normals)
    h[mesh.boundary_vertices] = 0.0
    return h


def gaussian_curvature(mesh: Mesh) -> np.ndarray:
    """``(V,)`` Gaussian curvature: the angle defect (``π`` less on the boundary) over the Voronoi area."""
    v, f = mesh.vertices, mesh.faces
    x = v[f]
    a = np.roll(x, -1, axis=1) - x
    b = np.roll(x, -2, axis=1) - x
    cos = np.einsum("fci,fci->fc", a, b) / (np.linalg.norm(a, axis=2) * np.linalg.norm(b, axis=2))
    angles = np.arccos(np.clip(cos, -1.0, 1.0))
    total = np.bincount(f.ravel(), weights=angles.ravel(), minlength=mesh.n_vertices)
    defect = 2 * np.pi - total
    defect[mesh.boundary_vertices] -= np.pi
    area = mass_matrix(mesh, "voronoi").diagonal()
    return defect / np.maximum(area, 1e-300)


def curvature(mesh: Mesh, measure: CurvatureMeasure = "mean") -> np.ndarray:
    """``(V,)`` curvature by ``measure`` (``'mean'``, ``'abs_mean'``, ``'gaussian'``; else ParameterError)."""
    if measure == "mean":
        return mean_curvature(mesh)
    if measure == "abs_mean":
        return np.abs(mean_curvature(mesh))
    if measure == "gaussian":
        return gaussian_curvature(mesh)
    raise ParameterError(f"unknown curvature measure {measure!r}. Fix: use 'mean', 'abs_mean' or 'gaussian'.")


def _adjacency(mesh: Mesh) -> sp.csr_matrix:
    e = mesh.edges
    a = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(mesh.n_vertices,) * 2)
    return (a + a.T).tocsr()


def _smooth(mesh: Mesh, values: np.ndarray, steps: int) -> np.ndarray:
    adj = _adjacency(mesh) + sp.identity(mesh.n_vertices, format="csr")
    deg = np.asarray(adj.sum(axis=1)).ravel()
    for _ in range(steps):
        values = (adj @ values) / deg
    return values


def max_curvature_vertex(mesh: Mesh, smooth_steps: int = 2) -> int:
    """The vertex of largest (1-ring smoothed) absolute mean curvature."""
    return int(np.argmax(_smooth(mesh, np.abs(mean_curvature(mesh)), smooth_steps)))


def curvature_features(
    mesh: Mesh,
    k: int,
    measure: CurvatureMeasure = "abs_mean",
    min_separation: float | None = None,
    smooth_steps: int = 2,
) -> np.ndarray:
    """Up to ``k`` feature points ``(k',)`` int64: strict 1-ring maxima of smoothed curvature, strongest
    first, none closer than ``min_separation`` (Euclidean; default ``sqrt(|M| / k) / 2``) to a stronger."""
    if k < 1:
        raise ParameterError(f"k must be >= 1, got {k}.")
    values = _smooth(mesh, curvature(mesh, measure), smooth_steps)
    adj = _adjacency(mesh).tocoo()
    neighbour_max = np.full(mesh.n_vertices, -np.inf)
    np.maximum.at(neighbour_max, adj.row, values[adj.col])
    candidates = np.flatnonzero(values > neighbour_max)
    candidates = candidates[np.argsort(-values[candidates], kind="stable")]
    sep = np.sqrt(mesh.area / k) / 2 if min_separation is None else float(min_separation)
    chosen: list[int] = []
    for c in candidates:
        if len(chosen) == k:
            break
        if chosen and np.min(np.linalg.norm(mesh.vertices[chosen] - mesh.vertices[c], axis=1)) < sep:
            continue
        chosen.append(int(c))
    return np.asarray(chosen, dtype=np.int64)


class _Distances:
    def __init__(
        self, mesh: Mesh, metric: str, solver: GeodesicSolver | None, rows: DistanceRows | None = None
    ) -> None:
        if metric not in ("geodesic", "euclidean"):
            raise ParameterError(f"metric must be 'geodesic' or 'euclidean', got {metric!r}.")
        self.mesh, self.metric, self.rows = mesh, metric, rows
        if rows is None:
            self.solver = solver if solver is not None or metric == "euclidean" else GeodesicSolver(mesh)

    def __call__(self, i: int) -> np.ndarray:
        if self.metric == "euclidean":
            diff = self.mesh.vertices - self.mesh.vertices[i]
            return np.sqrt(np.einsum("ij,ij->i", diff, diff))
        if self.rows is not None:  # solved once, kept for whoever asks next
            return np.maximum(self.rows(int(i)), 0.0)
        return np.maximum(self.solver.distance(int(i)), 0.0)


def farthest_point_sampling(
    mesh: Mesh,
    k: int,
    *,
    start: int | Literal["curvature"] = "curvature",
    landmarks=None,
    metric: Literal["geodesic", "euclidean"] = "geodesic",
    solver: GeodesicSolver | None = None,
    distances: DistanceRows | None = None,
    return_radius: bool = False,
):
    """``(k,)`` int64 farthest-point seeds (and the covering radius with ``return_radius``): ``landmarks``
    first (counted in ``k``), else ``start`` (a vertex, or ``'curvature'``: :func:`max_curvature_vertex`).
    ``metric``: ``'euclidean'`` or ``'geodesic'``, reusing ``solver`` (a :class:`~torchfmap.GeodesicSolver`)
    or ``distances`` (:class:`~torchfmap.operators.geodesic.DistanceRows`, whose units it then uses)."""
    n = mesh.n_vertices
    if k < 1 or k > n:
        raise ParameterError(f"k must be in [1, {n}] for a mesh of {n} vertices, got {k}.")
    dist = _Distances(mesh, metric, solver, distances)
    seeds: list[int] = []
    mind = np.full(n, np.inf)
    if landmarks is not None and len(np.atleast_1d(landmarks)):
        lm = check_vertex_indices(landmarks, n, "landmarks")
        if len(lm) > k:
            raise ParameterError(f"{len(lm)} landmarks but k={k}. Fix: ask for k >= the number of landmarks.")
        seeds.extend(int(i) for i in lm)
        for i in lm:
            mind = np.minimum(mind, dist(int(i)))
    else:
        if start == "curvature":
            first = max_curvature_vertex(mesh)
        else:
            (first,) = check_vertex_indices([start], n, "start")
        seeds.append(int(first))
        mind = dist(int(first))
    mind[seeds] = 0.0
    while len(seeds) < k:
        nxt = int(np.argmax(mind))
        seeds.append(nxt)
        mind = np.minimum(mind, dist(nxt))
        mind[nxt] = 0.0
    out = np.asarray(seeds, dtype=np.int64)
    return (out, float(mind.max())) if return_radius else out


def corresponding_seeds(
    mesh_x: Mesh,
    mesh_y: Mesh,
    landmarks,
    n_seeds: int,
    *,
    distances: tuple[DistanceRows, DistanceRows] | None = None,
) -> np.ndarray:
    """``(n_seeds, 2)`` distinct seed pairs ``(x vertex, y vertex)``: the ``landmarks`` ``(L, 2)`` first, then
    geodesic farthest points ``s`` of ``x``, each placed on ``y`` at the ``v`` minimising
    ``Σ_a w_a (d_y(v, a_y) - d_x(s, a_x))²`` over the pairs ``a`` placed so far, with
    ``w_a = 1 / (d_x(s, a_x)² + 1 / n_seeds)``; ``distances``: both meshes' ``normalized=True``
    :class:`~torchfmap.operators.DistanceRows`. Raises :class:`SeedError` for invalid landmarks,
    :class:`ParameterError` for ``n_seeds`` outside ``[L, min(V_x, V_y)]``."""
    pairs = check_landmark_pairs(landmarks, mesh_x.n_vertices, mesh_y.n_vertices)
    top = min(mesh_x.n_vertices, mesh_y.n_vertices)
    n_seeds = check_count(n_seeds, len(pairs), top, "n_seeds (landmarks to vertices)")
    if distances is None:
        distances = (DistanceRows(mesh_x, normalized=True), DistanceRows(mesh_y, normalized=True))
    dx, dy = distances
    r2 = 1.0 / n_seeds
    placed = [(int(a), int(b)) for a, b in pairs]
    used_x, used_y = {a for a, _ in placed}, {b for _, b in placed}
    nearest = np.min(dx.distances([a for a, _ in placed]), axis=0)
    nearest[list(used_x)] = -np.inf
    while len(placed) < n_seeds:  # bounded: one seed per pass, at most n_seeds passes
        s = int(np.argmax(nearest))
        d_s = np.array([dx(a)[s] for a, _ in placed])
        weights = 1.0 / (d_s**2 + r2)
        cost = weights @ (dy.distances([b for _, b in placed]) - d_s[:, None]) ** 2
        cost[list(used_y)] = np.inf
        v = int(np.argmin(cost))
        placed.append((s, v))
        used_x.add(s)
        used_y.add(v)
        nearest = np.minimum(nearest, dx(s))
        nearest[s] = -np.inf
    return np.asarray(placed, dtype=np.int64)


def heat_support_radius(time_abs: float, eps: float) -> float:
    """Radius where a Gaussian heat kernel ``exp(-d²/4t)`` falls to ``eps`` of its peak."""
    return float(np.sqrt(4.0 * time_abs * np.log(1.0 / eps)))


def coverage_seeds(
    mesh: Mesh,
    time: float,
    *,
    eps: float = 1e-3,
    landmarks=None,
    start: int | Literal["curvature"] = "curvature",
    max_seeds: int = 2000,
    operators: Operators | None = None,
    method: str = "krylov",
) -> np.ndarray:
    """``(S,)`` farthest-point seeds (landmarks first, past :func:`heat_support_radius`) whose heat kernels at
    relative ``time`` (absolute ``time * |M|``) exceed ``eps`` times their maximum on every vertex. Raises
    :class:`ParameterError` for ``time`` not finite > 0, ``eps`` not in (0, 1), no cover in ``max_seeds``."""
    if not np.isfinite(time) or time <= 0:
        raise ParameterError(f"diffusion time must be finite and > 0, got t={time}. Fix: e.g. t=1e-2.")
    if not 0 < eps < 1:
        raise ParameterError(f"eps must be in (0, 1), got {eps}.")
    ops = operators if operators is not None else laplacian(mesh)
    solver = GeodesicSolver(mesh)
    radius = heat_support_radius(time * mesh.area, eps)
    k = 1 if landmarks is None else len(np.atleast_1d(landmarks))
    seeds, cover = farthest_point_sampling(
        mesh, k, start=start, landmarks=landmarks, solver=solver, return_radius=True
    )
    mind = np.min(solver.distances(seeds), axis=0)
    while cover > radius and len(seeds) < max_seeds:
        nxt = int(np.argmax(mind))
        seeds = np.append(seeds, nxt)
        mind = np.minimum(mind, np.maximum(solver.distance(nxt), 0.0))
        cover = float(mind.max())
    covered = np.zeros(mesh.n_vertices, dtype=bool)
    new = seeds
    while True:
        kernels = heat_kernels(ops, new, [time * mesh.area], method=method)[0]
        covered |= (np.abs(kernels) > eps * np.abs(kernels).max(axis=0, keepdims=True)).any(axis=1)
        if covered.all():
            return seeds
        if len(seeds) >= max_seeds:
            raise ParameterError(
                f"{len(seeds)} seeds do not cover the surface at t={time:g} (eps={eps:g}). Fix: "
                "raise max_seeds, use a larger t, or a smaller eps."
            )
        nxt = int(np.argmax(np.where(covered, -np.inf, mind)))
        seeds = np.append(seeds, nxt)
        mind = np.minimum(mind, np.maximum(solver.distance(nxt), 0.0))
        new = np.array([nxt])


def replace_seeds(
    distances_x: DistanceRows, distances_y: DistanceRows, seeds: np.ndarray, p2p_yx: np.ndarray, n_fixed: int
) -> np.ndarray:
    """Seed pairs ``(S, 2)`` with the ``y`` side of each after the first ``n_fixed`` moved to the free
    ``y`` vertex whose image under ``p2p_yx (V_y,)`` is geodesically nearest its ``x`` side, unless that
    moves it by the covering radius ``sqrt(1 / S)`` or more. ``distances_*``: ``normalized=True`` rows."""
    radius = np.sqrt(1.0 / len(seeds))
    out = seeds.copy()
    held = {int(v) for v in seeds[:, 1]}  # no seed moves onto another's
    for i in range(n_fixed, len(seeds)):  # bounded: one pass over the seeds
        s, old = int(seeds[i, 0]), int(seeds[i, 1])
        held.discard(old)
        order = np.argsort(distances_x(s)[p2p_yx], kind="stable")
        new = next(int(v) for v in order if int(v) not in held)
        if distances_y(old)[new] >= radius:
            new = old
        out[i, 1] = new
        held.add(new)
    return out


def consistent_seeds(
    distances_x: DistanceRows, seeds_x: np.ndarray, images_y: np.ndarray, returns_x: np.ndarray
) -> np.ndarray:
    """Seed pairs ``(S', 2)``, in order: ``(s, t)`` for ``s`` in ``seeds_x``, ``t`` its image (``images_y``),
    where ``t``'s image back (``returns_x``) is within ``sqrt(1 / S) / 2`` of ``s`` (``distances_x``: units of
    ``sqrt(area)``) and no earlier seed took ``t``. ParameterError unless all three are 1-D of one length."""
    seeds_x, images_y, returns_x = (np.asarray(a, dtype=np.int64) for a in (seeds_x, images_y, returns_x))
    if not (seeds_x.ndim == images_y.ndim == returns_x.ndim == 1) or not (
        len(seeds_x) == len(images_y) == len(returns_x)
    ):
        raise ParameterError("seeds_x, images_y and returns_x must be 1-D index arrays of one length.")
    if not len(seeds_x):
        return np.zeros((0, 2), dtype=np.int64)
    radius = 0.5 * np.sqrt(1.0 / len(seeds_x))
    rows = distances_x.distances(seeds_x)  # (S, V_x)
    near = rows[np.arange(len(seeds_x)), returns_x] < radius
    taken: set[int] = set()
    keep = []
    for i in np.flatnonzero(near):  # bounded: one pass over the seeds
        if int(images_y[i]) not in taken:
            taken.add(int(images_y[i]))
            keep.append(i)
    return np.stack([seeds_x[keep], images_y[keep]], axis=1).astype(np.int64).reshape(-1, 2)
