"""Refiners: small callables that refine a map in a pair of bases, one per way of refining.

A kind returns its refiner (:meth:`torchfmap.kinds.BasisKind.refiner`); every refiner is called
the same way, ``refiner(C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds)`` ->
:class:`~torchfmap.fmap.Refined`, by :func:`torchfmap.match` (through
:func:`torchfmap.matching.results.refine_result`) and by the learned path: :class:`ICP` (any
kind), :class:`ZoomOut` (eigenbases), :class:`FixedSizeIterations` (bases that do not nest),
:class:`SeedMoves` (bases built at corresponding seeds). The refinement names of
``match(refine=...)`` are checked in one place, :func:`check_refine`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from ..bases.basis import Basis
from ..bases.orthonormalize import orthonormalize_pair
from ..bases.prepared import PreparedShape, with_eigenpairs
from ..errors import ParameterError
from ..fmap.defaults import LOCAL_SEARCH_PAIRS, SURFACE_SAMPLES, VERTICES_PER_SAMPLE
from ..fmap.nearest import SurfaceSampling, surface_sampling
from ..fmap.refine import (
    Refined,
    Samples,
    SequenceStep,
    icp_refine,
    zoomout,
    zoomout_iterations,
    zoomout_sequence,
)
from ..seeds import farthest_point_sampling, replace_seeds

#: The refinements of :func:`torchfmap.match` (``refine=``; None: no refinement): the type of
#: the argument, and the tuple of names the command line offers and :func:`check_refine` reads.
RefineMethod = Literal["icp", "zoomout"]
REFINE_METHODS: tuple[str, ...] = get_args(RefineMethod)
#: Fixed-size refinement steps (point map <-> functional map) in feature-aware bases.
FEATURE_REFINE_STEPS = 5
#: Rounds of seed re-placement after the fixed-size refinement (:func:`~torchfmap.seeds.replace_seeds`).
FEATURE_SEED_MOVES = 2
#: Farthest-point samples per basis column for the iterations of feature-aware refinement (the
#: least-squares map of ``K`` columns is fitted on ``25 K`` sample rows; only the last point map
#: of each round uses every vertex), so the cost of an iteration does not grow with ``V²``
#: (accuracy against every-vertex iterations: ``python -m bench accuracy --case feature_accuracy``).
FEATURE_SAMPLES_PER_COLUMN = 25


def shape_sampling(shape: PreparedShape, n_samples: int = SURFACE_SAMPLES) -> SurfaceSampling:
    """The shape's :func:`~torchfmap.fmap.nearest.surface_sampling` of ``n_samples`` (at most
    every vertex), computed once per shape and size (kept in the prepared shape)."""
    n = min(int(n_samples), shape.mesh.n_vertices)
    mass = shape.operators[1].diagonal() / shape.scale**2  # the operators' frame -> the mesh's units
    return shape.derive(("surface_sampling", n), lambda: surface_sampling(shape.mesh.vertices, mass, n))


def is_dense(shape_x: PreparedShape, shape_y: PreparedShape) -> bool:
    """Whether the pair is past :data:`~torchfmap.fmap.defaults.LOCAL_SEARCH_PAIRS`: point maps
    and refinements then search locally around samples instead of comparing every vertex with
    every vertex."""
    return shape_x.mesh.n_vertices * shape_y.mesh.n_vertices > LOCAL_SEARCH_PAIRS


def pair_samplings(shape_x: PreparedShape, shape_y: PreparedShape, n_samples: int | None = None):
    """``(SurfaceSampling of x, of y)`` of ``n_samples`` each (None: only for a dense pair,
    :func:`is_dense`, otherwise None; :data:`~torchfmap.fmap.defaults.SURFACE_SAMPLES`, or one per
    :data:`~torchfmap.fmap.defaults.VERTICES_PER_SAMPLE` vertices of a larger shape)."""
    if n_samples is None and not is_dense(shape_x, shape_y):
        return None

    def count(shape: PreparedShape) -> int:
        return (
            max(SURFACE_SAMPLES, shape.mesh.n_vertices // VERTICES_PER_SAMPLE)
            if n_samples is None
            else n_samples
        )

    return shape_sampling(shape_x, count(shape_x)), shape_sampling(shape_y, count(shape_y))


def check_refine(
    refine, *, optional: bool = True, allowed: tuple[str, ...] = REFINE_METHODS, what: str = "match"
) -> str | None:
    """``refine`` if it is one of ``allowed`` (:data:`REFINE_METHODS` by default; a path that
    refines one way only, as partial matching and the learned path, narrows it), or None when
    ``optional`` (no refinement): the one check of the names.

    Raises:
        ParameterError: any other value, naming ``what`` refines how.
    """
    if (refine is None and optional) or refine in allowed:
        return refine
    names = ", ".join(repr(a) for a in allowed) + (" or None" if optional else "")
    raise ParameterError(f"{what} refines by {names}; got refine={refine!r}. Fix: {names}.")


@dataclass(frozen=True)
class ICP:
    """ICP in the bases as they are (:func:`~torchfmap.fmap.icp_refine`, point maps by ``mode``)."""

    mode: str = "orthogonal"

    def __call__(self, C_xy, p2p_yx, shape_x, shape_y, basis_x: Basis, basis_y: Basis, seeds=None) -> Refined:
        samplings = pair_samplings(shape_x, shape_y)  # dense pairs: searched locally
        return Refined(
            *icp_refine(C_xy, basis_x, basis_y, mode=self.mode, samplings=samplings), basis_x, basis_y, seeds
        )


def check_eigenbases(eigenbases: tuple[Basis, Basis], k_final: int) -> tuple[Basis, Basis]:
    """Given eigenbases ``(basis_x, basis_y)`` that a ZoomOut to ``k_final`` grows within.

    Raises:
        ParameterError: fewer than ``k_final`` columns (a ZoomOut in another basis would refine
            a map solved in these in different functions).
    """
    have = min(b.k for b in eigenbases)
    if have < k_final:
        raise ParameterError(
            f"ZoomOut grows given eigenbases within their own eigenfunctions: it needs {k_final} "
            f"(k_final), the given bases hold {have}. Fix: save bases with at least {k_final} "
            "eigenfunctions (torchfmap basis --k), a smaller k or k_final, or refine='icp'."
        )
    return tuple(eigenbases)


def grown_eigenbases(shape_x: PreparedShape, shape_y: PreparedShape, eigenbases, k_final: int):
    """The eigenbases a ZoomOut grows in, holding at least ``k_final`` columns: the given
    ``eigenbases`` (:func:`check_eigenbases`), else the shapes' own (eigenpairs computed in
    place when they hold fewer)."""
    if eigenbases is None:
        return tuple(with_eigenpairs(s, k_final).eigenbasis for s in (shape_x, shape_y))
    return check_eigenbases(eigenbases, k_final)


def landmark_coordinates(
    shape_x: PreparedShape, shape_y: PreparedShape, landmarks: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(A_x (V_x, L), A_y (V_y, L))``: every vertex's geodesic distances to the ``(L, 2)``
    landmark pairs ``(x vertex, y vertex)``, in units of each shape's ``sqrt(area)`` (rows
    computed by, and kept in, each shape's ``distances``). Column ``l`` is the same function on
    both shapes wherever the map between them preserves distances to landmark ``l``."""
    pairs = np.asarray(landmarks, dtype=np.int64).reshape(-1, 2)
    return shape_x.distances.distances(pairs[:, 0]).T, shape_y.distances.distances(pairs[:, 1]).T


def stacked_anchors(*blocks: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray] | None:
    """``(A_x, A_y)``: the given ``(V_x, m_i)`` / ``(V_y, m_i)`` anchor blocks side by side, each
    divided by its mean row norm on ``y`` first, so that every block weighs alike (ZoomOut then
    scales the whole to the spectral embedding, :func:`~torchfmap.fmap.convert.values_to_p2p`).
    None blocks are skipped; None when none is given; a single block is returned as it is."""
    given = [b for b in blocks if b is not None]
    if len(given) <= 1:
        return given[0] if given else None
    scaled = []
    for ax, ay in given:
        norm = np.linalg.norm(ay, axis=1).mean()
        scaled.append((ax / norm, ay / norm) if norm > 0 else (ax, ay))
    return np.hstack([a for a, _ in scaled]), np.hstack([b for _, b in scaled])


@dataclass(frozen=True)
class ZoomOut:
    """ZoomOut in eigenbases (:func:`~torchfmap.fmap.zoomout`), grown from ``C_xy``'s size to
    ``k_final`` (default: twice that size) in ``eigenbases`` (given ones, whose first columns
    ``basis_x, basis_y`` are) or, when None, the shapes' own eigenbases; on ``samples`` samples
    per shape (:func:`shape_sampling`) if given, or by default on a dense pair
    (:func:`is_dense`), the final map then searched locally; ``progress``: a bar over the sizes.
    Anchors (:func:`stacked_anchors`, ZoomOut's ``anchors``) tie every point-map step to what is
    known to correspond: with ``landmarks`` ``(L, 2)`` the vertices' geodesic distances to them
    (:func:`landmark_coordinates`); with ``features`` ``((V_x, D), (V_y, D))`` per-vertex
    descriptors of both shapes (a trained network's, which the learned path passes). Returns
    the map in the grown bases (no seeds)."""

    k_final: int | None = None
    mode: str = "orthogonal"
    samples: int | None = None
    eigenbases: tuple[Basis, Basis] | None = None
    landmarks: np.ndarray | None = None
    features: tuple[np.ndarray, np.ndarray] | None = None
    progress: bool = False

    def __call__(self, C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds=None) -> Refined:
        k_final = self.k_final if self.k_final is not None else 2 * min(np.shape(C_xy))
        full_x, full_y = grown_eigenbases(shape_x, shape_y, self.eigenbases, k_final)
        samplings = pair_samplings(shape_x, shape_y, self.samples)
        samples = Samples.of_pair(samplings)
        distances = None if self.landmarks is None else landmark_coordinates(shape_x, shape_y, self.landmarks)
        anchors = stacked_anchors(distances, self.features)
        C, p2p = zoomout(
            C_xy, full_x, full_y, k_final, mode=self.mode, subsample=samples, anchors=anchors,
            p2p_yx=None if samples is None else p2p_yx, progress=self.progress,
        )  # fmt: skip
        return Refined(C, p2p, full_x.truncated(k_final), full_y.truncated(k_final), None)


def feature_samples(shape_x: PreparedShape, shape_y: PreparedShape, k: int) -> Samples:
    """The samples fixed-size iterations in bases of ``k`` columns are fitted on:
    :data:`FEATURE_SAMPLES_PER_COLUMN` ``x k`` farthest points per shape (at most every vertex);
    on a dense pair (:func:`is_dense`) the shapes' surface samplings, whose final map is
    searched locally."""
    samplings = pair_samplings(shape_x, shape_y)
    if samplings is not None:
        return Samples.of_surfaces(*samplings)
    n_samples = min(FEATURE_SAMPLES_PER_COLUMN * k, shape_x.mesh.n_vertices, shape_y.mesh.n_vertices)
    fps = (farthest_point_sampling(s.mesh, n_samples, metric="euclidean") for s in (shape_x, shape_y))
    return Samples(*fps)


def fixed_size_iterations(p2p_yx, bx: Basis, by: Basis, mode, samples) -> tuple[np.ndarray, np.ndarray]:
    """``(C_xy, p2p_yx)`` after :data:`FEATURE_REFINE_STEPS` point map <-> functional map
    alternations in ``bx, by`` (fixed size), fitted on ``samples`` (:func:`feature_samples`)."""
    steps = FEATURE_REFINE_STEPS
    return zoomout_sequence(p2p_yx, [bx] * steps, [by] * steps, mode=mode, subsample=samples)


@dataclass(frozen=True)
class FixedSizeIterations:
    """The bases keep their size: from the current map, ``C`` and the point map alternate
    :data:`FEATURE_REFINE_STEPS` times (on :data:`FEATURE_SAMPLES_PER_COLUMN` ``x K``
    farthest-point samples per shape, the last point map on every vertex)."""

    mode: str = "pullback"

    def __call__(self, C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds=None) -> Refined:
        samples = feature_samples(shape_x, shape_y, basis_x.k)
        C, p2p = fixed_size_iterations(p2p_yx, basis_x, basis_y, self.mode, samples)
        return Refined(C, p2p, basis_x, basis_y, seeds)


@dataclass(frozen=True)
class SeedMoves:
    """:class:`FixedSizeIterations`; then, for bases built at corresponding ``seeds`` ``(S, 2)``,
    :data:`FEATURE_SEED_MOVES` times: the seeds of ``y`` move to where the map puts them
    (:func:`~torchfmap.seeds.replace_seeds`, the first ``n_fixed``, the landmarks, stay), the
    bases are rebuilt by ``functions(shape, seeds (S,), times)`` (a seeded kind's raw
    functions), the map restarts from ``C = I`` in them and alternates again."""

    functions: Callable
    mode: str = "pullback"
    n_fixed: int = 0
    times: tuple | None = None

    def __call__(self, C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds=None) -> Refined:
        samples = feature_samples(shape_x, shape_y, basis_x.k)
        C, p2p = fixed_size_iterations(p2p_yx, basis_x, basis_y, self.mode, samples)
        bx, by = basis_x, basis_y
        if seeds is None:
            return Refined(C, p2p, bx, by, seeds)
        raw_x = self.functions(shape_x, seeds[:, 0], self.times)  # x's seeds never move (kernels cached)
        for _ in range(FEATURE_SEED_MOVES):
            seeds = replace_seeds(shape_x.distances, shape_y.distances, seeds, p2p, self.n_fixed)
            raw_y = self.functions(shape_y, seeds[:, 1], self.times)
            bx, by = (b.truncated(basis_x.k) for b in orthonormalize_pair(raw_x, raw_y))
            start = np.eye(by.k, bx.k)  # the rebuilt bases correspond column by column
            rebuilt = SequenceStep((bx,), (by,), self.mode)
            p2p = zoomout_iterations(rebuilt, [], C_xy=start, samples=samples)[1]
            C, p2p = fixed_size_iterations(p2p, bx, by, self.mode, samples)
        return Refined(C, p2p, bx, by, seeds)
