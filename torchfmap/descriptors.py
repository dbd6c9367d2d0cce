"""Pointwise descriptors ``(V, D)``: HKS and WKS (spectral: eigenpairs ``evals (k,)``, ``evecs (V, k)`` of
``L φ = λ B φ``), SHOT (local), landmark descriptors, normalisation, checks."""

from __future__ import annotations

from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ._util.checks import check_times, check_vertex_indices
from .errors import ParameterError
from .operators.heat import heat_kernels

#: WKS energies and width factor: ``sigma = WKS_SIGMA * (e_max - e_min) / E``.
WKS_ENERGIES = 100
WKS_SIGMA = 7.0
#: Relative heat times of the landmark descriptors (two kernels per landmark).
LANDMARK_TIMES = (1e-2, 3e-2)
#: SHOT's grid: azimuth sectors, elevation halves, radial shells, bins of the normals' cosine.
SHOT_GRID = (8, 2, 2, 11)


def _check_spectrum(evals: np.ndarray, evecs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    evals, evecs = np.asarray(evals, dtype=np.float64), np.asarray(evecs, dtype=np.float64)
    if evecs.ndim != 2 or evals.shape != (evecs.shape[1],):
        raise ParameterError(
            f"eigenvalues {evals.shape} and eigenvectors {evecs.shape} disagree: need (k,) and (V, k)."
        )
    if evals.size < 2:
        raise ParameterError("spectral descriptors need at least 2 eigenpairs.")
    return evals, evecs


def hks(eigenvalues, eigenvectors, n_times: int = 16, abs_times=None) -> np.ndarray:
    """Heat kernel signature ``Σ_k exp(-λ_k t) φ_k(x)²``, ``(V, T)``, of eigenpairs ``(k,)``, ``(V, k)``: at
    ``abs_times`` ``(T,)`` (> 0), default ``n_times`` log-spaced in ``[4 ln 10 / λ_max, 4 ln 10 / λ_1]``.
    :class:`ParameterError` for mismatched eigenpairs, fewer than 2, or a time <= 0."""
    evals, evecs = _check_spectrum(eigenvalues, eigenvectors)
    times = abs_times
    if times is None:
        lam1 = evals[evals > 1e-10 * evals.max()].min()
        times = np.geomspace(4 * np.log(10) / evals.max(), 4 * np.log(10) / lam1, n_times)
    times = check_times(times, "HKS times", "e.g. abs_times=None")
    return (evecs**2) @ np.exp(-np.outer(np.maximum(evals, 0), times))


def _wks_weights(evals: np.ndarray, n_energies: int, sigma_factor: float) -> np.ndarray:
    """``(k, E)`` normalised Gaussian weights of each eigenvalue at each log-energy."""
    keep = evals > 1e-10 * evals.max()  # the constant eigenfunction carries no information
    loge = np.log(np.where(keep, evals, 1.0))
    e_min, e_max = loge[keep].min(), loge[keep].max()
    energies = np.linspace(e_min, e_max, n_energies)
    sigma = sigma_factor * (e_max - e_min) / n_energies
    w = np.exp(-((energies[None, :] - loge[:, None]) ** 2) / (2 * sigma**2)) * keep[:, None]
    return w / np.maximum(w.sum(axis=0, keepdims=True), 1e-300)


def wks(
    eigenvalues, eigenvectors, n_energies: int = WKS_ENERGIES, sigma_factor: float = WKS_SIGMA
) -> np.ndarray:
    """Wave kernel signature ``(V, n_energies)``; ParameterError unless ``n_energies >= 1``, sigma > 0."""
    evals, evecs = _check_spectrum(eigenvalues, eigenvectors)
    if isinstance(n_energies, bool) or int(n_energies) != n_energies or n_energies < 1:
        raise ParameterError(f"n_energies must be an integer >= 1, got {n_energies!r}.")
    if not np.isfinite(sigma_factor) or sigma_factor <= 0:
        raise ParameterError(f"sigma_factor must be finite and > 0, got {sigma_factor!r}. Fix: e.g. 7.")
    return (evecs**2) @ _wks_weights(evals, n_energies, sigma_factor)


def landmark_descriptors(
    landmarks,
    *,
    kernel: Literal["heat", "wks"] = "heat",
    operators=None,
    area: float | None = None,
    times=LANDMARK_TIMES,
    evals=None,
    evecs=None,
    n_energies: int = 20,
    tol: float = 1e-6,
) -> np.ndarray:
    """Functions centred at landmarks: ``(V, L * n)`` (``n`` times or energies per landmark).
    ``kernel='heat'``: heat kernels ``K_t(l, ·)`` at relative ``times`` (absolute ``t·|M|``; needs
    ``operators=(L, B)``); ``'wks'``: wave kernels ``Σ_k w_e(λ_k) φ_k(l) φ_k(·)`` (needs ``evals``,
    ``evecs``). :class:`ParameterError` for an unknown ``kernel``, a missing input, or bad landmarks."""
    if kernel == "heat":
        if operators is None:
            raise ParameterError("heat landmark descriptors need operators=(L, B).")
        L, B = operators
        n = L.shape[0]
        lm = check_vertex_indices(landmarks, n, "landmarks")
        total = float(B.sum()) if area is None else float(area)
        K = heat_kernels((L, B), lm, np.asarray(times, dtype=np.float64) * total, tol=tol)  # (T, V, L)
        return K.transpose(1, 2, 0).reshape(n, -1)
    if kernel == "wks":
        evals, evecs = _check_spectrum(evals, evecs)
        lm = check_vertex_indices(landmarks, evecs.shape[0], "landmarks")
        w = _wks_weights(evals, n_energies, WKS_SIGMA)  # (k, E)
        coeffs = evecs[lm][:, :, None] * w[None]  # (L, k, E)
        return np.einsum("vk,lke->vle", evecs, coeffs).reshape(evecs.shape[0], -1)
    raise ParameterError(f"unknown landmark descriptor kernel {kernel!r}. Fix: 'heat' or 'wks'.")


def normalize_descriptors(F: np.ndarray, mass=None) -> np.ndarray:
    """Scale each column to unit norm (B-norm when ``mass`` is given); zero columns stay zero."""
    F = np.asarray(F, dtype=np.float64)
    if mass is None:
        norms = np.linalg.norm(F, axis=0)
    else:
        norms = np.sqrt(np.maximum(np.einsum("ij,ij->j", F, sp.csr_matrix(mass) @ F), 0.0))
    return F / np.where(norms > 0, norms, 1.0)


def check_descriptors(F: np.ndarray, n_vertices: int, name: str = "descriptors") -> np.ndarray:
    """``(V, D)`` finite float64 descriptors, or a clear error."""
    F = np.asarray(F, dtype=np.float64)
    F = F[:, None] if F.ndim == 1 else F
    if F.ndim != 2 or F.shape[0] != n_vertices:
        raise ParameterError(
            f"{name} must be (V, D) with V={n_vertices}, got shape {F.shape}. Fix: one row per vertex."
        )
    bad = np.flatnonzero(~np.isfinite(F).all(axis=0))
    if len(bad):
        raise ParameterError(
            f"{name} has non-finite values in columns {bad[:8].tolist()}. Fix: drop or repair them "
            "(e.g. a WKS of a mesh with zero-area vertices)."
        )
    return F


#: Vertices whose SHOT neighbour lists are held at once.
SHOT_BLOCK = 4096
#: Vertices up to which SHOT's support is every vertex; above, a voxel quadrature of about this many points.
SHOT_SUPPORT = 20_000


def shot(mesh, radius: float, support: int = SHOT_SUPPORT) -> np.ndarray:
    """SHOT signatures (Tombari et al. 2010) of a :class:`~torchfmap.Mesh`: ``(V, 352)``, unit L2 norm per
    vertex (zero with fewer than 5 other support points within ``radius``, finite > 0 in mesh units, else
    :class:`ParameterError`). Local, invariant to rigid motions: per local frame and :data:`SHOT_GRID`
    cell, an area-weighted histogram of the normals' cosine to the frame's ``z`` axis. The support is
    every vertex up to ``support`` vertices (an integer >= 1000) and above it a voxel quadrature of the
    surface (:func:`shot_support`, about ``support`` points), so the work per vertex stays bounded."""
    if not (np.isfinite(radius) and radius > 0):
        raise ParameterError(f"radius must be finite and > 0, got {radius!r}. Fix: e.g. 0.08 * sqrt(area).")
    if isinstance(support, bool) or not isinstance(support, (int, np.integer)) or support < 1000:
        raise ParameterError(f"support must be an integer >= 1000, got {support!r}. Fix: e.g. 20000.")
    vertices = mesh.vertices
    areas = np.bincount(mesh.faces.ravel(), np.repeat(mesh.face_areas / 3, 3), mesh.n_vertices)
    if mesh.n_vertices > support:
        points, areas, normals = shot_support(vertices, areas, mesh.vertex_normals, support)
        itself = np.full(len(vertices), -1)  # no support point is a vertex
    else:
        points, normals, itself = vertices, mesh.vertex_normals, np.arange(len(vertices))
    n_az, n_el, n_rad, n_cos = SHOT_GRID
    out = np.zeros((len(vertices), n_az * n_el * n_rad * n_cos))
    tree = cKDTree(points)
    for start in range(0, len(vertices), SHOT_BLOCK):  # neighbour lists a block at a time (memory)
        balls = tree.query_ball_point(vertices[start : start + SHOT_BLOCK], radius)
        for p, idx in enumerate(balls, start):  # bounded: one pass over the vertices
            idx = np.asarray(idx, dtype=np.int64)
            idx = idx[idx != itself[p]]  # the vertex itself has no direction
            d = points[idx] - vertices[p]
            dist = np.sqrt(np.einsum("ij,ij->i", d, d))
            if itself[p] < 0:  # nor has a support point on it (a cube holding this vertex alone)
                off = dist > 1e-9 * radius
                idx, d, dist = idx[off], d[off], dist[off]
            if len(idx) < 5:
                continue
            a = areas[idx]
            w = (radius - dist) * a
            _, axes = np.linalg.eigh((d * w[:, None]).T @ d / w.sum())
            x, z = axes[:, 2], axes[:, 0]
            dx, dz, nz = d @ x, d @ z, normals[idx] @ z
            if np.sum(a * np.sign(dx)) < 0:
                x, dx = -x, -dx
            if np.sum(a * np.sign(nz)) < 0:
                z, dz, nz = -z, -dz, -nz
            azimuth = ((np.arctan2(d @ np.cross(z, x), dx) + np.pi) / (2 * np.pi) * n_az).astype(int) % n_az
            cell = (azimuth * n_el + (dz > 0)) * n_rad + (dist > radius / 2)
            pos = (np.clip(nz, -1.0, 1.0) + 1) / 2 * (n_cos - 1)
            lo = np.minimum(np.floor(pos).astype(int), n_cos - 2)
            frac = pos - lo
            h = np.bincount(cell * n_cos + lo, a * (1 - frac), out.shape[1])
            h += np.bincount(cell * n_cos + lo + 1, a * frac, out.shape[1])
            out[p] = h / np.linalg.norm(h)
    return out


def shot_support(
    vertices: np.ndarray, areas: np.ndarray, normals: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A voxel quadrature of a surface: ``(points (S, 3), areas (S,), normals (S, 3))``, one point per
    occupied cube of edge ``sqrt(sum(areas) / n)`` (about ``n`` to ``3 n`` of them), at the area-weighted
    mean of its vertices, carrying their area and their area-weighted mean unit normal. ``vertices``,
    ``normals`` ``(V, 3)`` and ``areas`` ``(V,)`` (lumped vertex areas). The cubes lie in the surface's
    own frame (area-weighted centroid and principal axes, each axis signed by its third moment), so a
    rigid motion or a uniform scale of the surface moves the points with it."""
    edge = np.sqrt(areas.sum() / n)
    centred = vertices - areas @ vertices / areas.sum()
    _, axes = np.linalg.eigh((centred * areas[:, None]).T @ centred)
    local = centred @ axes
    local *= np.where(areas @ local**3 < 0, -1.0, 1.0)
    cells = np.floor((local - local.min(axis=0)) / edge).astype(np.int64)
    _, cell = np.unique(cells, axis=0, return_inverse=True)
    cell = cell.ravel()
    total = np.bincount(cell, areas)
    safe = np.where(total > 0, total, 1.0)
    points = np.stack([np.bincount(cell, areas * vertices[:, i]) for i in range(3)], axis=1) / safe[:, None]
    summed = np.stack([np.bincount(cell, areas * normals[:, i]) for i in range(3)], axis=1)
    length = np.linalg.norm(summed, axis=1)
    return points, total, summed / np.where(length > 0, length, 1.0)[:, None]
