"""Nearest-neighbour search between the rows of two embeddings: exhaustive, or local around
surface samples (:func:`surface_sampling`, :func:`local_nearest`)."""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np
from scipy.spatial import cKDTree

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
    """Index ``(M,)`` (int64) of the nearest row of ``reference (N, D)`` for every row of ``query
    (M, D)`` (ties: lowest index). Brute force in blocks of at most ``block_bytes``, float32
    products under ``precision='single'``; ``search='auto'``: a KD-tree in low dimensions."""
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
    # |r|² - 2 q·r as one GEMM [q, 1] · [-2r, |r|²]ᵀ (|q|² does not change the argmin)
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


class SurfaceSampling(NamedTuple):
    """Vertices grouped around samples: ``index (S,)`` samples; ``cell (V,)`` each vertex's nearest
    sample; ``weight (S,)`` cell areas; ``neighbors (S, m)`` nearest samples (itself first);
    ``order (V,)`` vertices by cell, cell ``c`` at ``start[c]:start[c + 1]``; ``ring (R,)`` each
    sample's neighbouring cells' vertices, sample ``s``'s at ``ring_start[s]:ring_start[s + 1]``."""

    index: np.ndarray
    cell: np.ndarray
    weight: np.ndarray
    neighbors: np.ndarray
    order: np.ndarray
    start: np.ndarray
    ring: np.ndarray
    ring_start: np.ndarray

    @property
    def n_vertices(self) -> int:
        return len(self.cell)

    def members(self, cells) -> np.ndarray:
        """The vertices ``(R,)`` of the given cells, cell by cell."""
        return np.concatenate([self.order[self.start[c] : self.start[c + 1]] for c in cells])


#: Neighbouring samples each sample knows (:class:`SurfaceSampling`): a cell and its first ring.
SAMPLE_NEIGHBORS = 8
#: A cell of more than this many times the mean vertex count is split (:func:`surface_sampling`).
CROWDED_CELL = 2
#: Voxels per sample of the thinning before farthest-point sampling (:func:`surface_sampling`).
VOXELS_PER_SAMPLE = 4


def surface_sampling(points: np.ndarray, mass: np.ndarray, n_samples: int) -> SurfaceSampling:
    """``n_samples`` evenly spread vertices of ``points (V, 3)`` and their cells, weighted by ``mass
    (V,)``; crowded cells are split (so read ``len(index)``). Raises ParameterError: ``points`` not
    ``(V, 3)`` finite, ``mass`` not ``(V,)``, or ``n_samples < 1``."""
    points = np.asarray(points, dtype=np.float64)
    mass = np.asarray(mass, dtype=np.float64).ravel()
    if points.ndim != 2 or points.shape[1] != 3 or not len(points) or not np.isfinite(points).all():
        raise ParameterError(f"points must be a finite (V, 3) array, got shape {points.shape}.")
    if mass.shape != (len(points),):
        raise ParameterError(f"mass must have one entry per vertex ({len(points)}), got {mass.shape}.")
    if n_samples < 1:
        raise ParameterError(f"n_samples must be >= 1, got {n_samples}.")
    n = len(points)
    if n_samples >= n:
        index = np.arange(n, dtype=np.int64)
    else:
        index = _split_crowded_cells(points, spread_samples(points, mass, n_samples), -(-n // n_samples))
    tree = cKDTree(points[index])
    cell = tree.query(points, k=1)[1].astype(np.int64)
    cell[index] = np.arange(len(index))
    m = min(SAMPLE_NEIGHBORS, len(index))
    neighbors = tree.query(points[index], k=m)[1].reshape(len(index), m).astype(np.int64)
    neighbors[:, 0] = np.arange(len(index))
    order = np.argsort(cell, kind="stable")
    start = np.searchsorted(cell[order], np.arange(len(index) + 1))
    weight = np.bincount(cell, weights=mass, minlength=len(index))
    ring_size = np.diff(start)[neighbors].sum(axis=1)
    ring = _segments(order, start[neighbors.ravel()], np.diff(start)[neighbors.ravel()])
    ring_start = np.concatenate([[0], np.cumsum(ring_size)])
    return SurfaceSampling(index, cell, weight, neighbors, order, start, ring, ring_start)


def _segments(values: np.ndarray, starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """``values[starts[i] : starts[i] + lengths[i]]`` for every ``i``, concatenated."""
    lengths = np.asarray(lengths, dtype=np.int64)
    total = int(lengths.sum())
    if not total:
        return values[:0]
    first = np.cumsum(lengths) - lengths
    offsets = (
        np.arange(total) - np.repeat(first, lengths) + np.repeat(np.asarray(starts, dtype=np.int64), lengths)
    )
    return values[offsets]


def _split_crowded_cells(points: np.ndarray, index: np.ndarray, per_cell: int) -> np.ndarray:
    """``index`` with farthest-point samples added in every cell of more than :data:`CROWDED_CELL`
    x ``per_cell`` vertices (one per ``per_cell`` of its vertices)."""
    cell = cKDTree(points[index]).query(points, k=1)[1]
    sizes = np.bincount(cell, minlength=len(index))
    order = np.argsort(cell, kind="stable")
    start = np.concatenate([[0], np.cumsum(sizes)])
    extra = []
    for c in np.flatnonzero(sizes > CROWDED_CELL * per_cell):  # bounded: one pass over the cells
        members = order[start[c] : start[c + 1]]
        own = int(np.flatnonzero(members == index[c])[0]) if (members == index[c]).any() else 0
        picks = _farthest_points(points[members], int(-(-sizes[c] // per_cell)), first=own)[1:]
        extra.append(members[picks])
    return np.unique(np.concatenate([index, *extra]))


def _voxel_thinning(points: np.ndarray, mass: np.ndarray, n_voxels: int) -> np.ndarray:
    """Sorted vertices ``(W,)``: per occupied voxel of a grid of about ``n_voxels`` voxels over the
    surface (area from ``mass``), the vertex nearest its centre."""
    area = float(mass.sum())
    lo = points.min(axis=0)
    extent = float(np.ptp(points, axis=0).max())
    h = np.sqrt(area / n_voxels) if area > 0 else extent / max(1.0, np.cbrt(n_voxels))
    h = h if h > 0 else 1.0
    grid = np.floor((points - lo) / h).astype(np.int64)
    centre = (grid + 0.5) * h + lo
    off = np.einsum("ij,ij->i", points - centre, points - centre)
    dims = grid.max(axis=0) + 1
    key = (grid[:, 0] * dims[1] + grid[:, 1]) * dims[2] + grid[:, 2]
    # ties by position: a vertex-permuted copy gets the same points
    order = np.lexsort((points[:, 2], points[:, 1], points[:, 0], off, key))
    first = np.ones(len(order), dtype=bool)
    first[1:] = key[order][1:] != key[order][:-1]
    return np.sort(order[first])


def spread_samples(points: np.ndarray, mass: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` distinct sorted vertices ``(S,)`` spread over ``points (V, 3)`` (areas ``mass
    (V,)``): voxel thinning, then farthest points. Deterministic, by position only."""
    candidates = _voxel_thinning(points, mass, VOXELS_PER_SAMPLE * n)
    if len(candidates) < n:  # fewer voxels than samples: every vertex is a candidate
        candidates = np.lexsort((points[:, 2], points[:, 1], points[:, 0]))
    cand = points[candidates]
    start = int(np.argmax(np.einsum("ij,ij->i", cand - cand.mean(axis=0), cand - cand.mean(axis=0))))
    return np.sort(candidates[_farthest_points(cand, n, first=start)])


def _farthest_points(points: np.ndarray, n: int, first: int = 0) -> np.ndarray:
    """At most ``n`` distinct rows of ``points (W, 3)`` by farthest-point sampling from row ``first``."""
    centred = points - points.min(axis=0)  # float32 keeps relative precision near the origin
    coords = [np.ascontiguousarray(centred[:, j], dtype=np.float32) for j in range(3)]
    chosen = np.empty(n, dtype=np.int64)
    chosen[0] = first
    dist = np.full(len(points), np.inf, dtype=np.float32)
    new, tmp = np.empty_like(dist), np.empty_like(dist)
    for i in range(n):  # bounded: n picks
        if i:
            chosen[i] = int(np.argmax(dist))
            if dist[chosen[i]] <= 0:  # every point is a copy of a chosen one
                return chosen[:i]
        new.fill(0.0)
        for c in coords:
            np.subtract(c, c[chosen[i]], out=tmp)
            np.multiply(tmp, tmp, out=tmp)
            new += tmp
        np.minimum(dist, new, out=dist)
    return chosen


def local_nearest(
    query: np.ndarray,
    reference: np.ndarray,
    sampling_q: SurfaceSampling,
    sampling_r: SurfaceSampling,
    *,
    coarse: np.ndarray | None = None,
    precision: Literal["double", "single"] = "single",
    only_samples: bool = False,
) -> np.ndarray:
    """The nearest row of ``reference (N, D)`` for every row of ``query (M, D)``, searched around
    where ``coarse (S_q,)`` (each query sample's reference sample; None: nearest sample rows) puts
    each query cell. ``only_samples``: the query's samples only (other entries -1). Raises
    ParameterError for rows that do not match the samplings, or a bad ``coarse``."""
    query = np.asarray(query)
    reference = np.asarray(reference)
    if len(query) != sampling_q.n_vertices or len(reference) != sampling_r.n_vertices:
        raise ParameterError(
            f"{len(query)} query and {len(reference)} reference rows for samplings of "
            f"{sampling_q.n_vertices} and {sampling_r.n_vertices} vertices. Fix: one row per vertex."
        )
    if query.ndim != 2 or reference.ndim != 2 or query.shape[1] != reference.shape[1]:
        raise ParameterError(f"query {query.shape} and reference {reference.shape} must be (M, D), (N, D).")
    if not (np.isfinite(query).all() and np.isfinite(reference).all()):
        raise ParameterError("nearest-neighbour inputs contain NaN or inf. Fix: check the map and bases.")
    if coarse is None:
        coarse = nearest_neighbor(query[sampling_q.index], reference[sampling_r.index], precision=precision)
    coarse = _check_coarse(coarse, len(sampling_q.index), len(sampling_r.index))
    dtype = np.float32 if precision == "single" else np.float64
    r = np.ascontiguousarray(reference, dtype=dtype)
    r_sq = np.einsum("ij,ij->i", r, r)
    out = np.full(len(query), -1, dtype=np.int64)
    if only_samples:  # in blocks of bounded memory
        q = np.ascontiguousarray(query[sampling_q.index], dtype=dtype)
        owners = np.arange(len(sampling_q.index))
        sizes = np.diff(sampling_r.ring_start)[coarse]
        per_row = max(1, int(NN_BLOCK_BYTES // (q.itemsize * max(1, q.shape[1]))))
        lo = 0
        while lo < len(owners):  # bounded: each block takes at least one sample
            hi = lo + max(1, int(np.searchsorted(np.cumsum(sizes[lo:]), per_row)))
            size = sizes[lo:hi]
            cand = _segments(sampling_r.ring, sampling_r.ring_start[coarse[lo:hi]], size)
            who = np.repeat(owners[lo:hi], size)
            d = r_sq[cand] - 2.0 * np.einsum("ij,ij->i", q[who], r[cand])
            first = np.concatenate([[0], np.cumsum(size)[:-1]])
            nearest = np.flatnonzero(d == np.minimum.reduceat(d, first)[who - lo])
            _, at = np.unique(who[nearest], return_index=True)  # the first nearest of each sample
            out[sampling_q.index[lo:hi]] = cand[nearest[at]]
            lo = hi
        return out
    q = np.ascontiguousarray(query, dtype=dtype)
    near_r = sampling_r.neighbors
    for s in range(len(sampling_q.index)):  # bounded: one block per query cell
        members = sampling_q.order[sampling_q.start[s] : sampling_q.start[s + 1]]
        if not len(members):
            continue
        cells = np.unique(near_r[coarse[sampling_q.neighbors[s]]])
        cand = sampling_r.members(cells)
        block = max(1, int(NN_BLOCK_BYTES // (q.itemsize * len(cand))))
        for lo in range(0, len(members), block):  # bounded memory: block x candidates
            rows = members[lo : lo + block]
            out[rows] = cand[np.argmin(r_sq[cand][None, :] - 2.0 * (q[rows] @ r[cand].T), axis=1)]
    return out


def search_p2p(
    query: np.ndarray,
    reference: np.ndarray,
    samplings: tuple[SurfaceSampling, SurfaceSampling] | None = None,
    *,
    coarse: np.ndarray | None = None,
    precision: Literal["double", "single"] = "single",
) -> np.ndarray:
    """The point map ``(M,)``: nearest row of ``reference (N, D)`` (``x``) for every row of ``query
    (M, D)`` (``y``): exhaustive when ``samplings`` ``(x, y)`` is None, else :func:`local_nearest`."""
    if samplings is None:
        return nearest_neighbor(query, reference, precision=precision)
    return local_nearest(query, reference, samplings[1], samplings[0], coarse=coarse, precision=precision)


def _check_coarse(coarse: np.ndarray, n_query: int, n_reference: int) -> np.ndarray:
    coarse = np.asarray(coarse)
    if coarse.shape != (n_query,) or not np.issubdtype(coarse.dtype, np.integer):
        raise ParameterError(f"coarse must be ({n_query},) sample indices, got {coarse.shape}.")
    if coarse.size and (coarse.min() < 0 or coarse.max() >= n_reference):
        raise ParameterError(f"coarse has sample indices outside [0, {n_reference}).")
    return coarse.astype(np.int64)
