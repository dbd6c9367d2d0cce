"""Remeshing with ground truth carried through (optional pymeshlab): :func:`remesh` by ``'isotropic'`` (edges
of one length), ``'anisotropic'`` (the same on the shape stretched by ``stretch`` along one direction, then
unstretched) or ``'decimate'``; ``density > 1``: edges longer at one end (:class:`_DensityWarp`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .errors import MeshError, ParameterError
from .mesh import Mesh

METHODS = ("isotropic", "anisotropic", "decimate")
#: Remeshing passes that adjust the edge length towards the target count, and iterations of one.
MAX_PASSES = 5
ITERATIONS = 6


@dataclass
class Remeshed:
    """:func:`remesh`'s new ``mesh`` and ``to_new (V_old,)``, the nearest new vertex of every old one."""

    mesh: Mesh
    to_new: np.ndarray


class _DensityWarp:
    """``x -> c + (x - c) / |x - c|^2`` (its own inverse), ``c`` at ``D = R / (sqrt(density) - 1)`` before the
    shape's extent ``R`` along ``u``: edges ``((D + R) / D)^2 = density`` times longer at the far end."""

    def __init__(self, V: np.ndarray, density: float, u: np.ndarray) -> None:
        self.on = density > 1.0
        if self.on:
            u = u / np.linalg.norm(u)
            mid = (V.max(axis=0) + V.min(axis=0)) / 2.0
            t = (V - mid) @ u
            R = float(np.ptp(t)) or float(np.linalg.norm(np.ptp(V, axis=0)))  # flat across u: the diagonal
            D = R / (math.sqrt(density) - 1.0)
            self.c = mid + (float(t.min()) - D) * u  # D before the nearest point along u

    def __call__(self, V: np.ndarray) -> np.ndarray:
        if not self.on:
            return V
        x = V - self.c
        return self.c + x / np.einsum("ij,ij->i", x, x)[:, None]


def _pymeshlab():
    try:
        import pymeshlab
    except ImportError as err:  # optional dependency
        raise ImportError(
            "remeshing needs pymeshlab. Fix: pip install 'torchfmap[remesh]' (or pip install pymeshlab)."
        ) from err
    return pymeshlab


def remesh(
    mesh: Mesh,
    n_vertices: int,
    method: str = "isotropic",
    *,
    stretch: float = 3.0,
    direction=None,
    density: float = 1.0,
    seed: int = 0,
) -> Remeshed:
    """``mesh`` remeshed by ``method`` (module docstring) to about ``n_vertices`` (``>= 100``) vertices,
    and the nearest new vertex of each old one. ``'anisotropic'`` stretches by ``stretch`` (> 1) along
    ``direction`` ``(3,)``; ``density`` (>= 1): longest over shortest edge length; random directions come
    from ``seed``. Raises :class:`ParameterError` for bad arguments (``density > 1`` with ``'decimate'``
    included), ImportError without pymeshlab, :class:`MeshError` if no pass gives a valid mesh."""
    if method not in METHODS:
        raise ParameterError(f"unknown remeshing method {method!r}. Fix: one of {', '.join(METHODS)}.")
    if int(n_vertices) != n_vertices or n_vertices < 100:
        raise ParameterError(f"n_vertices must be an integer >= 100, got {n_vertices}.")
    if method == "anisotropic" and not (math.isfinite(stretch) and stretch > 1):
        raise ParameterError(f"stretch must be a finite number > 1, got {stretch}.")
    if not (math.isfinite(density) and density >= 1) or (density > 1 and method == "decimate"):
        raise ParameterError(
            f"density must be a finite number >= 1 with 'isotropic' or 'anisotropic', got {density} "
            f"with {method!r}. Fix: density=1 (uniform) or another method."
        )
    ml = _pymeshlab()
    V = mesh.vertices
    rng = np.random.default_rng(seed)
    A = np.eye(3)
    if method == "anisotropic":
        d = rng.normal(size=3) if direction is None else np.asarray(direction, float)
        if d.shape != (3,) or not np.linalg.norm(d) > 0:
            raise ParameterError(f"direction must be a non-zero (3,) vector, got {direction!r}.")
        d = d / np.linalg.norm(d)
        A = np.eye(3) + (stretch - 1.0) * np.outer(d, d)
    warp = _DensityWarp(V, density, rng.normal(size=3))
    ms = ml.MeshSet()
    ms.add_mesh(ml.Mesh(warp(V) @ A, mesh.faces))
    base = ms.current_mesh_id()
    area = float(ms.get_geometric_measures()["surface_area"])
    # equilateral triangles, F = 2V: area = 2 V (sqrt(3) / 4) l^2
    length = math.sqrt(2.0 * area / (math.sqrt(3.0) * n_vertices))
    new, problem = None, ""
    for attempt in range(MAX_PASSES):  # bounded: edge length corrected from the count reached
        ms.set_current_mesh(base)
        ms.generate_copy_of_current_mesh()
        if method == "decimate":
            ms.meshing_decimation_quadric_edge_collapse(
                targetfacenum=int(2 * n_vertices) - 2 * attempt, preservenormal=True, preservetopology=True
            )
        else:
            ms.meshing_isotropic_explicit_remeshing(
                targetlen=ml.PureValue(length), iterations=ITERATIONS + attempt, adaptive=False
            )
        # a remesh may leave a zero-area face or a pinched vertex: clean what the operators refuse
        ms.meshing_remove_null_faces()
        ms.meshing_remove_duplicate_faces()
        ms.meshing_repair_non_manifold_edges()
        ms.meshing_repair_non_manifold_vertices()
        if mesh.n_components == 1:  # slivers split off by the repairs
            ms.meshing_remove_connected_component_by_diameter(mincomponentdiag=ml.PercentageValue(10.0))
        ms.meshing_remove_unreferenced_vertices()
        out = ms.current_mesh()
        got = out.vertex_number()
        verts = warp(out.vertex_matrix() @ np.linalg.inv(A))
        try:
            candidate = Mesh(verts, out.face_matrix().astype(np.int64), allow_nonmanifold=True)
        except MeshError as err:  # e.g. a sliver face: remesh again (more iterations)
            problem = str(err)
            continue
        new = candidate
        if method == "decimate" or abs(got - n_vertices) <= 0.03 * n_vertices:
            break
        length *= math.sqrt(got / n_vertices)
    if new is None:
        raise MeshError(f"remeshing gave no valid mesh in {MAX_PASSES} attempts: {problem}")
    to_new = cKDTree(verts).query(V)[1].astype(np.int64)
    return Remeshed(new, to_new)
