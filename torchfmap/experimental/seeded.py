"""A self-seeded second stage for the classical path (an experiment): :func:`seeded_match` reads seed pairs
off the eigenbasis ZoomOut map at :data:`SEEDED_SEEDS` farthest points (:func:`map_seeds`), then solves the
pair again with them as landmarks."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from ..bases.prepared import PreparedShape, prepare_shape
from ..errors import ParameterError
from ..fmap.convert import values_to_p2p
from ..fmap.defaults import DEFAULT_K
from ..matching.pipeline import match
from ..matching.results import MatchResult
from ..mesh import Mesh
from ..seeds import consistent_seeds, farthest_point_sampling

#: Farthest points of ``x`` offered as seeds.
SEEDED_SEEDS = 40


class SeededMatch(NamedTuple):
    """:func:`seeded_match`'s result: stage 2's map (``result.seeds``: its seed pairs ``(S, 2)``; stage 1's
    timings prefixed ``stage1:``) and stage 1's ZoomOut map (``first_stage``)."""

    result: MatchResult
    first_stage: MatchResult


def seeded_match(
    mesh_x: Mesh,
    mesh_y: Mesh,
    *,
    k: int = DEFAULT_K,
    k_final: int | None = None,
    k_descriptors: int = 100,
    shapes: tuple[PreparedShape, PreparedShape] | None = None,
    n_seeds: int = SEEDED_SEEDS,
    **match_kwargs,
) -> SeededMatch:
    """Match ``y`` to ``x`` in two stages (module docstring), with :func:`torchfmap.match`'s other arguments
    for both; stage 2 is skipped (``result`` is stage 1's) when fewer than two seeds agree. ParameterError for
    landmarks, bases, a basis or a refinement in ``match_kwargs``."""
    refused = sorted(set(match_kwargs) & {"landmarks", "bases", "basis", "refine"})
    if refused:
        raise ParameterError(
            f"seeded_match seeds a second solve from the eigenbasis ZoomOut map; {', '.join(refused)} "
            "would change that. Fix: drop them, or torchfmap.match(..., refine='zoomout')."
        )
    settings = dict(k=k, k_final=k_final, k_descriptors=k_descriptors, refine="zoomout", **match_kwargs)
    if shapes is None:  # as match prepares them: k, ZoomOut's k_final and the descriptors' eigenpairs
        n_max = min(mesh_x.n_vertices, mesh_y.n_vertices) - 1
        n_eigen = max(k, k_final or 2 * k, min(k_descriptors, n_max))
        shapes = (prepare_shape(mesh_x, n_eigen), prepare_shape(mesh_y, n_eigen))
    first = match(mesh_x, mesh_y, shapes=shapes, **settings)
    bx, by, C = first.basis_x, first.basis_y, first.C_xy
    seeds = map_seeds(shapes[0], C, C.T, bx.values, by.values, n_seeds)  # C_yx = C_xyᵀ
    if len(seeds) < 2:
        return SeededMatch(first, first)
    second = match(mesh_x, mesh_y, landmarks=seeds, basis="laplacian", shapes=shapes, **settings)
    timings = {f"stage1:{key}": v for key, v in first.timings.items()} | second.timings
    return SeededMatch(dataclasses.replace(second, timings=timings, seeds=seeds), first)


def map_seeds(
    shape_x: PreparedShape,
    C_xy: np.ndarray,
    C_yx: np.ndarray,
    values_x: np.ndarray,
    values_y: np.ndarray,
    n_seeds: int,
    landmarks: np.ndarray | None = None,
) -> np.ndarray:
    """Seed pairs ``(S, 2)``: ``landmarks`` ``(L, 2)`` first, then those of ``n_seeds`` farthest points of
    ``x`` sent to ``y`` by ``C_yx (K_x, K_y)`` and back by ``C_xy (K_y, K_x)`` (orthogonal rule in
    ``values_x (V_x, K_x)``, ``values_y (V_y, K_y)``) that agree (:func:`~torchfmap.seeds.consistent_seeds`);
    no vertex of ``y`` twice. Without landmarks the farthest points are cached on ``shape_x``."""
    given = np.zeros((0, 2), dtype=np.int64) if landmarks is None else np.asarray(landmarks, dtype=np.int64)
    n = min(n_seeds + len(given), shape_x.mesh.n_vertices)
    if len(given):
        s = farthest_point_sampling(shape_x.mesh, n, landmarks=given[:, 0], metric="euclidean")[len(given) :]
    else:
        s = shape_x.derive(("seeds", n), lambda: farthest_point_sampling(shape_x.mesh, n, metric="euclidean"))
    t = values_to_p2p(C_yx, values_y, values_x[s], mode="orthogonal")  # x -> y at the seeds
    back = values_to_p2p(C_xy, values_x, values_y[t], mode="orthogonal")  # and back
    found = consistent_seeds(shape_x.distances, s, t, back)
    found = found[~np.isin(found[:, 1], given[:, 1])]
    return np.concatenate([given, found]).astype(np.int64)
