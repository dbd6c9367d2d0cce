"""The heat-kernel action ``exp(-t A) X``, ``A = B⁻¹L``, without an eigendecomposition.

Default kernel (``'delta'``): ``K_t(p, ·) = exp(-t A) B⁻¹ e_p = Σ_k exp(-λ_k t) φ_k φ_k(p)``,
symmetric, integrating to 1; ``'indicator'``: ``exp(-t A) e_p``. Times are absolute. Methods:
``krylov`` (default; shift-and-invert Lanczos, :mod:`torchfmap.operators.krylov`), ``rational``
(Carathéodory-Fejér partial fractions, complex shifted solves ``(tL + z_j B) x = B u``),
``backward_euler`` (``n_steps`` implicit steps) and ``spectral`` (``n_eigen`` eigenpairs).
``local=True`` / ``'auto'`` solves each seed on a geodesic patch (Dirichlet zero outside).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Literal

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from .._util.checks import (
    check_symmetric,
    check_times,
    check_tolerance,
    check_vertex_indices,
    lumped_diagonal,
)
from ..errors import ParameterError
from .eigen import eigenpairs
from .krylov import krylov_heat
from .laplacian import Operators
from .solvers import factorize

Method = Literal["krylov", "rational", "backward_euler", "spectral"]
METHODS = ("krylov", "rational", "backward_euler", "spectral")
#: Patches larger than this fraction of the mesh are solved globally under ``local='auto'``.
LOCAL_MAX_FRACTION = 0.25
#: ``local='auto'`` tries patches only for times whose Gaussian support is below this fraction of the area.
LOCAL_AUTO_FRACTION = 0.05
#: Most times a local patch grows by 1.5x.
LOCAL_MAX_GROWTH = 40
#: Highest CF order computed reliably in double precision.
CF_MAX_ORDER = 14


@lru_cache(maxsize=16)
def cf_poles(n: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Poles ``z (n,)``, residues ``c (n,)`` and measured error of the CF approximation of exp.

    ``r(x) = Σ_j c_j / (x - z_j)`` approximates ``exp(x)`` on ``(-∞, 0]`` (Trefethen, Weideman &
    Schmelzer 2006, Fig. 4.1); the error is measured on a dense grid. Raises :class:`ParameterError`
    for an odd ``n`` or one outside ``[2, CF_MAX_ORDER]``.
    """
    if n < 2 or n % 2 or n > CF_MAX_ORDER:
        raise ParameterError(f"CF order must be even and in [2, {CF_MAX_ORDER}], got {n}.")
    n_cheb, n_fft, scale = 75, 1024, 9.0
    w = np.exp(2j * np.pi * np.arange(n_fft) / n_fft)
    t = w.real
    transplanted = np.exp(scale * (t - 1) / (t + 1 + 1e-16))
    c = np.real(np.fft.fft(transplanted)) / n_fft
    analytic = np.polyval(c[n_cheb::-1], w)
    u_mat, sing, vh = np.linalg.svd(sla.hankel(c[1 : n_cheb + 1]))
    sigma = float(sing[n])
    u = u_mat[::-1, n]
    v = vh[n, :]
    pad = np.zeros(n_fft - n_cheb)
    blaschke = np.fft.fft(np.concatenate([u, pad])) / np.fft.fft(np.concatenate([v, pad]))
    extended = analytic - sigma * w**n_cheb * blaschke
    roots = np.roots(v)
    q = roots[np.abs(roots) > 1]
    numerator = np.real(np.fft.fft(extended * np.polyval(np.poly(q), w)) / n_fft)[n::-1]
    res = np.array(
        [np.polyval(numerator, qj) / np.polyval(np.poly(np.delete(q, j)), qj) for j, qj in enumerate(q)]
    )
    z = scale * (q - 1) ** 2 / (q + 1) ** 2
    c_res = 4 * res * z / (q**2 - 1)
    if len(z) != n:
        raise ParameterError(f"CF order {n}: found {len(z)} poles (round-off). Fix: use a lower order.")
    x = -np.concatenate([np.linspace(0.0, 60.0, 6001), np.logspace(-8, 8, 3201)])
    approx = (c_res[None, :] / (x[:, None] - z[None, :])).sum(axis=1)
    return z, c_res, float(np.abs(approx - np.exp(x)).max())


def cf_order_for(tol: float) -> int:
    """Smallest even CF order whose measured uniform error is below ``tol / 10`` (capped)."""
    for n in range(4, CF_MAX_ORDER + 1, 2):
        if cf_poles(n)[2] < tol / 10:
            return n
    return CF_MAX_ORDER


def _mass_solve(B: sp.spmatrix, X: np.ndarray) -> np.ndarray:
    d = lumped_diagonal(B)
    if d is not None:
        return X / d[:, None] if X.ndim == 2 else X / d
    return factorize(B, spd=True).solve(X)


def _rational(L, B, X, times, tol) -> np.ndarray:
    # the error is uniform relative to max|x|; a spread-out point source needs that much more accuracy
    total = np.abs(np.ones(X.shape[0]) @ (B @ X))
    spread = np.max(np.abs(X), axis=0) * B.sum() / np.maximum(total, 1e-300)
    z, c, _ = cf_poles(cf_order_for(tol / max(1.0, float(spread.max()))))
    upper = z.imag > 0  # poles come in conjugate pairs: sum one half, take 2 Re
    BX = B @ X
    out = np.empty((len(times),) + X.shape)
    for ti, t in enumerate(times):
        acc = np.zeros(X.shape, dtype=complex)
        for zj, cj in zip(z[upper], c[upper], strict=True):
            # r(-tA) x = sum_j c_j (-tA - z_j)^{-1} x = -sum_j c_j (tL + z_j B)^{-1} B x
            acc -= cj * factorize(t * L + zj * B).solve(BX.astype(complex))
        real_poles = np.abs(z.imag) < 1e-14
        for zj, cj in zip(z[real_poles], c[real_poles], strict=True):
            acc -= 0.5 * cj * factorize(t * L + zj.real * B).solve(BX)
        out[ti] = 2 * acc.real
    return out


def _backward_euler(L, B, X, times, n_steps: int) -> np.ndarray:
    out = np.empty((len(times),) + X.shape)
    for ti, t in enumerate(times):
        fac = factorize(B + (t / n_steps) * L, spd=True)
        u = X.copy()
        for _ in range(n_steps):
            u = fac.solve(B @ u)
        out[ti] = u
    return out


def _spectral(L, B, X, times, n_eigen: int) -> np.ndarray:
    lam, phi = eigenpairs(L, B, n_eigen)
    coeffs = phi.T @ (B @ X)  # (k, S)
    return np.stack([phi @ (np.exp(-lam * t)[:, None] * coeffs) for t in times])


def heat_apply(
    operators: Operators,
    X: np.ndarray,
    abs_times,
    method: Method = "krylov",
    *,
    tol: float = 1e-8,
    n_steps: int = 1,
    n_eigen: int = 200,
    factors: dict | None = None,
) -> np.ndarray:
    """``exp(-t B⁻¹L) X`` for every absolute time: ``X (V, S)`` (or ``(V,)``) -> ``(T, V, S)``.

    ``factors``: the ``krylov`` factorisations, kept by the caller between calls. Raises
    :class:`ParameterError` for times not finite and > 0, an unknown method, or ``tol`` outside
    ``[1e-14, 1)``.
    """
    L, B = operators
    tol = check_tolerance(tol)
    times = check_times(abs_times)
    if method not in METHODS:
        raise ParameterError(f"unknown heat method {method!r}. Fix: use one of {METHODS}.")
    X = np.asarray(X, dtype=np.float64)
    single = X.ndim == 1
    X = X[:, None] if single else X
    if method == "krylov":
        out = krylov_heat(L, B, X, times, tol, factors=factors)
    elif method == "rational":
        out = _rational(L, B, X, times, tol)
    elif method == "backward_euler":
        if n_steps < 1:
            raise ParameterError(f"n_steps must be >= 1, got {n_steps}.")
        out = _backward_euler(L, B, X, times, n_steps)
    else:
        out = _spectral(L, B, X, times, n_eigen)
    return out[:, :, 0] if single else out


def _initial(B, seeds: np.ndarray, n: int, kernel: str) -> np.ndarray:
    E = np.zeros((n, len(seeds)))
    E[seeds, np.arange(len(seeds))] = 1.0
    if kernel == "indicator":
        return E
    if kernel == "delta":
        return _mass_solve(B, E)
    raise ParameterError(f"kernel must be 'delta' or 'indicator', got {kernel!r}.")


def _edge_graph(L: sp.spmatrix, vertices: np.ndarray) -> sp.csr_matrix:
    coo = sp.coo_matrix(L)
    off = coo.row != coo.col
    r, c = coo.row[off], coo.col[off]
    lengths = np.linalg.norm(vertices[r] - vertices[c], axis=1)
    return sp.csr_matrix((lengths, (r, c)), shape=L.shape)


def _local_kernel(L, B, graph, seed, t, mean_edge, method, kernel, tol, n_steps, local):
    """Kernel of one seed on a geodesic patch grown by 1.5x until its outer 20 % is below ``tol``
    of the peak; ``(patch, values)``, or None when it outgrows ``LOCAL_MAX_FRACTION``."""
    n = L.shape[0]
    radius = max(np.sqrt(4.0 * t * np.log(1.0 / tol)), 3.0 * mean_edge)
    for _ in range(LOCAL_MAX_GROWTH):
        dist = dijkstra(graph, indices=seed, limit=radius)
        patch = np.flatnonzero(np.isfinite(dist))
        if local == "auto" and len(patch) > LOCAL_MAX_FRACTION * n:
            return None
        Lp = L[patch][:, patch]
        Bp = B[patch][:, patch]
        X0 = _initial(Bp, np.array([int(np.searchsorted(patch, seed))]), len(patch), kernel)
        vals = heat_apply((Lp, Bp), X0, [t], method, tol=tol, n_steps=n_steps)[0, :, 0]
        band = dist[patch] > 0.8 * radius
        if len(patch) == n or np.abs(vals[band]).max(initial=0.0) <= tol * np.abs(vals).max():
            return patch, vals
        radius *= 1.5
    return None  # the patch never settled: the caller solves this seed globally


def heat_kernels(
    operators: Operators,
    seeds,
    abs_times,
    method: Method = "krylov",
    *,
    kernel: Literal["delta", "indicator"] = "delta",
    tol: float = 1e-8,
    local: bool | Literal["auto"] = False,
    vertices: np.ndarray | None = None,
    n_steps: int = 1,
    n_eigen: int = 200,
    factors: dict | None = None,
) -> np.ndarray:
    """Heat kernels ``K_t(p_i, ·)``, float64 ``(T, V, S)`` (global ``krylov`` lays it out ``(V, T, S)``).

    Args:
        operators: ``(L, B)`` of the mesh (``L`` symmetric); seeds: ``(S,)`` vertex indices;
            abs_times: ``(T,)`` absolute times > 0.
        kernel: ``'delta'`` (``exp(-tA) B⁻¹ e_p``) or ``'indicator'`` (``exp(-tA) e_p``).
        local: solve on a geodesic patch of each seed (``'auto'``: when small); needs ``vertices (V, 3)``.
        factors: as :func:`heat_apply` (global solves only).

    Raises:
        ParameterError / SeedError: bad seeds, times, ``tol`` or kernel, a non-symmetric ``L``, or
            ``local`` without ``vertices``.
    """
    L, B = operators
    n = L.shape[0]
    tol = check_tolerance(tol)
    seeds = check_vertex_indices(seeds, n, "seeds")
    times = check_times(abs_times)
    check_symmetric(L, "heat kernels", "laplacian(mesh, scheme='cotan') or scheme='robust'")
    if not local or method == "spectral":
        X0 = _initial(B, seeds, n, kernel)
        return heat_apply(
            (L, B), X0, times, method, tol=tol, n_steps=n_steps, n_eigen=n_eigen, factors=factors
        )
    if vertices is None:
        raise ParameterError("local heat kernels need the mesh vertices. Fix: pass vertices=mesh.vertices.")
    graph = _edge_graph(L, np.asarray(vertices))
    mean_edge = float(graph.data.mean())
    area = float(B.sum())
    out = np.zeros((len(times), n, len(seeds)))
    reach = np.pi * 4.0 * times * np.log(1.0 / tol)  # area inside the Gaussian support radius
    far = np.flatnonzero(reach > LOCAL_AUTO_FRACTION * area) if local == "auto" else np.zeros(0, int)
    if len(far):  # kernels reaching too far: all seeds, these times, one global solve
        X0 = _initial(B, seeds, n, kernel)
        out[far] = heat_apply((L, B), X0, times[far], method, tol=tol, n_steps=n_steps)
    for ti in np.setdiff1d(np.arange(len(times)), far):
        fallback = []
        for si, s in enumerate(seeds):
            values = _local_kernel(
                L, B, graph, int(s), times[ti], mean_edge, method, kernel, tol, n_steps, local
            )
            if values is None:
                fallback.append(si)
            else:
                out[ti, values[0], si] = values[1]
        if fallback:
            X0 = _initial(B, seeds[fallback], n, kernel)
            out[ti][:, fallback] = heat_apply(
                (L, B), X0, times[ti : ti + 1], method, tol=tol, n_steps=n_steps
            )[0]
    return out
