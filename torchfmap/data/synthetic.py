"""Synthetic meshes: icospheres, smooth deformations, and the demo pair shipped in ``torchfmap/data/demo/``
(:func:`make_demo_pair`: ``blob_a``, ``blob_b`` and the ground truth ``blob_b_to_a.txt``)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np
import trimesh

from ..errors import ParameterError
from ..io import load_mesh, read_map
from ..mesh import Mesh

#: Gaussian bumps (direction, height, width) that break the ellipsoid's symmetries.
_BUMPS = (
    ((1.0, 0.2, 0.3), 0.35, 0.35),
    ((-0.6, 0.8, 0.1), 0.25, 0.30),
    ((0.1, -0.5, 0.9), 0.45, 0.25),
    ((-0.5, -0.6, -0.7), 0.20, 0.40),
)


def icosphere(subdivisions: int = 3, radius: float = 1.0) -> Mesh:
    """A geodesic sphere (``10 * 4**s + 2`` vertices) projected onto the sphere of ``radius``."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    v = np.asarray(sphere.vertices, dtype=np.float64)
    v *= radius / np.linalg.norm(v, axis=1, keepdims=True)
    return Mesh(v, np.asarray(sphere.faces), name=f"icosphere{subdivisions}")


def _bumpy_blob(subdivisions: int) -> Mesh:
    base = icosphere(subdivisions)
    u = base.vertices
    r = np.ones(len(u))
    for direction, height, width in _BUMPS:
        d = np.asarray(direction) / np.linalg.norm(direction)
        ang = np.arccos(np.clip(u @ d, -1, 1))
        r += height * np.exp(-((ang / width) ** 2))
    v = u * r[:, None] * np.array([1.8, 1.0, 0.8])
    return Mesh(v, base.faces, name="blob_a")


def _bend(v: np.ndarray, strength: float = 0.35) -> np.ndarray:
    """Bend along x around the z axis: a near-isometric, non-rigid deformation."""
    radius = 1.0 / strength
    theta = v[:, 0] / radius
    rr = radius - v[:, 1]
    return np.stack([rr * np.sin(theta), radius - rr * np.cos(theta), v[:, 2]], axis=1)


def make_demo_pair(subdivisions: int = 4, seed: int = 0) -> tuple[Mesh, Mesh, np.ndarray]:
    """``(blob_a, blob_b, gt_b_to_a)``: a bumpy blob, its bent and vertex-shuffled copy, and ``(V,)``
    ``gt_b_to_a[i]``, the vertex of ``blob_a`` that vertex ``i`` of ``blob_b`` came from."""
    a = _bumpy_blob(subdivisions)
    perm = np.random.default_rng(seed).permutation(a.n_vertices)
    b = a.copy(_bend(a.vertices)).permuted(perm)
    b.name = "blob_b"
    return a, b, perm


def demo_pair_paths() -> tuple[Path, Path, Path]:
    """Paths of the shipped demo files ``(blob_a.off, blob_b.off, blob_b_to_a.txt)``."""
    root = Path(str(resources.files("torchfmap") / "data" / "demo"))
    return root / "blob_a.off", root / "blob_b.off", root / "blob_b_to_a.txt"


def demo_pair() -> tuple[Mesh, Mesh, np.ndarray]:
    """Load the shipped demo pair: ``(blob_a, blob_b, gt_b_to_a)``."""
    pa, pb, pgt = demo_pair_paths()
    return load_mesh(pa), load_mesh(pb), read_map(pgt)


def stretch_deform(mesh: Mesh, seed: int = 0, strength: float = 1.0) -> Mesh:
    """A smooth, non-isometric deformation of ``mesh`` keeping vertex ids and faces (ground truth: identity),
    drawn from ``seed``: a local stretch along a random axis, then a scaling around a far vertex, Gaussian
    bumps of ``strength`` (>= 0, else :class:`ParameterError`; 0 keeps the geometry)."""
    if not np.isfinite(strength) or strength < 0:
        raise ParameterError(f"strength must be finite and >= 0, got {strength}. Fix: e.g. strength=1.")
    rng = np.random.default_rng(seed)
    v = np.array(mesh.vertices, dtype=np.float64)
    scale = np.sqrt(mesh.area)
    c = v[rng.integers(len(v))]
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    w = np.exp(-np.sum((v - c) ** 2, axis=1) / (2 * (0.35 * scale) ** 2))
    v = v + strength * w[:, None] * ((v - c) @ axis)[:, None] * axis[None]
    far = np.argsort(np.linalg.norm(v - v.mean(axis=0), axis=1))[-max(1, len(v) // 10) :]
    c2 = v[far[rng.integers(len(far))]]
    w2 = np.exp(-np.sum((v - c2) ** 2, axis=1) / (2 * (0.25 * scale) ** 2))
    v = c2 + (1.0 + 0.6 * strength * w2)[:, None] * (v - c2)
    name = f"{mesh.name}~{seed}" if mesh.name else None
    return Mesh(v, mesh.faces, name=name, **mesh._flags)
