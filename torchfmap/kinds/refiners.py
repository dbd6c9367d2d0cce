"""Refiners: ``refiner(C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds)`` ->
:class:`~torchfmap.fmap.Refined`, one per way of refining."""

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

#: The refinements of :func:`torchfmap.match` (``refine=``; None: no refinement).
RefineMethod = Literal["icp", "zoomout"]
REFINE_METHODS: tuple[str, ...] = get_args(RefineMethod)
#: Fixed-size refinement steps (point map <-> functional map) in feature-aware bases.
FEATURE_REFINE_STEPS = 5
#: Rounds of seed re-placement after the fixed-size refinement (:func:`~torchfmap.seeds.replace_seeds`).
FEATURE_SEED_MOVES = 2
#: Farthest-point samples per basis column for the iterations of feature-aware refinement.
FEATURE_SAMPLES_PER_COLUMN = 25


def shape_sampling(shape: PreparedShape, n_samples: int = SURFACE_SAMPLES) -> SurfaceSampling:
    """The shape's :func:`~torchfmap.fmap.nearest.surface_sampling` of ``n_samples`` (at most every
    vertex), cached in the prepared shape."""
    n = min(int(n_samples), shape.mesh.n_vertices)
    mass = shape.operators[1].diagonal() / shape.scale**2  # to the mesh's units
    return shape.derive(("surface_sampling", n), lambda: surface_sampling(shape.mesh.vertices, mass, n))


def is_dense(shape_x: PreparedShape, shape_y: PreparedShape) -> bool:
    """Whether the pair is past :data:`~torchfmap.fmap.defaults.LOCAL_SEARCH_PAIRS` (local search)."""
    return shape_x.mesh.n_vertices * shape_y.mesh.n_vertices > LOCAL_SEARCH_PAIRS


def pair_samplings(shape_x: PreparedShape, shape_y: PreparedShape, n_samples: int | None = None):
    """``(SurfaceSampling of x, of y)`` of ``n_samples`` each; ``n_samples=None``: a default count,
    and None returned for a pair that is not dense (:func:`is_dense`)."""
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
    """``refine`` if it is one of ``allowed``, or None when ``optional``; else ParameterError
    naming ``what`` refines how."""
    if (refine is None and optional) or refine in allowed:
        return refine
    names = ", ".join(repr(a) for a in allowed) + (" or None" if optional else "")
    raise ParameterError(f"{what} refines by {names}; got refine={refine!r}. Fix: {names}.")


@dataclass(frozen=True)
class ICP:
    """ICP in the bases as they are (:func:`~torchfmap.fmap.icp_refine`, point maps by ``mode``)."""

    mode: str = "orthogonal"

    def __call__(self, C_xy, p2p_yx, shape_x, shape_y, basis_x: Basis, basis_y: Basis, seeds=None) -> Refined:
        samplings = pair_samplings(shape_x, shape_y)
        return Refined(
            *icp_refine(C_xy, basis_x, basis_y, mode=self.mode, samplings=samplings), basis_x, basis_y, seeds
        )


def check_eigenbases(eigenbases: tuple[Basis, Basis], k_final: int) -> tuple[Basis, Basis]:
    """Given eigenbases ``(basis_x, basis_y)``; ParameterError if fewer than ``k_final`` columns."""
    have = min(b.k for b in eigenbases)
    if have < k_final:
        raise ParameterError(
            f"ZoomOut grows given eigenbases within their own eigenfunctions: it needs {k_final} "
            f"(k_final), the given bases hold {have}. Fix: save bases with at least {k_final} "
            "eigenfunctions (torchfmap basis --k), a smaller k or k_final, or refine='icp'."
        )
    return tuple(eigenbases)


def grown_eigenbases(shape_x: PreparedShape, shape_y: PreparedShape, eigenbases, k_final: int):
    """``eigenbases`` (checked), else the shapes' own grown to ``k_final`` columns."""
    if eigenbases is None:
        return tuple(with_eigenpairs(s, k_final).eigenbasis for s in (shape_x, shape_y))
    return check_eigenbases(eigenbases, k_final)


def landmark_coordinates(
    shape_x: PreparedShape, shape_y: PreparedShape, landmarks: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(A_x (V_x, L), A_y (V_y, L))``: every vertex's geodesic distances to the ``(L, 2)``
    landmark pairs ``(x vertex, y vertex)``, in units of each shape's ``sqrt(area)``."""
    pairs = np.asarray(landmarks, dtype=np.int64).reshape(-1, 2)
    return shape_x.distances.distances(pairs[:, 0]).T, shape_y.distances.distances(pairs[:, 1]).T


def stacked_anchors(*blocks: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray] | None:
    """``(A_x, A_y)``: the anchor blocks side by side, each divided by its mean row norm on ``y``
    (None blocks skipped; None if none; one block as is)."""
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
    """ZoomOut in eigenbases to ``k_final`` (default: twice the start), on ``samples`` samples per
    shape (default: on dense pairs), anchored by distances to ``landmarks`` and ``features``.
    Returns the map in the grown bases (no seeds)."""

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
    """Samples of fixed-size iterations: :data:`FEATURE_SAMPLES_PER_COLUMN` ``x k`` farthest points
    per shape, or a dense pair's surface samplings."""
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
    """Fixed-size iterations (:func:`fixed_size_iterations`) in the bases as they are."""

    mode: str = "pullback"

    def __call__(self, C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds=None) -> Refined:
        samples = feature_samples(shape_x, shape_y, basis_x.k)
        C, p2p = fixed_size_iterations(p2p_yx, basis_x, basis_y, self.mode, samples)
        return Refined(C, p2p, basis_x, basis_y, seeds)


@dataclass(frozen=True)
class SeedMoves:
    """:class:`FixedSizeIterations`; then :data:`FEATURE_SEED_MOVES` times ``y``'s ``seeds (S, 2)``
    (but the first ``n_fixed``) move to their images, the bases are rebuilt and refined again."""

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
        raw_x = self.functions(shape_x, seeds[:, 0], self.times)  # x's seeds never move
        for _ in range(FEATURE_SEED_MOVES):
            seeds = replace_seeds(shape_x.distances, shape_y.distances, seeds, p2p, self.n_fixed)
            raw_y = self.functions(shape_y, seeds[:, 1], self.times)
            bx, by = (b.truncated(basis_x.k) for b in orthonormalize_pair(raw_x, raw_y))
            start = np.eye(by.k, bx.k)
            rebuilt = SequenceStep((bx,), (by,), self.mode)
            p2p = zoomout_iterations(rebuilt, [], C_xy=start, samples=samples)[1]
            C, p2p = fixed_size_iterations(p2p, bx, by, self.mode, samples)
        return Refined(C, p2p, bx, by, seeds)
