"""Point-to-point maps <-> functional maps: ``p2p_yx[v]`` is the vertex of ``x`` matched to vertex
``v`` of ``y``; ``C_xy`` ``(K_y, K_x)`` maps coefficients on ``x`` to coefficients on ``y``."""

from __future__ import annotations

from typing import Literal

import numpy as np

from .._util.checks import check_p2p
from ..bases.basis import Basis
from ..errors import ParameterError
from .nearest import SurfaceSampling, nearest_neighbor, search_p2p


def _check_fmap(C_xy: np.ndarray, k_x: int, k_y: int) -> np.ndarray:
    C_xy = np.asarray(C_xy, dtype=np.float64)
    if C_xy.ndim != 2 or C_xy.shape[0] > k_y or C_xy.shape[1] > k_x:
        raise ParameterError(
            f"C_xy has shape {C_xy.shape}, but the bases have K_y={k_y}, K_x={k_x}. Fix: C_xy is (K_y, K_x)."
        )
    if not np.isfinite(C_xy).all():
        raise ParameterError("C_xy contains NaN or inf.")
    return C_xy


def fmap_to_p2p(
    C_xy: np.ndarray,
    basis_x: Basis,
    basis_y: Basis,
    *,
    mode: Literal["pullback", "orthogonal"] = "pullback",
    search: Literal["auto", "brute", "kdtree"] = "auto",
    precision: Literal["double", "single"] = "single",
    rows: np.ndarray | None = None,
    samplings: tuple[SurfaceSampling, SurfaceSampling] | None = None,
) -> np.ndarray:
    """``p2p_yx`` ``(V_y,)`` from ``C_xy`` (``(k_y, k_x)``, the first columns of each basis);
    ``rows`` ``(R,)``: only these vertices of ``y``. ``mode``: ``'pullback'`` (rows of ``Φ_y C_xy``
    among rows of ``Φ_x``) or ``'orthogonal'`` (rows of ``Φ_y`` among rows of ``Φ_x C_xyᵀ``).
    ``samplings``: both shapes' :class:`SurfaceSampling` ``(x, y)``: search locally (not with
    ``rows``; ``search`` then does not apply)."""
    C_xy = _check_fmap(C_xy, basis_x.k, basis_y.k)
    ky, kx = C_xy.shape
    if samplings is not None and rows is None:
        query, reference = embedding_pair(C_xy, basis_x.values[:, :kx], basis_y.values[:, :ky], mode=mode)
        return search_p2p(query, reference, samplings, precision=precision)
    phi_y = basis_y.values[:, :ky] if rows is None else basis_y.values[rows, :ky]
    return values_to_p2p(C_xy, basis_x.values[:, :kx], phi_y, mode=mode, search=search, precision=precision)


def values_to_p2p(
    C_xy: np.ndarray,
    phi_x: np.ndarray,
    phi_y: np.ndarray,
    *,
    mode: Literal["pullback", "orthogonal"],
    search: Literal["auto", "brute", "kdtree"] = "auto",
    precision: Literal["double", "single"] = "single",
    anchors: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """:func:`fmap_to_p2p` on arrays ``C_xy (K_y, K_x)``, ``phi_x (V_x, K_x)``, ``phi_y (V_y, K_y)``
    -> ``p2p_yx (V_y,)``; ``anchors`` ``(A_x (V_x, m), A_y (V_y, m))`` appended to the embeddings."""
    query, ref = embedding_pair(C_xy, phi_x, phi_y, mode=mode, anchors=anchors)
    return nearest_neighbor(query, ref, search=search, precision=precision)


def embedding_pair(
    C_xy: np.ndarray,
    phi_x: np.ndarray,
    phi_y: np.ndarray,
    *,
    mode: Literal["pullback", "orthogonal"],
    anchors: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``(E_y (V_y, D), E_x (V_x, D))``: the rows whose nearest neighbours are :func:`values_to_p2p`."""
    if mode == "pullback":
        query, ref = phi_y @ C_xy, phi_x
    elif mode == "orthogonal":
        query, ref = phi_y, phi_x @ C_xy.T
    else:
        raise ParameterError(f"unknown mode {mode!r}. Fix: 'pullback' or 'orthogonal'.")
    if anchors is not None:
        ax, ay = anchors
        norm = np.linalg.norm(ay, axis=1).mean()
        w = np.linalg.norm(query, axis=1).mean() / norm if norm > 0 else 0.0
        query, ref = np.hstack([query, w * ay]), np.hstack([ref, w * ax])
    return query, ref


def fmap_to_p2p_bijective(
    C_xy: np.ndarray,
    C_yx: np.ndarray,
    basis_x: Basis,
    basis_y: Basis,
    *,
    search: Literal["auto", "brute", "kdtree"] = "auto",
    precision: Literal["double", "single"] = "single",
) -> np.ndarray:
    """``p2p_yx`` consistent with both directions (Ren et al. 2021): nearest neighbours of
    ``[Φ_y C_xy, Φ_y]`` among ``[Φ_x, Φ_x C_yx]``."""
    C_xy = _check_fmap(C_xy, basis_x.k, basis_y.k)
    C_yx = _check_fmap(C_yx, basis_y.k, basis_x.k)
    ky, kx = C_xy.shape
    if C_yx.shape != (kx, ky):
        raise ParameterError(f"C_yx must be {(kx, ky)} to pair with C_xy {C_xy.shape}, got {C_yx.shape}.")
    phi_x, phi_y = basis_x.values[:, :kx], basis_y.values[:, :ky]
    emb_y = np.hstack([phi_y @ C_xy, phi_y])
    emb_x = np.hstack([phi_x, phi_x @ C_yx])
    return nearest_neighbor(emb_y, emb_x, search=search, precision=precision)


def p2p_to_fmap(
    p2p_yx: np.ndarray, basis_x: Basis, basis_y: Basis, k_x: int | None = None, k_y: int | None = None
):
    """``C_xy = Φ_yᵀ B_y Φ_x[p2p_yx]`` (``(k_y, k_x)``): the B-projection of pulled-back functions."""
    p2p_yx = check_p2p(p2p_yx, basis_y.n_vertices, basis_x.n_vertices, "p2p_yx")
    kx = basis_x.k if k_x is None else k_x
    ky = basis_y.k if k_y is None else k_y
    if kx > basis_x.k or ky > basis_y.k:
        raise ParameterError(f"k_x={kx}, k_y={ky} exceed the bases' sizes {basis_x.k}, {basis_y.k}.")
    phi_y = basis_y.values[:, :ky]
    return phi_y.T @ (basis_y.mass @ basis_x.values[p2p_yx, :kx])
