"""Refinement of functional maps: ICP and ZoomOut, in eigenbases and feature-aware bases.

Which applies where:

- **ICP** (Ovsjanikov et al. 2012): alternate nearest neighbours and the closest orthogonal
  ``C``. Any pair of B-orthonormal bases of equal size ``K`` in which isometries give
  orthogonal maps: eigenbases, and feature-aware bases built from *corresponding* seeds.
- **ZoomOut** (Melzi et al. 2019): alternate nearest neighbours and ``C = Φ_yᵀ B_y Φ_x[p2p]``
  while the basis grows. It needs *nested* bases. For an eigenbasis, the first ``k``
  eigenfunctions with ``k`` increasing. For feature-aware bases, pass a sequence of bases with
  growing spans (:func:`zoomout_sequence`): more scales (large to small ``t``) or more seeds
  (harmonic spans are nested in the seed set); :func:`torchfmap.pipeline.match` builds such
  sequences from corresponding landmarks.
"""

from __future__ import annotations

import numpy as np

from ..bases.basis import Basis
from ..errors import ParameterError
from .convert import fmap_to_p2p, p2p_to_fmap


def icp_refine(C_xy: np.ndarray, basis_x: Basis, basis_y: Basis, n_iter: int = 10, tol: float = 1e-10):
    """ICP refinement; returns ``(C_xy, p2p_yx)``. ``C_xy`` must be square."""
    C = np.asarray(C_xy, dtype=np.float64)
    if C.shape[0] != C.shape[1]:
        raise ParameterError(f"ICP needs a square map, got {C.shape}. Fix: use the same K on both shapes.")
    k = C.shape[0]
    p2p = fmap_to_p2p(C, basis_x, basis_y)
    for _ in range(n_iter):
        target = p2p_to_fmap(p2p, basis_x, basis_y, k, k)
        u, _, vt = np.linalg.svd(target)
        new = u @ vt
        p2p = fmap_to_p2p(new, basis_x, basis_y)
        change = np.linalg.norm(new - C) / max(np.linalg.norm(C), 1e-300)
        C = new
        if change < tol:
            break
    return C, p2p


def zoomout(C_xy: np.ndarray, basis_x: Basis, basis_y: Basis, k_final: int, step: int = 1):
    """ZoomOut by basis prefixes: from ``C_xy.shape`` up to ``(k_final, k_final)``.

    Meaningful when the first columns span nested, coarse-to-fine subspaces (eigenbases).
    Returns ``(C_xy (k_final, k_final), p2p_yx)``.
    """
    C = np.asarray(C_xy, dtype=np.float64)
    if k_final > min(basis_x.k, basis_y.k):
        raise ParameterError(f"k_final={k_final} exceeds the bases' sizes {basis_x.k}, {basis_y.k}.")
    if step < 1:
        raise ParameterError(f"step must be >= 1, got {step}.")
    k = min(C.shape)
    p2p = fmap_to_p2p(C, basis_x, basis_y)
    while k < k_final:
        k = min(k + step, k_final)
        C = p2p_to_fmap(p2p, basis_x, basis_y, k, k)
        p2p = fmap_to_p2p(C, basis_x, basis_y)
    return C, p2p


def zoomout_sequence(p2p_yx: np.ndarray, bases_x: list[Basis], bases_y: list[Basis]):
    """ZoomOut over explicit sequences of bases with growing spans (feature-aware bases).

    Starting from a point map, for each pair ``(bases_x[i], bases_y[i])``: project, then
    convert back. Returns ``(C_xy in the last pair, p2p_yx)``.
    """
    if len(bases_x) != len(bases_y) or not bases_x:
        raise ParameterError("bases_x and bases_y must be non-empty sequences of the same length.")
    p2p = np.asarray(p2p_yx)
    C = None
    for bx, by in zip(bases_x, bases_y, strict=True):
        C = p2p_to_fmap(p2p, bx, by)
        p2p = fmap_to_p2p(C, bx, by)
    return C, p2p
