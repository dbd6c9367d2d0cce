"""Refinement of functional maps: ICP and ZoomOut, in eigenbases and feature-aware bases.

Which applies where:

- **ICP** (Ovsjanikov et al. 2012): alternate nearest neighbours and the closest orthogonal
  ``C``. Any pair of B-orthonormal bases of equal size ``K`` in which isometries give
  orthogonal maps: eigenbases, and feature-aware bases built from *corresponding* seeds.
- **ZoomOut** (Melzi et al. 2019): alternate nearest neighbours and ``C = Φ_yᵀ B_y Φ_x[p2p]``
  while the basis grows. It needs *nested* bases. For an eigenbasis, the first ``k``
  eigenfunctions with ``k`` increasing. For feature-aware bases, pass a sequence of bases with
  growing spans (:func:`zoomout_sequence`): more scales (large to small ``t``) or more seeds
  (harmonic spans are nested in the seed set); or iterate at a fixed size, then move the seeds.

These functions take bases and plain settings only; the refiners that choose among them for a
kind of basis (``ICP``, ``ZoomOut``, ... in ``torchfmap.kinds.refiners``) call them.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np

from ..bases.basis import Basis
from ..errors import ParameterError
from .convert import check_p2p, fmap_to_p2p, p2p_to_fmap, values_to_p2p
from .defaults import zoomout_step

Mode = Literal["pullback", "orthogonal"]


def icp_refine(
    C_xy: np.ndarray,
    basis_x: Basis,
    basis_y: Basis,
    n_iter: int = 10,
    tol: float = 1e-10,
    *,
    mode: Mode = "orthogonal",
):
    """ICP refinement; returns ``(C_xy, p2p_yx)``. ``C_xy`` must be square.

    ``mode`` is the point-map conversion (:func:`~torchfmap.fmap.fmap_to_p2p`): ``'orthogonal'``
    (the default) is the classical choice in eigenbases; ``'pullback'`` works in any basis.
    """
    C = np.asarray(C_xy, dtype=np.float64)
    if C.shape[0] != C.shape[1]:
        raise ParameterError(f"ICP needs a square map, got {C.shape}. Fix: use the same K on both shapes.")
    k = C.shape[0]
    p2p = fmap_to_p2p(C, basis_x, basis_y, mode=mode)
    for _ in range(n_iter):
        target = p2p_to_fmap(p2p, basis_x, basis_y, k, k)
        u, _, vt = np.linalg.svd(target)
        new = u @ vt
        p2p = fmap_to_p2p(new, basis_x, basis_y, mode=mode)
        change = np.linalg.norm(new - C) / max(np.linalg.norm(C), 1e-300)
        C = new
        if change < tol:
            break
    return C, p2p


def _check_samples(subsample, basis_x: Basis, basis_y: Basis) -> tuple[np.ndarray, np.ndarray] | None:
    if subsample is None:
        return None
    try:
        sx, sy = (np.asarray(s) for s in subsample)
    except (TypeError, ValueError) as err:
        raise ParameterError("subsample must be a pair (vertices of x, vertices of y).") from err
    for s, b, name in ((sx, basis_x, "x"), (sy, basis_y, "y")):
        if s.ndim != 1 or not len(s) or not np.issubdtype(s.dtype, np.integer):
            raise ParameterError(f"subsample of {name} must be a non-empty 1-D array of vertex indices.")
        if s.min() < 0 or s.max() >= b.n_vertices:
            raise ParameterError(f"subsample of {name} has vertices outside [0, {b.n_vertices}).")
    return sx.astype(np.int64), sy.astype(np.int64)


def check_anchors(anchors, basis_x: Basis, basis_y: Basis) -> tuple[np.ndarray, np.ndarray] | None:
    """``anchors`` as ``(A_x (V_x, m), A_y (V_y, m))`` float64 arrays, one finite row per vertex of
    each basis (None passes). Raises ParameterError naming what is wrong."""
    if anchors is None:
        return None
    try:
        ax, ay = (np.asarray(a, dtype=np.float64) for a in anchors)
    except (TypeError, ValueError) as err:
        raise ParameterError("anchors must be a pair (A_x (V_x, m), A_y (V_y, m)) of arrays.") from err
    if ax.ndim != 2 or ay.ndim != 2 or ax.shape[1] != ay.shape[1] or not ax.shape[1]:
        raise ParameterError(
            f"anchors must be (V_x, m) and (V_y, m) arrays, m >= 1; got {ax.shape}, {ay.shape}."
        )
    if (len(ax), len(ay)) != (basis_x.n_vertices, basis_y.n_vertices):
        raise ParameterError(
            f"anchors have {len(ax)} and {len(ay)} rows; the bases {basis_x.n_vertices} and "
            f"{basis_y.n_vertices} vertices. Fix: one row per vertex, source first."
        )
    if not (np.isfinite(ax).all() and np.isfinite(ay).all()):
        raise ParameterError("anchors hold NaN or infinite values. Fix: finite coordinates only.")
    return ax, ay


def anchored_p2p(C, phi_x: np.ndarray, phi_y: np.ndarray, mode: Mode, anchors=None) -> np.ndarray:
    """``p2p_yx`` ``(V_y,)`` of ``C (cy, cx)`` from the first ``cx`` / ``cy`` columns of the rows
    ``phi_x``, ``phi_y`` (:func:`~torchfmap.fmap.convert.values_to_p2p`, with its ``anchors``)."""
    cy, cx = C.shape
    return values_to_p2p(C, phi_x[:, :cx], phi_y[:, :cy], mode=mode, anchors=anchors)


def _sample_step(C, bx: Basis, by: Basis, kx: int, ky: int, samples, mode: Mode, anchors=None):
    """One ZoomOut step on samples: match samples of y to samples of x with ``C``, then the
    least-squares map ``C (ky, kx)`` with ``Φ_y[S_y] C ≈ Φ_x[S_x[p2p]]`` (no mass on samples)."""
    sx, sy = samples
    phi_x, phi_y = bx.values[sx], by.values[sy]
    rows = None if anchors is None else (anchors[0][sx], anchors[1][sy])
    p2p = anchored_p2p(C, phi_x, phi_y, mode, rows)
    return np.linalg.lstsq(phi_y[:, :ky], phi_x[p2p, :kx], rcond=None)[0]


def zoomout(
    C_xy: np.ndarray,
    basis_x: Basis,
    basis_y: Basis,
    k_final: int,
    step: int | None = None,
    *,
    mode: Mode = "orthogonal",
    subsample=None,
    guard: bool = True,
    anchors: tuple[np.ndarray, np.ndarray] | None = None,
):
    """ZoomOut by basis prefixes: from ``C_xy.shape`` up to ``(k_final, k_final)``.

    Meaningful when the first columns span nested, coarse-to-fine subspaces (eigenbases).

    ``guard``: ZoomOut never returns a map worse than its start by its own energy
    (:func:`zoomout_energy`, the orthogonality defect of the map's prefixes, Melzi et al. 2019
    Eq. 2): the point map of every iteration (with ``subsample``: the start and the end) is
    scored at ``k_final`` and the best one is returned, with its ``C`` of size ``k_final``.

    Args:
        step: eigenfunctions added per iteration (default
            :func:`~torchfmap.fmap.defaults.zoomout_step` of the start size).
        mode: point-map conversion (default ``'orthogonal'``, the classical choice in
            eigenbases).
        subsample: ``(vertices of x, vertices of y)``: run the iterations on these samples only
            (nearest neighbours between samples, least-squares maps), as in the ZoomOut
            paper's accelerated variant; only the final point map uses every vertex. The cost
            of an iteration drops from ``V_x V_y k`` to ``S_x S_y k``.
        anchors: ``(A_x (V_x, m), A_y (V_y, m))``: coordinates that correspond on both shapes
            (e.g. geodesic distances to landmark pairs,
            :func:`~torchfmap.kinds.refiners.landmark_coordinates`), appended
            to the spectral embedding of every point-map step at equal weight, so the map also
            keeps each vertex's distances to the landmarks. The spectral embedding alone is
            ambiguous where the shapes are not isometric; the anchors tie it to known pairs.

    Returns:
        ``(C_xy (k_final, k_final), p2p_yx (V_y,))``.
    """
    C = np.asarray(C_xy, dtype=np.float64)
    if k_final < min(C.shape):
        raise ParameterError(
            f"k_final={k_final} is below the map's size {min(C.shape)}: ZoomOut only grows. Fix: "
            "k_final >= the current K (or truncate C_xy first)."
        )
    if k_final > min(basis_x.k, basis_y.k):
        raise ParameterError(f"k_final={k_final} exceeds the bases' sizes {basis_x.k}, {basis_y.k}.")
    step = zoomout_step(min(C.shape)) if step is None else step
    if step < 1:
        raise ParameterError(f"step must be >= 1, got {step}.")
    samples = _check_samples(subsample, basis_x, basis_y)
    anchors = check_anchors(anchors, basis_x, basis_y)
    k = min(C.shape)
    sizes = list(range(k, k_final, step)) + [k_final]
    best = EnergyGuard(basis_x, basis_y, sizes, enabled=guard)

    def to_p2p(C):
        return anchored_p2p(C, basis_x.values, basis_y.values, mode, anchors)

    if samples is None:
        p2p = to_p2p(C)
        best.offer(p2p)
        while k < k_final:
            k = min(k + step, k_final)
            C = p2p_to_fmap(p2p, basis_x, basis_y, k, k)
            p2p = to_p2p(C)
            best.offer(p2p)
    else:
        if guard:
            best.offer(to_p2p(C))
        while k < k_final:
            k = min(k + step, k_final)
            C = _sample_step(C, basis_x, basis_y, k, k, samples, mode, anchors)
        p2p = to_p2p(C)
        best.offer(p2p)
    if best.replaces(p2p):
        p2p = best.p2p_yx
        C = p2p_to_fmap(p2p, basis_x, basis_y, k_final, k_final)
    return C, p2p


class EnergyGuard:
    """ZoomOut's guard (the one rule of :func:`zoomout` and the hybrid kind's ZoomOut): every
    point map offered is scored by :func:`zoomout_energy` in ``basis_x, basis_y`` over the prefix
    ``sizes``, and the lowest-energy one is kept (the first of equal ones), so ZoomOut never
    returns a map worse than its start by its own energy. ``enabled=False``: nothing is kept."""

    def __init__(self, basis_x: Basis, basis_y: Basis, sizes, *, enabled: bool = True) -> None:
        self.basis_x, self.basis_y, self.sizes, self.enabled = basis_x, basis_y, list(sizes), enabled
        self.energy = np.inf
        #: the kept point map ``(V_y,)``, None before the first offer (or when disabled)
        self.p2p_yx: np.ndarray | None = None

    def offer(self, p2p_yx: np.ndarray) -> None:
        """Score ``p2p_yx`` and keep it if its energy is the lowest so far."""
        if self.enabled:
            energy = zoomout_energy(p2p_yx, self.basis_x, self.basis_y, self.sizes)
            if self.p2p_yx is None or energy < self.energy:
                self.energy, self.p2p_yx = energy, p2p_yx

    def replaces(self, p2p_yx: np.ndarray) -> bool:
        """Whether the kept map is another than ``p2p_yx`` (the last iterate): the caller then
        returns the kept one, refitted at the final size."""
        return self.p2p_yx is not None and self.p2p_yx is not p2p_yx


def zoomout_energy(p2p_yx: np.ndarray, basis_x: Basis, basis_y: Basis, sizes) -> float:
    """ZoomOut's energy of a point map (Melzi et al. 2019, Eq. 2): ``Σ_k ‖C_kᵀ C_k - I‖² / k``
    over the prefix sizes ``k`` in ``sizes``, ``C_k`` the ``(k, k)`` prefix of the map's
    ``C = Φ_yᵀ B_y Φ_x[p2p]`` at the largest size. Small for maps whose functional maps are
    orthogonal at every scale (near-isometries); a map mixing up parts raises it."""
    kf = max(sizes)
    C = p2p_to_fmap(p2p_yx, basis_x, basis_y, kf, kf)
    total = 0.0
    for k in sizes:
        Ck = C[:k, :k]
        total += float(np.sum((Ck.T @ Ck - np.eye(k)) ** 2)) / k
    return total


def zoomout_sequence(
    p2p_yx: np.ndarray,
    bases_x: list[Basis],
    bases_y: list[Basis],
    *,
    mode: Mode = "pullback",
    subsample=None,
):
    """ZoomOut over explicit sequences of bases with growing spans (feature-aware bases).

    Starting from a point map, for each pair ``(bases_x[i], bases_y[i])``: project, then
    convert back. With ``subsample`` ``(vertices of x, vertices of y)``, only the first
    projection uses every vertex; the later steps match samples to samples and fit ``C`` by
    least squares (as :func:`zoomout`'s accelerated variant), and only the final point map
    is computed on every vertex. ``mode``: the point-map conversion (default ``'pullback'``,
    valid in any basis). Returns ``(C_xy in the last pair, p2p_yx (V_y,))``.
    """
    if len(bases_x) != len(bases_y) or not bases_x:
        raise ParameterError("bases_x and bases_y must be non-empty sequences of the same length.")
    p2p = check_p2p(p2p_yx, bases_y[0].n_vertices, bases_x[0].n_vertices, "p2p_yx")
    samples = _check_samples(subsample, bases_x[0], bases_y[0])
    C = None
    for bx, by in zip(bases_x, bases_y, strict=True):
        if samples is None or C is None:
            C = p2p_to_fmap(p2p, bx, by)
        else:
            C = _sample_step(C, bx, by, bx.k, by.k, samples, mode)
        if samples is None:
            p2p = fmap_to_p2p(C, bx, by, mode=mode)
    if samples is not None:
        p2p = fmap_to_p2p(C, bases_x[-1], bases_y[-1], mode=mode)
    return C, p2p


class Refined(NamedTuple):
    """Result of a refiner (``torchfmap.kinds.refiners``): the map, the bases it lives in and
    their seed pairs ``(S, 2)`` (or None)."""

    C_xy: np.ndarray
    p2p_yx: np.ndarray
    basis_x: Basis
    basis_y: Basis
    seeds: np.ndarray | None
