"""The landmark default of :func:`torchfmap.match` (``basis='auto'`` with landmarks): the least distorted map
among :data:`AUTO_KINDS`, overridden by a clear verdict of the landmark cross-validation."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from .._util.checks import check_count
from .._util.progress import SILENT, Steps
from ..bases.prepared import PreparedShape
from ..errors import ParameterError
from ..fmap import check_landmark_pairs
from ..fmap.defaults import DEFAULT_K
from ..fmap.solver import check_solve_memory
from ..kinds import BasisKind, get_kind
from ..kinds.refiners import RefineMethod, check_refine, pair_samplings
from ..mesh import Mesh
from .checks import check_unused, check_zoomout_sizes
from .quality import DISTORTION_RESOLUTION, warn_if_off_by_one
from .results import MatchResult, refine_result
from .solve import P2PMode, prepare_shapes, solve_functional_map, solve_pair

#: The kinds the landmark default solves in, in order of preference.
AUTO_KINDS = ("laplacian", "hybrid")
#: The eigenbasis is kept unless a feature-aware map distorts geodesic distances by this fraction less.
AUTO_MARGIN = DISTORTION_RESOLUTION
#: Folds of the cross-validation, at most.
CV_FOLDS = 4
#: The cross-validation needs this many landmarks.
CV_MIN_LANDMARKS = 3
#: A refinement is cross-validated (:func:`refine_guarded`, reported, not a veto) from this many landmarks.
CV_REFINE_MIN_LANDMARKS = 5
#: A kind replaces the distortion's choice only if its held-out error is below this fraction of the chosen's.
CV_RATIO = 0.5


def _fold_map(shape_x, shape_y, kind: BasisKind, k: int, pairs, held, fold: int, times, fold_maps, solve):
    """Fold ``fold``'s map of ``kind``, solved without the ``held`` pairs; cached in ``fold_maps``."""
    key = (kind.name, fold)
    if fold_maps is not None and key in fold_maps:
        return fold_maps[key]
    times = times if kind.needs_landmarks else None
    solved = solve_functional_map(shape_x, shape_y, kind, k, landmarks=pairs[~held], times=times, **solve)
    if fold_maps is not None:
        fold_maps[key] = solved
    return solved


def _cv_folds(shape_x, pairs: np.ndarray, folds: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """``(rows (L, V_x), held)``: distances from the pairs' ``x`` vertices and each fold's held-out mask."""
    if len(pairs) < CV_MIN_LANDMARKS:
        raise ParameterError(
            f"cross-validation holds landmarks out: {CV_MIN_LANDMARKS} or more are needed, got {len(pairs)}."
        )
    n_folds = min(folds, len(pairs))
    held = [np.arange(len(pairs)) % n_folds == fold for fold in range(n_folds)]
    return shape_x.distances.distances(pairs[:, 0]), held


def landmark_scores(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    pairs: np.ndarray,
    kinds,
    k: int,
    *,
    folds: int = CV_FOLDS,
    times=None,
    p2p_mode: P2PMode | None = None,
    steps: Steps = SILENT,
    fold_maps: dict | None = None,
    **solve,
) -> dict[str, float]:
    """``{kind: mean held-out error}`` (units of ``sqrt(area)``): each kind's unrefined maps solved without
    each fold's landmark pairs, a held-out ``(a, b)`` scoring ``d_x(p2p_yx[b], a)``; kinds not built are left
    out. ``fold_maps``: a cache; ``solve``: other settings of :func:`~torchfmap.matching.solve.solve_pair`.

    Raises:
        ParameterError: fewer than :data:`CV_MIN_LANDMARKS` pairs."""
    rows, every_fold = _cv_folds(shape_x, pairs, folds)
    scores = {}
    for name in kinds:
        kind = get_kind(name)
        errors = []
        try:
            for fold, held in enumerate(every_fold):
                steps(f"cross-validation: {name}, fold {fold + 1} of {len(every_fold)}")
                C, bx, by, _, _ = _fold_map(
                    shape_x, shape_y, kind, k, pairs, held, fold, times, fold_maps, solve
                )
                sent = kind.to_p2p(C, bx, by, p2p_mode or kind.p2p_mode, rows=pairs[held, 1])
                errors.extend(rows[held, sent])
        except ParameterError:
            continue
        scores[name] = float(np.mean(errors))
    return scores


def refinement_scores(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    pairs: np.ndarray,
    kind: BasisKind,
    k: int,
    make_refiner,
    *,
    folds: int = CV_FOLDS,
    times=None,
    p2p_mode: P2PMode | None = None,
    steps: Steps = SILENT,
    fold_maps: dict | None = None,
    **solve,
) -> tuple[float, float]:
    """``(raw, refined)`` mean held-out landmark errors (folds as :func:`landmark_scores`) of each fold's map
    before and after ``make_refiner(fold_pairs)``.

    Raises:
        ParameterError: fewer than :data:`CV_MIN_LANDMARKS` pairs, or as the kind and refiner."""
    rows, every_fold = _cv_folds(shape_x, pairs, folds)
    mode = p2p_mode or kind.p2p_mode
    samplings = pair_samplings(shape_x, shape_y)
    raw, refined = [], []
    for fold, held in enumerate(every_fold):
        steps(f"refinement check: {kind.name}, fold {fold + 1} of {len(every_fold)}")
        C, bx, by, seeds, _ = _fold_map(shape_x, shape_y, kind, k, pairs, held, fold, times, fold_maps, solve)
        p2p = kind.to_p2p(C, bx, by, mode, samplings=samplings)
        after = make_refiner(pairs[~held])(C, p2p, shape_x, shape_y, bx, by, seeds).p2p_yx
        raw.extend(rows[held, p2p[pairs[held, 1]]])
        refined.extend(rows[held, after[pairs[held, 1]]])
    return float(np.mean(raw)), float(np.mean(refined))


def refine_guarded(
    result: MatchResult,
    kind: BasisKind,
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    pairs: np.ndarray | None,
    k: int,
    make_refiner,
    *,
    cross_validate: bool = True,
    times=None,
    p2p_mode: P2PMode | None = None,
    steps: Steps = SILENT,
    **solve,
) -> MatchResult:
    """``result`` refined by :func:`~torchfmap.matching.results.refine_result`, cross-validated
    (:func:`refinement_scores`) with ``cross_validate`` and :data:`CV_REFINE_MIN_LANDMARKS` or more ``pairs``
    ``(L, 2)``. ``make_refiner(pairs, bar=False)``: the refiner on these landmarks.

    Raises:
        ParameterError: as the refiner."""
    held_out = None
    if cross_validate and pairs is not None and len(pairs) >= CV_REFINE_MIN_LANDMARKS:
        held_out = refinement_scores(
            shape_x, shape_y, pairs, kind, k, make_refiner, times=times, p2p_mode=p2p_mode, steps=steps,
            **solve,
        )  # fmt: skip
    steps(f"{kind.name}: refinement")
    return refine_result(result, make_refiner(pairs, steps.enabled), shape_x, shape_y, held_out)


def match_landmark_default(
    mesh_x: Mesh,
    mesh_y: Mesh,
    landmarks: np.ndarray,
    *,
    k: int = DEFAULT_K,
    refine: RefineMethod | None = None,
    k_final: int | None = None,
    times=None,
    zoomout_samples: int | None = None,
    shapes: tuple[PreparedShape, PreparedShape] | None = None,
    k_descriptors: int = 100,
    p2p_mode: P2PMode | None = None,
    steps: Steps = SILENT,
    **solve,
) -> MatchResult:
    """The landmark default of :func:`match`: each kind of :data:`AUTO_KINDS` solved on shapes prepared once
    (the eigenbasis refined), the least distorted map kept (the eigenbasis within :data:`AUTO_MARGIN`) unless
    another kind's held-out error is below :data:`CV_RATIO` of its own; a feature-aware choice is then refined
    and kept only if no more distorted than the eigenbasis's. ``skipped``: kinds not built, with the reason.
    ``landmarks``: ``(L, 2)``; the rest as :func:`match`.

    Raises:
        ParameterError: what the eigenbasis refuses, or an unknown refinement;
            :class:`~torchfmap.MemoryEstimateError` for a ``k`` too large for memory."""
    t0 = time.perf_counter()
    refine = check_refine(refine)
    pairs = check_landmark_pairs(landmarks, mesh_x.n_vertices, mesh_y.n_vertices)
    n_max = min(mesh_x.n_vertices, mesh_y.n_vertices) - 1
    check_count(k, 1, n_max, "k (basis size)")  # before any work
    check_solve_memory(k, k)
    need = [k, min(k_descriptors, n_max)]
    if refine == "zoomout":
        need.append(k_final or 2 * k)
    steps("operators and eigenpairs")
    shape_x, shape_y = prepare_shapes(mesh_x, mesh_y, shapes, min(max(need), n_max))
    prep = time.perf_counter() - t0
    pref = AUTO_KINDS[0]
    check_unused(get_kind(AUTO_KINDS[-1]), refine, k_final, None)
    check_zoomout_sizes(get_kind(pref), refine, k, k_final)
    steps("landmark reading check")
    warn_if_off_by_one(shape_x, shape_y, pairs)
    candidates: dict[str, MatchResult] = {}
    skipped: dict[str, str] = {}
    fold_maps: dict = {}  # shared by the refinement check and the basis check

    def refined(result: MatchResult, kind: BasisKind) -> MatchResult:
        def make_refiner(fold_pairs: np.ndarray, bar: bool = False):
            return kind.refiner(
                refine, k_final=k_final, mode=p2p_mode, n_fixed=len(fold_pairs),
                times=times if kind.needs_landmarks else None, zoomout_samples=zoomout_samples,
                landmarks=fold_pairs, progress=bar,
            )  # fmt: skip

        return refine_guarded(
            result, kind, shape_x, shape_y, pairs, k, make_refiner, times=times, p2p_mode=p2p_mode,
            steps=steps, k_descriptors=k_descriptors, fold_maps=fold_maps, **solve,
        )  # fmt: skip

    for name in AUTO_KINDS:
        kind = get_kind(name)
        first = name == pref
        try:
            grow = (k_final or 2 * k) if first and refine == "zoomout" and kind.grows else 0
            result = solve_pair(
                shape_x, shape_y, kind, k, landmarks=pairs, times=times if kind.needs_landmarks else None,
                n_eigen=grow, k_descriptors=k_descriptors, p2p_mode=p2p_mode, steps=steps, **solve,
            )  # fmt: skip
            candidates[name] = refined(result, kind) if first and refine is not None else result
        except ParameterError as err:
            if first:  # the eigenbasis refuses only what every kind would
                raise
            skipped[name] = str(err)
    best = min(candidates, key=lambda n: candidates[n].distortion)
    if candidates[best].distortion > (1 - AUTO_MARGIN) * candidates[pref].distortion:
        best = pref
    fold_scores: dict[str, float] = {}
    t_cv = time.perf_counter()
    if len(pairs) >= CV_MIN_LANDMARKS:  # the landmarks as the judge: a clear verdict overrides
        cv_solve = dict(solve, k_descriptors=k_descriptors, p2p_mode=p2p_mode, steps=steps)
        fold_scores = landmark_scores(
            shape_x, shape_y, pairs, list(candidates), k, times=times, fold_maps=fold_maps, **cv_solve
        )
        top = min(fold_scores, key=fold_scores.get) if fold_scores else best
        if best in fold_scores and fold_scores[top] < CV_RATIO * fold_scores[best]:
            best = top
    t_cv = time.perf_counter() - t_cv
    if refine is not None and best != pref:
        candidates[best] = refined(candidates[best], get_kind(best))
    if candidates[best].distortion > candidates[pref].distortion:
        best = pref  # do no harm: never a map more distorted than the eigenbasis's
    chosen = candidates[best]
    timings = {"prepare": prep, "cross-validation": t_cv}
    for name, c in candidates.items():
        timings |= {f"{name}:{step}": t for step, t in c.timings.items()}
    return dataclasses.replace(
        chosen, timings=timings, candidates=candidates, skipped=skipped, fold_scores=fold_scores
    )
