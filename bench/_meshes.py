"""Deterministic test meshes shared by the benchmark scripts in ``bench/``.

``bench_mesh(n)`` gives an irregular, closed, genus-0 triangle mesh with exactly ``n`` vertices
(real meshes: ``_common.data_path``).
"""

from __future__ import annotations

import _common  # noqa: F401  (puts this checkout first on sys.path, before torchfmap)
import numpy as np
from scipy.spatial import ConvexHull

import torchfmap

# Bump centres (unit vectors, normalised below), widths (radians) and heights.
_BUMP_CENTRES = np.array([[0.0, 0.0, 1.0], [1.0, 0.3, -0.2], [-0.5, -0.8, 0.1], [0.2, 0.9, -0.6]])
_BUMP_WIDTHS = np.array([0.5, 0.35, 0.7, 0.25])
_BUMP_HEIGHTS = np.array([1.0, 0.8, -0.6, 0.9])


def _fibonacci_sphere(n: int) -> np.ndarray:
    """``(n, 3)`` near-uniform unit vectors on the golden-angle spiral."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    rho = np.sqrt(1.0 - z**2)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)


def bench_mesh(n_vertices: int, seed: int = 0) -> torchfmap.Mesh:
    """An irregular closed genus-0 mesh with exactly ``n_vertices`` vertices.

    Fibonacci-sphere points get a deterministic tangential jitter (a fifth of the point spacing),
    are triangulated by their convex hull (faces oriented outward), then displaced radially by
    ``r = 1 + 0.3 * sum_k h_k exp(-(d_k / w_k)^2)`` (``d_k`` the angular distance to bump ``k``)
    and stretched by 1.6 along x, so the surface is neither a sphere nor convex.

    Args:
        n_vertices: number of vertices (>= 4).
        seed: seed of the jitter.
    """
    if n_vertices < 4:
        raise ValueError(f"bench_mesh needs at least 4 vertices, got {n_vertices}.")
    rng = np.random.default_rng(seed)
    p = _fibonacci_sphere(n_vertices)
    jitter = rng.normal(size=p.shape) * 0.2 * np.sqrt(4.0 * np.pi / n_vertices)
    jitter -= np.einsum("ij,ij->i", jitter, p)[:, None] * p  # keep it tangential
    p = p + jitter
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    hull = ConvexHull(p)
    if len(hull.vertices) != n_vertices:
        raise RuntimeError(f"convex hull used {len(hull.vertices)} of {n_vertices} points.")
    f = hull.simplices.astype(np.int64)
    x = p[f]
    normals = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    inward = np.einsum("ij,ij->i", normals, x.sum(axis=1)) < 0  # hull contains the origin
    f[inward] = f[inward][:, ::-1]
    centres = _BUMP_CENTRES / np.linalg.norm(_BUMP_CENTRES, axis=1, keepdims=True)
    angle = np.arccos(np.clip(p @ centres.T, -1.0, 1.0))  # (n, k) angular distances
    r = 1.0 + 0.3 * (_BUMP_HEIGHTS * np.exp(-((angle / _BUMP_WIDTHS) ** 2))).sum(axis=1)
    v = p * r[:, None] * np.array([1.6, 1.0, 1.0])
    return torchfmap.Mesh(v, f, name=f"bench{n_vertices}")


def mesh_name(n: int) -> str:
    """``'bench5K'`` for 5000 vertices, ``'bench1234'`` otherwise."""
    return f"bench{n // 1000}K" if n % 1000 == 0 else f"bench{n}"
