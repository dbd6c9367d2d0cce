"""The landmark default of :func:`torchfmap.match` (``basis=None`` or ``'auto'`` with
landmarks): which basis to solve a pair in, chosen without ground truth.

Each kind of :data:`AUTO_KINDS` is solved on shapes prepared once
(:func:`~torchfmap.matching.solve.solve_pair`) and the map that preserves geodesic distances best is kept
(:data:`AUTO_MARGIN` in favour of the eigenbasis). Then the user's landmarks judge: each kind is
solved again with some landmarks held out and scored by where its map sends them
(:func:`landmark_scores`); a kind whose held-out error is below :data:`CV_RATIO` of the chosen
kind's replaces it.
"""

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

#: The kinds the landmark default (``basis=None`` or ``'auto'`` with landmarks) solves in, in
#: order of preference: the eigenbasis first (optimal for isometries), then the feature-aware
#: ``hybrid``; the cross-validation scores the same kinds. ``diffusion`` is not a candidate:
#: its maps are built by trilateration from the landmarks, so they preserve geodesic distances
#: by construction and score a lower distortion than maps with lower error, and once a
#: feature-aware map must also be no more distorted than the eigenbasis's (the last check of
#: :func:`match_landmark_default`) a cross-validated ``diffusion`` was never the map returned on
#: the dev sets (SMAL_r across species, cat-lion, TOSCA, FAUST_r; 3, 7 and 15 landmarks), while
#: its folds cost most (heat kernels at newly trilaterated seeds in every fold).
AUTO_KINDS = ("laplacian", "hybrid")
#: The landmark default keeps the eigenbasis unless a feature-aware map distorts geodesic
#: distances by this fraction less (:func:`~torchfmap.matching.quality.geodesic_distortion`): the score's
#: resolution (on near-isometric pairs the scores of good maps differ by discretisation noise,
#: and there the eigenbasis is the better basis).
AUTO_MARGIN = DISTORTION_RESOLUTION
#: Folds of the cross-validation, at most (one held-out landmark per fold when there are fewer).
CV_FOLDS = 4
#: The cross-validation needs this many landmarks (each fold then solves with two or more).
CV_MIN_LANDMARKS = 3
#: A refinement is cross-validated (:func:`refine_guarded`, reported, not a veto) from this many
#: landmarks: each of the :data:`CV_FOLDS` folds then keeps three or more.
CV_REFINE_MIN_LANDMARKS = 5
#: A cross-validated kind replaces the distortion's choice only when its held-out landmark error
#: is below this fraction of the chosen kind's: the held-out landmarks are few, so only a clear
#: verdict overrides the choice (two or three landmarks cannot rank close maps).
CV_RATIO = 0.5


def _folds(n_pairs: int, folds: int) -> list[np.ndarray]:
    """Fold ``f`` of ``F = min(folds, n_pairs)`` holds out the pairs ``i`` with ``i % F == f``."""
    n_folds = min(folds, n_pairs)
    return [np.arange(n_pairs) % n_folds == fold for fold in range(n_folds)]


def _fold_map(shape_x, shape_y, kind: BasisKind, k: int, pairs, held, fold: int, times, fold_maps, solve):
    """Fold ``fold``'s map of ``kind``, solved without the ``held`` pairs
    (:func:`~torchfmap.matching.solve.solve_functional_map`); ``fold_maps``: a dict kept by the
    caller (``(kind, fold) ->`` map), so the basis check and the refinement check of one match
    solve each fold once."""
    key = (kind.name, fold)
    if fold_maps is not None and key in fold_maps:
        return fold_maps[key]
    solved = solve_functional_map(
        shape_x,
        shape_y,
        kind,
        k,
        landmarks=pairs[~held],
        times=times if kind.needs_landmarks else None,
        **solve,
    )
    if fold_maps is not None:
        fold_maps[key] = solved
    return solved


def _check_cv(pairs: np.ndarray) -> None:
    if len(pairs) < CV_MIN_LANDMARKS:
        raise ParameterError(
            f"cross-validation holds landmarks out: {CV_MIN_LANDMARKS} or more are needed, got {len(pairs)}."
        )


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
    """Cross-validation of the basis by the user's landmarks: for each kind, the mean error at
    the held-out landmarks of maps solved (unrefined, :func:`~torchfmap.matching.solve.solve_functional_map`)
    with the others, converted (``p2p_mode``, default the kind's) at the held-out landmarks only.

    Fold ``f`` of ``F = min(folds, L)`` holds out the landmark pairs ``i`` with ``i % F == f``;
    a held-out pair ``(a, b)`` scores ``d_x(p2p_yx[b], a)``, the geodesic distance on ``x`` (in
    units of ``sqrt(area)``) between where the map sends ``b`` and where it should. Kinds that
    cannot be built on a fold are left out. ``times`` go to the feature-aware kinds; ``steps``
    names each fold as it starts; ``fold_maps``: a dict of the fold maps solved so far, read and
    filled (one match's checks share it); ``solve``: the other settings of
    :func:`~torchfmap.matching.solve.solve_pair`. Returns ``{kind: mean held-out
    error}``.

    Raises:
        ParameterError: fewer than :data:`CV_MIN_LANDMARKS` pairs.
    """
    _check_cv(pairs)
    rows = shape_x.distances.distances(pairs[:, 0])  # (L, V_x): distances from each true match
    every_fold = _folds(len(pairs), folds)
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
    """The refinement cross-validated by the user's landmarks: the mean held-out landmark error
    (as :func:`landmark_scores`, same folds) of each fold's map, unrefined and refined by
    ``make_refiner(fold_pairs)`` (the refiner the match runs, built on the fold's landmarks
    ``(L_f, 2)``; called as :func:`~torchfmap.matching.results.refine_result` calls it);
    ``fold_maps`` as there.
    Returns ``(raw, refined)`` mean held-out errors (units of ``sqrt(area_x)``): whether the
    refinement moves landmarks it was not given towards their partners or away from them, which
    :func:`~torchfmap.matching.results.refine_result` reports.

    Raises:
        ParameterError: fewer than :data:`CV_MIN_LANDMARKS` pairs, or as the kind and refiner.
    """
    _check_cv(pairs)
    rows = shape_x.distances.distances(pairs[:, 0])
    mode = p2p_mode or kind.p2p_mode
    samplings = pair_samplings(shape_x, shape_y)
    raw, refined = [], []
    every_fold = _folds(len(pairs), folds)
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
    """``result`` refined under the one guard (:mod:`~torchfmap.matching.results`, the
    distortion); with :data:`CV_REFINE_MIN_LANDMARKS` or more landmark ``pairs`` ``(L, 2)`` the
    refinement is also cross-validated and its held-out figures reported (:func:`refinement_scores`,
    the folds solved as ``result`` was: ``k``, ``times``, ``p2p_mode``, ``solve``, which may
    hold its ``fold_maps``).
    ``make_refiner(pairs, bar=False)``: the refiner on these landmarks (``bar``: its progress bar,
    shown for the whole map's refinement, not the folds'). ``cross_validate=False``: no folds
    (given bases, which folds cannot re-solve).

    Raises:
        ParameterError: as the refiner.
    """
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
    """The landmark default of :func:`match` (``basis=None`` or ``'auto'`` with landmarks): each
    kind of :data:`AUTO_KINDS` solved (:func:`solve_pair`) on shapes prepared once, the
    eigenbasis refined as asked (ZoomOut is where it gains most) and the feature-aware kinds
    unrefined; the map of least geodesic distortion is kept (the eigenbasis within
    :data:`AUTO_MARGIN`), and a chosen feature-aware map is then refined (guarded by the same
    score), so only one feature-aware refinement runs. With :data:`CV_MIN_LANDMARKS` or more
    landmarks, the landmark cross-validation (:func:`landmark_scores`, reported as
    ``fold_scores``) replaces that choice by the other kind when its held-out error is below
    :data:`CV_RATIO` of the chosen kind's (refined in turn). Last, a feature-aware map
    is returned only if, as returned (refined or not), it distorts geodesic distances no more
    than the eigenbasis's map: the cross-validation's evidence is a few raw folds, the refined
    eigenbasis is at hand, and neither check alone ranks every pair. Kinds that cannot be built on these
    meshes (e.g. too few vertices for their columns) are skipped, with the reason
    (``skipped``); ``candidates`` holds each solved kind's result (:func:`match` warns if the
    chosen map collapsed). ``landmarks``: ``(L, 2)``
    pairs; ``steps``: a :class:`~torchfmap._util.progress.Steps` naming each step as it starts;
    ``solve``: the other solver settings of :func:`solve_pair`; the rest as :func:`match`.

    Raises:
        ParameterError: what the eigenbasis refuses (it refuses only what every kind would),
            or an unknown refinement; :class:`~torchfmap.MemoryEstimateError` for a ``k`` whose
            solve would not fit in memory (before any work).
    """
    t0 = time.perf_counter()
    refine = check_refine(refine)
    pairs = check_landmark_pairs(landmarks, mesh_x.n_vertices, mesh_y.n_vertices)
    n_max = min(mesh_x.n_vertices, mesh_y.n_vertices) - 1
    check_count(k, 1, n_max, "k (basis size)")  # the eigenbasis's own check, before any work
    check_solve_memory(k, k)
    need = [k, min(k_descriptors, n_max)]  # the eigenbasis: k, and its descriptors
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

    fold_maps: dict = {}  # the folds' maps, solved once for the refinement check and the basis check

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
