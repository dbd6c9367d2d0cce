"""Point-to-point maps <-> functional maps, with memory-bounded nearest-neighbour search.

Direction is in every name: ``p2p_yx[v]`` is the vertex of ``x`` matched to vertex ``v`` of
``y`` (so functions pull back as ``f_y = f_x[p2p_yx]``), and ``C_xy`` ``(K_y, K_x)`` maps
coefficients on ``x`` to coefficients on ``y``. For B-orthonormal bases,
``C_xy = Φ_yᵀ B_y Φ_x[p2p_yx]`` and, conversely, ``Φ_y C_xy ≈ Φ_x[p2p_yx]``: each row of
``Φ_y C_xy`` is matched to its nearest row of ``Φ_x`` (``mode='pullback'``, valid in any
basis). ``mode='orthogonal'`` matches rows of ``Φ_y`` to rows of ``Φ_x C_xyᵀ`` instead, the
classical choice for (near-)orthogonal ``C`` in eigenbases.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from ..bases.basis import Basis
from ..errors import ParameterError

#: Memory budget (bytes) of one block of the brute-force distance matrix.
NN_BLOCK_BYTES = 128 * 2**20
#: At or below this dimension a KD-tree beats brute force.
KDTREE_MAX_DIM = 12


class Neighbors(NamedTuple):
    """Result of :func:`nearest_neighbor_distance`: ``index (M,)`` int64, ``distance (M,)`` float64."""

    index: np.ndarray
    distance: np.ndarray


def nearest_neighbor(
    query: np.ndarray,
    reference: np.ndarray,
    *,
    search: Literal["auto", "brute", "kdtree"] = "auto",
    precision: Literal["double", "single"] = "double",
    block_bytes: int = NN_BLOCK_BYTES,
) -> np.ndarray:
    """Index ``(M,)`` (int64) of the nearest row of ``reference (N, D)`` for every row of
    ``query (M, D)``; :func:`nearest_neighbor_distance` also returns the distances.

    Brute force evaluates ``|r|² - 2 q·r`` for a block of queries at a time in one reused
    ``(block, N)`` buffer of at most ``block_bytes`` (memory is bounded whatever ``M`` and
    ``N``); a KD-tree is used for low dimensions under ``search='auto'``. Ties go to the
    lowest index.

    ``precision='single'`` runs the brute-force products in float32 (faster: see
    ``python -m bench speed --case nn_speed``); rows whose nearest and second-nearest distances differ by
    less than float32
    round-off may then resolve differently from float64.
    """
    return _nearest(query, reference, search, precision, block_bytes)[0]


def nearest_neighbor_distance(
    query: np.ndarray,
    reference: np.ndarray,
    *,
    search: Literal["auto", "brute", "kdtree"] = "auto",
    precision: Literal["double", "single"] = "double",
    block_bytes: int = NN_BLOCK_BYTES,
) -> Neighbors:
    """:func:`nearest_neighbor` with the distances: ``Neighbors(index (M,), distance (M,))``,
    the distances in float64 whatever ``precision``."""
    idx, dist, query, reference = _nearest(query, reference, search, precision, block_bytes)
    if dist is None:
        diff = query - reference[idx]
        dist = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    return Neighbors(idx, dist)


def _nearest(query, reference, search: str, precision: str, block_bytes: int):
    """``(index, distance or None, query, reference)``: the search of :func:`nearest_neighbor`."""
    query = np.ascontiguousarray(query, dtype=np.float64)
    reference = np.ascontiguousarray(reference, dtype=np.float64)
    if query.ndim != 2 or reference.ndim != 2 or query.shape[1] != reference.shape[1]:
        raise ParameterError(
            f"query {query.shape} and reference {reference.shape} must be (M, D) and (N, D)."
        )
    if not (np.isfinite(query).all() and np.isfinite(reference).all()):
        raise ParameterError("nearest-neighbour inputs contain NaN or inf. Fix: check the map and bases.")
    if precision not in ("double", "single"):
        raise ParameterError(f"unknown precision {precision!r}. Fix: 'double' or 'single'.")
    if search == "auto":
        search = "kdtree" if query.shape[1] <= KDTREE_MAX_DIM else "brute"
    if search == "kdtree":
        dist, idx = cKDTree(reference).query(query, k=1)
        return idx.astype(np.int64), dist, query, reference
    if search != "brute":
        raise ParameterError(f"unknown search {search!r}. Fix: 'auto', 'brute' or 'kdtree'.")
    dtype = np.float32 if precision == "single" else np.float64
    # |r|² - 2 q·r as ONE product [q, 1] · [-2r, |r|²]ᵀ (|q|² is constant per row: not needed
    # for the argmin), so each block costs a GEMM and an argmin, no elementwise passes
    n_dim = reference.shape[1]
    ref_aug = np.empty((len(reference), n_dim + 1), dtype=dtype)
    ref_aug[:, :n_dim] = -2.0 * reference
    ref_aug[:, n_dim] = np.einsum("ij,ij->i", reference, reference)
    block = max(1, min(len(query), int(block_bytes // (np.dtype(dtype).itemsize * max(1, len(reference))))))
    buffer = np.empty((block, len(reference)), dtype=dtype)
    q_aug = np.ones((block, n_dim + 1), dtype=dtype)
    idx = np.empty(len(query), dtype=np.int64)
    for start in range(0, len(query), block):
        m = min(block, len(query) - start)
        q_aug[:m, :n_dim] = query[start : start + m]
        d = buffer[:m]
        np.matmul(q_aug[:m], ref_aug.T, out=d)
        idx[start : start + m] = np.argmin(d, axis=1)
    return idx, None, query, reference


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
) -> np.ndarray:
    """``p2p_yx`` ``(V_y,)`` from ``C_xy`` (``(k_y, k_x)``, using the first columns of each basis);
    ``rows`` ``(R,)``: only these vertices of ``y`` (an ``(R,)`` map).

    ``mode``: ``'pullback'`` (nearest neighbour of each row of ``Φ_y C_xy`` among the rows of
    ``Φ_x``; valid in any basis, the default) or ``'orthogonal'`` (of each row of ``Φ_y`` among
    the rows of ``Φ_x C_xyᵀ``; the classical choice in eigenbases, a kind's ``p2p_mode``).

    The nearest-neighbour search runs in float32 by default (see :func:`nearest_neighbor`):
    a vertex whose two best matches are equally good to 1e-6 may pick either.
    """
    C_xy = _check_fmap(C_xy, basis_x.k, basis_y.k)
    ky, kx = C_xy.shape
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
    """The point-map rules of :func:`fmap_to_p2p` on plain arrays: ``C_xy (K_y, K_x)``,
    ``phi_x (V_x, K_x)``, ``phi_y (V_y, K_y)`` -> ``p2p_yx (V_y,)`` (for callers whose bases
    are arrays or tensors, e.g. the learned path). ``anchors`` ``(A_x (V_x, m), A_y (V_y, m))``,
    coordinates that correspond on both shapes (checked by the caller, e.g.
    :func:`~torchfmap.fmap.zoomout`), are appended to both embeddings at equal weight: scaled so
    that their mean row norm on ``y`` is the spectral embedding's."""
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
    return nearest_neighbor(query, ref, search=search, precision=precision)


def fmap_to_p2p_bijective(
    C_xy: np.ndarray,
    C_yx: np.ndarray,
    basis_x: Basis,
    basis_y: Basis,
    *,
    search: Literal["auto", "brute", "kdtree"] = "auto",
    precision: Literal["double", "single"] = "single",
) -> np.ndarray:
    """``p2p_yx`` that is consistent with both directions (Ren et al. 2021's bijective term).

    Each vertex ``v`` of ``y`` is embedded as ``[Φ_y C_xy, Φ_y](v)`` and each vertex ``u`` of
    ``x`` as ``[Φ_x, Φ_x C_yx](u)``; nearest neighbours in this joint space favour matches that
    both maps agree on.
    """
    C_xy = _check_fmap(C_xy, basis_x.k, basis_y.k)
    C_yx = _check_fmap(C_yx, basis_y.k, basis_x.k)
    ky, kx = C_xy.shape
    if C_yx.shape != (kx, ky):
        raise ParameterError(f"C_yx must be {(kx, ky)} to pair with C_xy {C_xy.shape}, got {C_yx.shape}.")
    phi_x, phi_y = basis_x.values[:, :kx], basis_y.values[:, :ky]
    emb_y = np.hstack([phi_y @ C_xy, phi_y])
    emb_x = np.hstack([phi_x, phi_x @ C_yx])
    return nearest_neighbor(emb_y, emb_x, search=search, precision=precision)


def check_p2p(p2p: np.ndarray, n_target: int, n_source: int, name: str = "p2p") -> np.ndarray:
    """A ``(n_target,)`` int map into ``[0, n_source)``, or a clear error."""
    p2p = np.asarray(p2p)
    if p2p.shape != (n_target,):
        raise ParameterError(f"{name} must have one entry per vertex ({n_target}), got shape {p2p.shape}.")
    if not np.issubdtype(p2p.dtype, np.integer):
        raise ParameterError(f"{name} must hold integer vertex indices, got {p2p.dtype}.")
    if p2p.size and (p2p.min() < 0 or p2p.max() >= n_source):
        raise ParameterError(f"{name} has indices outside [0, {n_source}). Fix: maps are 0-based.")
    return p2p.astype(np.int64)


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
