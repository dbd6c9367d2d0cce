"""Partial-to-partial matching of two parts of one whole that overlap only partly, in the same units: a
bootstrap partial map, its consistent core (:func:`consistent_core`) and trilateration from seeds on it
(:func:`trilaterate`), whose residual marks the overlap. Why: docs/guide.md, "Partial shapes"."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..bases.prepared import PreparedShape, prepare_shape
from ..errors import ParameterError
from ..fmap import p2p_to_fmap
from ..fmap.defaults import DEFAULT_K, W_DCOMM, W_LAP_SMOOTH, W_LMK, W_ORIENT
from ..fmap.nearest import search_p2p
from .partial import AREA_SLACK, MIN_AREA_RATIO, common_frame, match_partial, partial_rank
from .results import MatchResult

__all__ = ["PairMatchResult", "consistent_core", "match_partial_pair", "settle_seeds", "trilaterate"]

#: Anchors of :func:`consistent_core`, spread by farthest points over the part.
CORE_ANCHORS = 100
#: The share of the consistent anchors a vertex (or anchor) must agree with to join them.
CORE_AGREEMENT = 0.5
#: A kept distance: within this of its image's, in units of the larger part's ``sqrt(area)``.
CORE_TOLERANCE = 0.02
#: Seeds of :func:`trilaterate`, spread over the core.
TRILATERATION_SEEDS = 100
#: Width ``σ`` of the seeds' diffusion functions, in units of the larger part's ``sqrt(area)``.
TRILATERATION_WIDTH = 0.15
#: Relative residual ``|f_y(v) - f_x(p(v))| / |f_y(v)|`` at which a vertex is half in the overlap.
OVERLAP_TOLERANCE = 0.15
#: How far (units of the larger part's ``sqrt(area)``) :func:`settle_seeds` moves a seed's image.
SEED_RADIUS = 0.05
#: Rounds of core -> trilateration.
OVERLAP_ROUNDS = 2


@dataclass
class PairMatchResult(MatchResult):
    """A :class:`~torchfmap.MatchResult` of two parts, with ``overlap_y`` ``(V_y,)`` in ``[0, 1]``."""

    overlap_y: np.ndarray | None = None


def _physical(shape: PreparedShape, rows, unit: float) -> np.ndarray:
    """Geodesic rows of ``shape`` in units of ``unit`` (a length): its rows are in ``sqrt(area)``."""
    return shape.distances.distances(np.asarray(rows, dtype=np.int64)) * (np.sqrt(shape.mesh.area) / unit)


def _spread(shape: PreparedShape, among: np.ndarray, n: int) -> np.ndarray:
    """``n`` farthest points (geodesic) among the vertices ``among`` (bool ``(V,)``)."""
    candidates = np.flatnonzero(among)
    seeds = [int(candidates[0])]
    nearest = shape.distances.distances(np.array(seeds))[0]
    for _ in range(min(n, len(candidates)) - 1):
        nxt = int(candidates[np.argmax(nearest[candidates])])
        if nearest[nxt] <= 0:
            break
        seeds.append(nxt)
        nearest = np.minimum(nearest, shape.distances.distances(np.array([nxt]))[0])
    return np.array(seeds, dtype=np.int64)


def consistent_core(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    p2p_yx: np.ndarray,
    *,
    n_anchors: int = CORE_ANCHORS,
    agreement: float = CORE_AGREEMENT,
    tolerance: float = CORE_TOLERANCE,
) -> np.ndarray:
    """Bool ``(V_y,)``: vertices of ``y`` agreeing with at least ``agreement`` of the largest group of
    mutually agreeing anchors (``n_anchors`` farthest points, grown along the leading eigenvector of their
    agreement matrix); two vertices agree when their distance on ``y`` and their images' on ``x`` differ by
    less than ``tolerance`` (units of ``sqrt(area_x)``)."""
    unit = np.sqrt(shape_x.mesh.area)
    anchors = _spread(shape_y, np.ones(shape_y.mesh.n_vertices, bool), n_anchors)
    d_y = _physical(shape_y, anchors, unit)
    images, inverse = np.unique(p2p_yx[anchors], return_inverse=True)
    d_x = _physical(shape_x, images, unit)[inverse][:, p2p_yx]
    agree = np.abs(d_y - d_x) < tolerance  # (A, V_y)
    pairs = agree[:, anchors] & agree[:, anchors].T
    lead = np.abs(np.linalg.eigh(pairs.astype(np.float64))[1][:, -1])
    group: list[int] = []
    for a in np.argsort(-lead, kind="stable"):
        if not group or pairs[a, group].mean() >= agreement:
            group.append(int(a))
    return agree[group].mean(axis=0) >= agreement


def _features(shape: PreparedShape, seeds: np.ndarray, unit: float, width: float) -> np.ndarray:
    unique, column = np.unique(seeds, return_inverse=True)  # two seeds may share an image
    return np.exp(-((_physical(shape, unique, unit).T[:, column] / width) ** 2))


def trilaterate(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    seeds: np.ndarray,
    *,
    width: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(p2p_yx, residual_y, p2p_xy, residual_x)`` from ``seeds`` ``(S, 2)`` (vertex of ``x``, vertex of
    ``y``): each vertex sent to the vertex of the other part with the nearest functions ``exp(-(d / width)²)``
    at the seeds (units of ``sqrt(area_x)``), and its relative residual (1 where ``f(v)`` vanishes)."""
    unit = np.sqrt(shape_x.mesh.area)
    width = TRILATERATION_WIDTH if width is None else width
    f_x = _features(shape_x, seeds[:, 0], unit, width)
    f_y = _features(shape_y, seeds[:, 1], unit, width)

    def one_way(query, reference):
        p2p = search_p2p(query, reference, precision="double")
        norm = np.linalg.norm(query, axis=1)
        res = np.linalg.norm(query - reference[p2p], axis=1)
        return p2p, np.where(norm > 0, res / np.maximum(norm, 1e-300), 1.0)

    return (*one_way(f_y, f_x), *one_way(f_x, f_y))


def settle_seeds(
    shape_x: PreparedShape, shape_y: PreparedShape, seeds: np.ndarray, *, width: float | None = None
) -> np.ndarray:
    """``seeds`` ``(S, 2)``, each image on ``x`` moved within :data:`SEED_RADIUS` to fit the other seeds."""
    unit = np.sqrt(shape_x.mesh.area)
    width = TRILATERATION_WIDTH if width is None else width
    f_x = _features(shape_x, seeds[:, 0], unit, width)
    f_y = _features(shape_y, seeds[:, 1], unit, width)[seeds[:, 1]]
    out = seeds.copy()
    reach = np.exp(-((SEED_RADIUS / width) ** 2))  # f_x at the seed's own image, at SEED_RADIUS
    for i in range(len(seeds)):
        near = np.flatnonzero(f_x[:, i] >= reach)
        others = np.arange(len(seeds)) != i
        cost = np.linalg.norm(f_x[np.ix_(near, others)] - f_y[i, others], axis=1)
        out[i, 0] = near[np.argmin(cost)]
    return out


def _indicator(residual: np.ndarray, tolerance: float) -> np.ndarray:
    """``[0, 1]``: 1 at zero residual, 0.5 at ``tolerance``, 0 at twice it."""
    return np.clip(1.0 - 0.5 * residual / tolerance, 0.0, 1.0)


def _polished(shape_x, shape_y, p2p_yx, inside, *, k, refine, k_final, weights) -> np.ndarray:
    """``p2p_yx`` with ``y``'s overlap ``inside`` re-matched into ``x`` (:func:`~.partial.match_partial`)."""
    mesh = shape_y.mesh
    drop = ~inside[mesh.faces].all(axis=1)
    if drop.all():
        return p2p_yx
    piece, ids = mesh.without_faces(np.flatnonzero(drop)).referenced()
    piece, kept = piece.largest_component()
    n_eigen = (k_final or 2 * k) if refine else k
    a = piece.area / shape_x.mesh.area
    if not (MIN_AREA_RATIO <= a <= AREA_SLACK) or piece.n_vertices <= n_eigen + 1:
        return p2p_yx
    sub = prepare_shape(piece, n_eigen)
    got = match_partial(shape_x, sub, k=k, refine=refine, k_final=k_final, **weights)
    out = p2p_yx.copy()
    out[ids[kept]] = got.p2p_yx
    return out


def match_partial_pair(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    *,
    k: int = DEFAULT_K,
    refine: str | None = None,
    k_final: int | None = None,
    w_lap: float = W_LAP_SMOOTH,
    w_orient: float = W_ORIENT,
    w_dcomm: float = W_DCOMM,
    w_lmk: float = W_LMK,
    landmarks: np.ndarray | None = None,
    rounds: int = OVERLAP_ROUNDS,
    tolerance: float = OVERLAP_TOLERANCE,
    polish: bool = False,
    settle: bool = True,
) -> PairMatchResult:
    """Match two overlapping parts ``x`` and ``y`` of one whole on prepared shapes: a :class:`PairMatchResult`
    (``kind`` ``'partial_pair'``) with ``C_xy`` ``(r, k_x)``, ``r`` the overlap's rank; ``p2p_yx_initial`` the
    bootstrap map if ``y`` is the smaller part. ``landmarks`` ``(L, 2)`` must lie on the overlap; ``settle``:
    :func:`settle_seeds` each round; ``polish``: ``y``'s overlap re-matched by
    :func:`~.partial.match_partial`.

    Raises:
        ParameterError: ``rounds`` < 1 or ``tolerance`` not > 0; or as :func:`~.partial.match_partial`."""
    if rounds < 1 or not tolerance > 0:
        raise ParameterError(
            f"match_partial_pair needs rounds >= 1 and tolerance > 0, got {rounds}, {tolerance}."
        )
    t0 = time.perf_counter()
    swap = shape_y.mesh.area > shape_x.mesh.area  # the larger part plays the whole
    big, small = (shape_y, shape_x) if swap else (shape_x, shape_y)
    pairs = None if landmarks is None else np.asarray(landmarks, dtype=np.int64)
    if pairs is not None and swap:
        pairs = pairs[:, ::-1]
    first = match_partial(
        big, small, landmarks=pairs, k=k, refine=refine, k_final=k_final, w_lap=w_lap,
        w_orient=w_orient, w_dcomm=w_dcomm, w_lmk=w_lmk,
    )  # fmt: skip
    timings = dict(first.timings) | {"bootstrap": time.perf_counter() - t0}
    t0 = time.perf_counter()
    p2p_sb = first.p2p_yx
    core = consistent_core(big, small, p2p_sb)
    if pairs is not None:
        core[pairs[:, 1]] = True
    for _ in range(rounds):
        if not core.any():
            core = np.ones_like(core)
        on_small = _spread(small, core, TRILATERATION_SEEDS)
        if pairs is not None:
            on_small = np.concatenate([pairs[:, 1], np.setdiff1d(on_small, pairs[:, 1])])
        on_big = p2p_sb[on_small] if pairs is None else np.concatenate(
            [pairs[:, 0], p2p_sb[on_small[len(pairs):]]]
        )  # fmt: skip
        seeds = np.stack([on_big, on_small], axis=1)
        if settle:
            seeds = settle_seeds(big, small, seeds)
            if pairs is not None:
                seeds[: len(pairs)] = pairs
        p2p_sb, res_small, p2p_bs, res_big = trilaterate(big, small, seeds)
        core = res_small < tolerance
    timings["overlap"] = time.perf_counter() - t0
    ov_small, ov_big = _indicator(res_small, tolerance), _indicator(res_big, tolerance)
    if swap:  # y is the larger part: its map into x is the one from big to small
        p2p, overlap_x, overlap_y = p2p_bs, ov_small, ov_big
    else:
        p2p, overlap_x, overlap_y = p2p_sb, ov_big, ov_small
    if polish:
        t0 = time.perf_counter()
        weights = dict(w_lap=w_lap, w_orient=w_orient, w_dcomm=w_dcomm, w_lmk=w_lmk)
        p2p = _polished(
            shape_x, shape_y, p2p, overlap_y > 0.5, k=k, refine=refine, k_final=k_final, weights=weights
        )
        timings["polish"] = time.perf_counter() - t0
    full = shape_x.eigenbasis
    share = float(shape_y.operators[1].diagonal() @ (overlap_y > 0.5)) / shape_y.area
    a = shape_y.mesh.area / shape_x.mesh.area
    k_x = first.C_xy.shape[1]
    part = common_frame(shape_y.eigenbasis, a)
    r = max(1, round(share * partial_rank(full.eigenvalues, part.eigenvalues, k_x))) if a <= 1 else k_x
    C = p2p_to_fmap(p2p, full, part, k_x, min(r, part.k))
    result = PairMatchResult(
        p2p, C, full.truncated(k_x), part.truncated(C.shape[0]), first.p2p_yx if not swap else p2p,
        timings, kind="partial_pair", refined=refine is not None,
    )  # fmt: skip
    result.overlap, result.overlap_y = overlap_x, overlap_y
    result.partial_rank = C.shape[0]
    return result
