"""Discrete Laplace-Beltrami operators: stiffness ``L`` (the weak ``-Δ``: positive semidefinite, rows
summing to zero) and mass ``B`` (summing to the surface area). Schemes: ``cotan``, ``robust``
(intrinsic Delaunay, also for point clouds) and ``mean_value`` (Floater; **not symmetric**: harmonic
bases only). Masses: ``voronoi``, ``barycentric`` (lumped) and ``fem`` (consistent)."""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np
import robust_laplacian
import scipy.sparse as sp

from .._util.checks import lumped_diagonal as lumped_diagonal  # public here too (re-export)
from ..errors import MeshError, ParameterError
from ..mesh import Mesh

LaplacianScheme = Literal["cotan", "robust", "mean_value"]
MassScheme = Literal["voronoi", "barycentric", "fem"]
LAPLACIAN_SCHEMES = ("cotan", "robust", "mean_value")
MASS_SCHEMES = ("voronoi", "barycentric", "fem")


class Operators(NamedTuple):
    """Stiffness and mass matrices, both ``(V, V)`` scipy CSR float64. Unpacks as ``L, B``."""

    stiffness: sp.csr_matrix
    mass: sp.csr_matrix


def _corner_geometry(v: np.ndarray, f: np.ndarray):
    """``a, b`` ``(F, 3, 3)``: ``a[:, c] = x[f[c+1]] - x[f[c]]``, ``b[:, c] = x[f[c+2]] - x[f[c]]``."""
    x = v[f]  # (F, 3, 3)
    a = np.roll(x, -1, axis=1) - x
    b = np.roll(x, -2, axis=1) - x
    return a, b


def _cotangents(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """``(F, 3)``: cotangent of the angle at each corner."""
    a, b = _corner_geometry(v, f)
    dot = np.einsum("fci,fci->fc", a, b)
    cross = np.linalg.norm(np.cross(a, b), axis=2)
    return dot / cross


def _assemble_symmetric(f: np.ndarray, w: np.ndarray, n: int) -> sp.csr_matrix:
    """``L`` from per-corner weights ``w (F, 3)`` on the edge opposite each corner."""
    i = np.roll(f, -1, axis=1).ravel()
    j = np.roll(f, -2, axis=1).ravel()
    w = w.ravel()
    rows = np.concatenate([i, j, i, j])
    cols = np.concatenate([j, i, i, j])
    vals = np.concatenate([-w, -w, w, w])
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, n))


def cotan_stiffness(mesh: Mesh) -> sp.csr_matrix:
    """``(V, V)`` cotangent stiffness matrix (PSD, see the module docstring)."""
    cot = _cotangents(mesh.vertices, mesh.faces)
    return _assemble_symmetric(mesh.faces, 0.5 * cot, mesh.n_vertices)


def mean_value_stiffness(mesh: Mesh) -> sp.csr_matrix:
    """``(V, V)`` Floater mean-value weights as a (non-symmetric) stiffness matrix."""
    v, f = mesh.vertices, mesh.faces
    a, b = _corner_geometry(v, f)
    la = np.linalg.norm(a, axis=2)
    lb = np.linalg.norm(b, axis=2)
    cross = np.linalg.norm(np.cross(a, b), axis=2)
    dot = np.einsum("fci,fci->fc", a, b)
    tan_half = cross / (la * lb + dot)  # tan(alpha/2), alpha the angle at the corner
    i = f.ravel()
    j1 = np.roll(f, -1, axis=1).ravel()
    j2 = np.roll(f, -2, axis=1).ravel()
    w1 = (tan_half / la).ravel()
    w2 = (tan_half / lb).ravel()
    rows = np.concatenate([i, i, i, i])
    cols = np.concatenate([j1, j2, i, i])
    vals = np.concatenate([-w1, -w2, w1, w2])
    return sp.csr_matrix((vals, (rows, cols)), shape=(mesh.n_vertices, mesh.n_vertices))


def mass_matrix(mesh: Mesh, scheme: MassScheme = "voronoi") -> sp.csr_matrix:
    """``(V, V)`` mass matrix; lumped (diagonal) unless ``scheme='fem'``. Sums to the area.

    Raises:
        ParameterError: an unknown ``scheme``.
    """
    v, f, n = mesh.vertices, mesh.faces, mesh.n_vertices
    area = mesh.face_areas
    if scheme == "barycentric":
        m = np.bincount(f.ravel(), weights=np.repeat(area / 3.0, 3), minlength=n)
        return sp.diags(m).tocsr()
    if scheme == "voronoi":
        cot = _cotangents(v, f)
        a, b = _corner_geometry(v, f)
        la2 = np.einsum("fci,fci->fc", a, a)
        lb2 = np.einsum("fci,fci->fc", b, b)
        vor = (la2 * np.roll(cot, -2, axis=1) + lb2 * np.roll(cot, -1, axis=1)) / 8.0
        obtuse = cot < 0
        any_obtuse = obtuse.any(axis=1, keepdims=True)
        per_corner = np.where(any_obtuse, np.where(obtuse, area[:, None] / 2.0, area[:, None] / 4.0), vor)
        m = np.bincount(f.ravel(), weights=per_corner.ravel(), minlength=n)
        return sp.diags(m).tocsr()
    if scheme == "fem":
        rows = np.repeat(f, 3, axis=1).ravel()
        cols = np.tile(f, (1, 3)).ravel()
        local = np.where(np.eye(3, dtype=bool).ravel()[None, :], 2.0, 1.0) * (area[:, None] / 12)
        return sp.csr_matrix((local.ravel(), (rows, cols)), shape=(n, n))
    raise ParameterError(f"unknown mass scheme {scheme!r}. Fix: use one of {MASS_SCHEMES}.")


def point_cloud_laplacian(points, n_neighbors: int = 30, mollify_factor: float = 1e-5) -> Operators:
    """Tufted intrinsic-Delaunay Laplacian of a point cloud ``(V, 3)`` via ``robust-laplacian``."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 4:
        raise MeshError(f"a point cloud must be (V>=4, 3) coordinates, got shape {p.shape}.")
    if not np.isfinite(p).all():
        raise MeshError("the point cloud has NaN or infinite coordinates. Fix: drop those points.")
    L, M = robust_laplacian.point_cloud_laplacian(p, mollify_factor=mollify_factor, n_neighbors=n_neighbors)
    return Operators(sp.csr_matrix(L, dtype=np.float64), sp.csr_matrix(M, dtype=np.float64))


def laplacian(
    mesh: Mesh | np.ndarray,
    scheme: LaplacianScheme = "cotan",
    mass: MassScheme = "voronoi",
    *,
    mollify_factor: float = 1e-5,
    n_neighbors: int = 30,
) -> Operators:
    """Stiffness ``L`` and mass ``B`` of a mesh (or, with ``scheme='robust'``, a ``(V, 3)`` point cloud).

    ``mass`` is ignored by ``'robust'``; ``mollify_factor``, ``n_neighbors`` go to ``robust-laplacian``.
    Returns :class:`Operators` ``(L, B)``, both ``(V, V)`` CSR float64, ``L`` positive semidefinite.

    Raises:
        ParameterError: an unknown ``scheme`` or ``mass``.
        MeshError: a vertex no face uses (see :meth:`~torchfmap.Mesh.referenced`), a point
            cloud without ``scheme='robust'``, or a scale at which the products over- or underflow.
    """
    if scheme not in LAPLACIAN_SCHEMES:
        raise ParameterError(f"unknown Laplacian scheme {scheme!r}. Fix: use one of {LAPLACIAN_SCHEMES}.")
    if mass not in MASS_SCHEMES:
        raise ParameterError(f"unknown mass scheme {mass!r}. Fix: use one of {MASS_SCHEMES}.")
    if not isinstance(mesh, Mesh):
        if scheme != "robust":
            raise MeshError(
                "point clouds (arrays) only have scheme='robust' Laplacians. Fix: pass a Mesh, or "
                "scheme='robust'."
            )
        return point_cloud_laplacian(mesh, n_neighbors=n_neighbors, mollify_factor=mollify_factor)
    unused = np.flatnonzero(np.bincount(mesh.faces.ravel(), minlength=mesh.n_vertices) == 0)
    if len(unused):
        raise MeshError(
            f"{len(unused)} vertices are not used by any face (e.g. {unused[:5].tolist()}): they would "
            "have no mass and no stiffness, so every solve on them is singular. Fix: "
            "`sub, ids = mesh.referenced()`, work on `sub`, and map results back (vertex i of sub "
            "is vertex ids[i] of the mesh)."
        )
    if scheme == "robust":
        L, M = robust_laplacian.mesh_laplacian(mesh.vertices, mesh.faces, mollify_factor=mollify_factor)
        return Operators(sp.csr_matrix(L, dtype=np.float64), sp.csr_matrix(M, dtype=np.float64))
    with np.errstate(all="ignore"):  # over/underflow is checked just below
        stiffness = cotan_stiffness(mesh) if scheme == "cotan" else mean_value_stiffness(mesh)
        ops = Operators(stiffness, mass_matrix(mesh, mass))
        total = float(ops.mass.sum())
    finite = np.isfinite(ops.stiffness.data).all() and np.isfinite(ops.mass.data).all()
    if not (finite and 0 < total < np.inf):
        raise MeshError(
            f"the {scheme} Laplacian of this mesh has non-finite entries or no mass: its scale (largest "
            f"coordinate {np.abs(mesh.vertices).max():.3g}) over- or underflows float64 products. "
            "Fix: rescale it first, e.g. mesh.normalized()."
        )
    return ops


def total_area(mesh: Mesh) -> float:
    """Surface area ``|M|`` (sum of triangle areas)."""
    return mesh.area


def normalize_area(mesh: Mesh, center: bool = True) -> Mesh:
    """The mesh scaled to unit total area (and centred at its area-weighted centroid)."""
    return mesh.normalized(center=center)
