"""The classical matching pipeline: bases -> descriptors -> functional map -> point map -> refinement.

:func:`match` is the recipe; each step is public for callers with their own bases or
descriptors. What a basis *kind* means (whether it needs landmarks, how its functions are
built, its solver weight, point-map rule and refinement) lives in the registry
:data:`torchfmap.bases.KINDS`; this module reads it and never compares kind names.
Evaluating whole collections is :mod:`torchfmap.collection`.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from typing import Literal

import numpy as np

from ._checks import check_count
from .bases import Basis
from .bases.prepared import PreparedShape, check_prepared, prepare_shape, with_eigenpairs
from .descriptors import WKS_ENERGIES, landmark_descriptors, normalize_descriptors, wks
from .errors import MapWarning, ParameterError
from .fmap import check_landmark_pairs, solve_fmap
from .fmap.defaults import W_DCOMM, W_LMK, W_PRIOR
from .kinds import BasisKind, get_kind, kind_of
from .match_checks import check_given_bases, check_unused
from .mesh import Mesh
from .quality import (
    OFF_BY_ONE_RATIO,
    geodesic_distortion,
    landmark_distortion,
    map_seeds,
    warn_collapsed,
)
from .quality import warn_if_off_by_one as warn_if_off_by_one
from .results import MatchContext, MatchResult, RefineMethod, refine_result

P2PMode = Literal["pullback", "orthogonal"]
#: The kinds the landmark default (``basis=None`` or ``'auto'`` with landmarks) solves in, in
#: order of preference: the eigenbasis first (optimal for isometries), then the feature-aware
#: ``hybrid``. ``diffusion`` is not a candidate: its maps are built by trilateration from the
#: landmarks, so they preserve geodesic distances by construction and score a lower distortion
#: than maps with lower error (bench/landmark_default.py: chosen on 1 of 6 near-isometric pairs
#: at 7 landmarks, 1.24x the eigenbasis's error there).
AUTO_KINDS = ("laplacian", "hybrid")
#: The landmark default keeps the eigenbasis unless a feature-aware map distorts geodesic
#: distances by this fraction less (:func:`~torchfmap.quality.geodesic_distortion`): on
#: near-isometric pairs the scores of good maps differ by discretisation noise, and there the
#: eigenbasis is the better basis.
AUTO_MARGIN = 0.1

__all__ = [
    "AUTO_KINDS",
    "AUTO_MARGIN",
    "OFF_BY_ONE_RATIO",
    "MatchResult",
    "PreparedShape",
    "landmark_distortion",
    "match",
    "match_bases",
    "match_descriptors",
    "prepare_shape",
    "refine_result",
    "warn_if_off_by_one",
]


def match_descriptors(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    landmarks: np.ndarray | None = None,
    *,
    n_descriptors: int = 20,
    k_descriptors: int = 100,
) -> tuple[np.ndarray, np.ndarray]:
    """``(V_x, D)``, ``(V_y, D)`` descriptors of :func:`match`, normalised (unit B-norm columns).

    ``n_descriptors`` WKS columns (evenly subsampled from
    :data:`~torchfmap.descriptors.WKS_ENERGIES` energies computed on the first
    ``k_descriptors`` eigenpairs of each prepared shape), then, with ``landmarks`` ``(L, 2)``,
    two heat kernels per landmark (:func:`~torchfmap.descriptors.landmark_descriptors`).

    Raises:
        ParameterError: ``n_descriptors < 1`` or shapes prepared without eigenpairs.
    """
    if n_descriptors < 1:
        raise ParameterError(f"n_descriptors must be >= 1, got {n_descriptors}.")
    out = []
    for s, shape in enumerate((shape_x, shape_y)):
        if shape.eigenbasis is None:
            raise ParameterError("WKS descriptors need eigenpairs. Fix: prepare_shape(mesh, n_eigen > 0).")
        eig = shape.eigenbasis.truncated(min(k_descriptors, shape.eigenbasis.k))
        step = max(1, WKS_ENERGIES // n_descriptors)
        parts = [wks(eig.eigenvalues, eig.values)[:, ::step][:, :n_descriptors]]
        if landmarks is not None:
            parts.append(landmark_descriptors(landmarks[:, s], operators=shape.operators))
        out.append(normalize_descriptors(np.hstack(parts), shape.operators[1]))
    return out[0], out[1]


def match_bases(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    kind: str | BasisKind,
    k: int,
    landmarks: np.ndarray | None = None,
    times=None,
) -> tuple[Basis, Basis, np.ndarray | None]:
    """The pair of B-orthonormal bases :func:`match` solves in, with exactly ``k`` columns each,
    and the corresponding seed pairs ``(S, 2)`` they are built at (None when the columns do not
    correspond): ``KINDS[kind].pair_bases`` (:data:`torchfmap.bases.KINDS`). The seed pairs are
    also recorded on both bases (``Basis.pair_landmarks``, saved with them), so that
    ``match(bases=...)`` can tell them from bases built apart.

    Raises:
        ParameterError: an unknown kind, a kind that needs landmarks without them, or ``k``
            outside its range.
    """
    bx, by, seeds = get_kind(kind).pair_bases(shape_x, shape_y, k, landmarks, times)
    if seeds is not None:  # recorded (and saved with the bases): they were built together
        bx.pair_landmarks = by.pair_landmarks = np.asarray(seeds, dtype=np.int64).reshape(-1, 2)
    return bx, by, seeds


def match(
    mesh_x: Mesh,
    mesh_y: Mesh,
    *,
    landmarks=None,
    basis: BasisKind | None = None,
    k: int = 50,
    refine: RefineMethod | None = None,
    k_final: int | None = None,
    n_descriptors: int = 20,
    k_descriptors: int = 100,
    w_lap: float | None = None,
    w_orient: float | None = None,
    w_dcomm: float = W_DCOMM,
    w_lmk: float = W_LMK,
    w_prior: float | None = None,
    times=None,
    p2p_mode: P2PMode | None = None,
    zoomout_samples: int | None = None,
    bases: tuple[Basis, Basis] | None = None,
    shapes: tuple[PreparedShape, PreparedShape] | None = None,
) -> MatchResult:
    """Match ``y`` to ``x``: returns ``p2p_yx`` and ``C_xy``.

    The steps, each public for callers with their own bases or descriptors:
    :func:`prepare_shape` -> :func:`match_bases` -> :func:`match_descriptors` ->
    :func:`~torchfmap.fmap.solve_fmap` -> :func:`~torchfmap.fmap.fmap_to_p2p` -> the kind's
    :meth:`~torchfmap.kinds.BasisKind.refine`.

    The default basis: without landmarks, the Laplacian eigenbasis. With landmarks, ``match``
    chooses without ground truth (``basis='auto'``): it solves the pair in each kind of
    :data:`AUTO_KINDS` (the eigenbasis, where landmarks enter as descriptors and constraints,
    refined as asked, and the feature-aware ``hybrid`` kind, built at the landmarks) and keeps
    the map that preserves geodesic distances best
    (:func:`~torchfmap.quality.geodesic_distortion`), the eigenbasis unless the other map
    distorts them :data:`AUTO_MARGIN` less (a chosen ``hybrid`` map is then refined); ``kind``,
    ``distortion`` and ``candidates`` of the result say what was chosen and why. With landmarks,
    a refinement that raises the distortion is dropped (the start is kept), for
    every kind. The feature-aware ``basis='diffusion'`` builds ``k``
    heat kernels at corresponding seeds (see :func:`match_bases`), whose map is close to the
    identity; its solve is pulled to ``C = I`` with weight ``w_prior`` (default
    :data:`~torchfmap.fmap.defaults.W_PRIOR`; at ``inf`` the identity is the map and no
    descriptors are computed).

    Args:
        mesh_x, mesh_y: source and target.
        landmarks: ``(L, 2)`` corresponding pairs ``(vertex on x, vertex on y)``; required by
            the feature-aware bases, used as descriptors and constraints by the eigenbasis.
        basis: a kind of :data:`torchfmap.bases.KINDS` (``'laplacian'``, ``'diffusion'``,
            ``'harmonic'``, ``'stack'``, ``'hybrid'``, ``'eigen_diffusion'``), or ``'auto'``;
            default: ``'auto'`` with landmarks, ``'laplacian'`` without (see above).
        k: basis size; every basis has exactly ``k`` columns.
        refine: ``'icp'`` or ``'zoomout'`` (the kind's own refinement: the eigenbasis
            grows up to ``k_final``, default ``2k``; feature-aware kinds iterate at a fixed
            size from the current map, then move their seeds), ``'seeded'`` (without
            landmarks: ZoomOut, then the pair solved again with the seeds where that map agrees
            both ways as landmarks, and ZoomOut; see :func:`_match_seeded`), or None.
        n_descriptors, k_descriptors: see :func:`match_descriptors`.
        w_lap, w_orient, w_dcomm, w_lmk: weights of Laplacian commutativity (default
            the kind's ``w_lap``), orientation preservation (tells left from right,
            which WKS alone cannot), descriptor commutativity and pointwise landmark
            preservation (see :func:`~torchfmap.fmap.solve_fmap`; defaults: the kind's
            ``w_orient``, :data:`~torchfmap.fmap.defaults.W_DCOMM`, ``W_LMK``). With the last
            three at 0 the solve is the exact row-wise one; otherwise preconditioned CG.
        w_prior: proximity-to-identity weight for feature-aware bases (see above).
        times: relative diffusion times of feature-aware bases (default: one time,
            :func:`~torchfmap.kinds.seed_time` of the seed count).
        p2p_mode: functional map -> point map conversion (:func:`~torchfmap.fmap.fmap_to_p2p`);
            default: the kind's ``p2p_mode`` (``'orthogonal'`` for the eigenbasis).
        zoomout_samples: run eigenbasis ZoomOut on this many farthest-point samples per shape
            (the final point map uses every vertex).
        bases: ``(basis_x, basis_y)`` to solve in instead of building them (e.g. files written
            by ``torchfmap basis``; ``(V_x, K_x)`` and ``(V_y, K_y)``, B-orthonormal). Their
            columns are not assumed to correspond, so the map is solved from descriptors;
            ``k`` is ignored; ``basis`` names their kind for the defaults (default:
            ``'laplacian'`` if every column is an eigenfunction, else ``'stack'``); ZoomOut
            needs ``'laplacian'`` bases (ICP works in any).
        shapes: ``(prepare_shape(mesh_x, ...), prepare_shape(mesh_y, ...))`` to reuse across
            pairs (operators, eigenpairs, geodesic rows and heat kernels are then computed once
            per shape, not once per pair); eigenpairs are extended in place when a call needs
            more. The maps are the same as without.

    Raises:
        ParameterError: unknown basis or refinement, a feature-aware basis without landmarks,
            an invalid ``k``, or given bases that do not fit the meshes;
            :class:`~torchfmap.SeedError` for invalid landmarks.
    """
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    pairs = None
    if landmarks is not None and len(np.atleast_1d(landmarks)):
        pairs = check_landmark_pairs(landmarks, mesh_x.n_vertices, mesh_y.n_vertices)
    # the eigenbasis, with or without landmarks: on the dev benchmarks it is the best or tied
    # default at 3-15 landmarks (bench/faust.py, bench/feature_accuracy.py; the issue notes)
    if basis == "auto" and (pairs is None or bases is not None):
        raise ParameterError(
            "basis='auto' chooses among bases built at landmarks. Fix: pass landmarks, or name a "
            "basis (e.g. basis='laplacian')."
        )
    if refine == "seeded":
        if pairs is not None or bases is not None or basis not in (None, "laplacian"):
            raise ParameterError(
                "refine='seeded' seeds a second solve from the eigenbasis map without landmarks. Fix: "
                "drop landmarks / bases / basis, or refine='zoomout'."
            )
        passed = dict(
            k=k, k_final=k_final, n_descriptors=n_descriptors, k_descriptors=k_descriptors,
            w_lap=w_lap, w_orient=w_orient, w_dcomm=w_dcomm, w_lmk=w_lmk, p2p_mode=p2p_mode,
            zoomout_samples=zoomout_samples,
        )  # fmt: skip
        return _match_seeded(mesh_x, mesh_y, shapes, passed)
    if basis in (None, "auto") and pairs is not None and bases is None:
        passed = dict(
            k=k, refine=refine, k_final=k_final, n_descriptors=n_descriptors, k_descriptors=k_descriptors,
            w_lap=w_lap, w_orient=w_orient, w_dcomm=w_dcomm, w_lmk=w_lmk, w_prior=w_prior, times=times,
            p2p_mode=p2p_mode, zoomout_samples=zoomout_samples,
        )  # fmt: skip
        return _match_auto(mesh_x, mesh_y, pairs, shapes, passed)
    name = basis or "laplacian"
    together = False  # given bases built as a pair at corresponding seeds: their columns correspond
    if bases is not None:
        given_x, given_y, together = check_given_bases(bases, mesh_x, mesh_y)
        eigen_only = all(c.family == "laplacian" for b in (given_x, given_y) for c in b.columns if c.kept)
        seeded = kind_of(given_x) if together else None
        name = basis or ("laplacian" if eigen_only else seeded or "stack")
        k = min(given_x.k, given_y.k)
    kind = get_kind(name)
    together = together and kind.needs_landmarks
    eigen_zoomout = kind.grows and not kind.needs_landmarks  # ZoomOut of given bases: eigenbases only
    if bases is not None and refine == "zoomout" and not eigen_zoomout and not together:
        raise ParameterError(
            "ZoomOut grows nested bases: given bases only support it as eigenbases. Fix: "
            "refine='icp', or basis='laplacian' with eigenbasis files."
        )
    n_max = min(mesh_x.n_vertices, mesh_y.n_vertices) - 1
    k = check_count(k, 1, n_max, "k (basis size)")
    k_descriptors = min(check_count(k_descriptors, 2, 10**9, "k_descriptors"), n_max)  # small meshes
    if refine not in (None, "icp", "zoomout"):
        raise ParameterError(f"unknown refinement {refine!r}. Fix: 'icp', 'zoomout', 'seeded' or None.")
    check_unused(kind, refine, k_final, times)
    grow = refine == "zoomout" and kind.grows
    if grow and k_final is not None and k_final < k:
        raise ParameterError(f"k_final={k_final} is below k={k}: ZoomOut grows the basis. Fix: k_final >= k.")
    prior = kind.needs_landmarks and (bases is None or together)  # else columns need not correspond
    w_prior = (W_PRIOR if w_prior is None else w_prior) if prior else 0.0
    need_desc = kind.uses_descriptors(w_prior)
    n_eigen = max(kind.n_eigen(k), (k_final or 2 * k) if grow else 0, k_descriptors if need_desc else 0)
    if shapes is None:
        shape_x, shape_y = prepare_shape(mesh_x, n_eigen), prepare_shape(mesh_y, n_eigen)
    else:
        shape_x, shape_y = (with_eigenpairs(s, n_eigen) for s in check_prepared(shapes, (mesh_x, mesh_y)))
    if pairs is not None:
        warn_if_off_by_one(shape_x, shape_y, pairs)
    timings["operators+eigen"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if bases is None:
        bx, by, seeds = match_bases(shape_x, shape_y, kind, k, pairs, times)
    else:
        bx, by = given_x.truncated(k), given_y.truncated(k)
        seeds = np.asarray(given_x.pair_landmarks) if together else None
    timings["basis"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if need_desc:
        desc_x, desc_y = match_descriptors(
            shape_x, shape_y, pairs, n_descriptors=n_descriptors, k_descriptors=k_descriptors
        )
    timings["descriptors"] = time.perf_counter() - t0

    t0 = time.perf_counter()

    def solve_block(block_x: Basis, block_y: Basis, prior) -> np.ndarray:
        return solve_fmap(
            block_x,
            block_y,
            desc_x,
            desc_y,
            w_lap=kind.w_lap if w_lap is None else w_lap,
            w_orient=kind.w_orient if w_orient is None else w_orient,
            w_dcomm=w_dcomm,
            meshes=(mesh_x, mesh_y),
            landmarks=pairs,
            w_lmk=w_lmk if pairs is not None else 0.0,
            prior=prior,
            w_prior=w_prior if prior is not None else 0.0,
        )

    C = kind.solve_map(bx, by, solve_block, w_prior)
    mode = p2p_mode or kind.p2p_mode
    p2p = kind.to_p2p(C, bx, by, mode)
    timings["fmap+p2p"] = time.perf_counter() - t0
    context = MatchContext(shape_x, shape_y, kind, k, k_final, mode, len(pairs) if pairs is not None else 0,
                       times, zoomout_samples)  # fmt: skip
    distortion = None
    if pairs is not None:  # the score that chooses among kinds and guards the refinement
        distortion = geodesic_distortion(shape_x, shape_y, p2p, context.anchors)
    result = MatchResult(p2p, C, bx, by, p2p, timings, seeds, kind.name, distortion, _context=context)
    if refine is not None:
        result = refine_result(result, refine)
    warn_collapsed(result.p2p_yx, mesh_x.n_vertices)
    return result


def _match_auto(mesh_x: Mesh, mesh_y: Mesh, pairs: np.ndarray, shapes, kwargs: dict) -> MatchResult:
    """The landmark default of :func:`match`: each kind of :data:`AUTO_KINDS` solved on shapes
    prepared once, the eigenbasis refined as asked (ZoomOut is where it gains most) and the
    feature-aware kinds unrefined; the map of least geodesic distortion is kept (the eigenbasis
    within :data:`AUTO_MARGIN`), and a chosen feature-aware map is then refined (guarded by the
    same score), so only one feature-aware refinement runs. Kinds that cannot be built on these
    meshes (e.g. too few vertices for their columns) are skipped, with the reason."""
    t0 = time.perf_counter()
    refine, k = kwargs.pop("refine"), kwargs["k"]
    n_max = min(mesh_x.n_vertices, mesh_y.n_vertices) - 1
    check_count(k, 1, n_max, "k (basis size)")  # the eigenbasis's own check, before any work
    need = [k, min(kwargs["k_descriptors"], n_max)]  # the eigenbasis: k, and its descriptors
    if refine == "zoomout":
        need.append(kwargs["k_final"] or 2 * k)
    n_eigen = min(max(need), n_max)
    if shapes is None:
        shapes = (prepare_shape(mesh_x, n_eigen), prepare_shape(mesh_y, n_eigen))
    prep = time.perf_counter() - t0
    candidates: dict[str, MatchResult] = {}
    skipped: dict[str, str] = {}
    check_unused(get_kind(AUTO_KINDS[-1]), refine, kwargs["k_final"], None)
    for name in AUTO_KINDS:
        kind = get_kind(name)
        first = name == AUTO_KINDS[0]
        passed = dict(kwargs, refine=refine if first else None)  # the others: once chosen
        passed.update(
            k_final=kwargs["k_final"] if first else None,
            times=kwargs["times"] if kind.needs_landmarks else None,
        )
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", MapWarning)  # said of the chosen map only, below
                if candidates:  # the first kind warned about the landmarks already
                    warnings.simplefilter("ignore", UserWarning)
                candidates[name] = match(mesh_x, mesh_y, landmarks=pairs, basis=name, shapes=shapes, **passed)
        except ParameterError as err:
            if name == AUTO_KINDS[0]:  # the eigenbasis refuses only what every kind would
                raise
            skipped[name] = str(err)
    pref = AUTO_KINDS[0]
    best = min(candidates, key=lambda n: candidates[n].distortion)
    if candidates[best].distortion > (1 - AUTO_MARGIN) * candidates[pref].distortion:
        best = pref
    chosen = candidates[best]
    if refine is not None and best != pref:
        ctx = dataclasses.replace(chosen._context, k_final=kwargs["k_final"])  # the caller's k_final
        chosen = candidates[best] = refine_result(dataclasses.replace(chosen, _context=ctx), refine)
    warn_collapsed(chosen.p2p_yx, mesh_x.n_vertices, stacklevel=4)
    timings = {"prepare": prep}
    for name, c in candidates.items():
        timings |= {f"{name}:{step}": t for step, t in c.timings.items()}
    return dataclasses.replace(chosen, timings=timings, candidates=candidates, skipped=skipped)


#: Farthest points of ``x`` offered as seeds by ``refine='seeded'``.
SEEDED_SEEDS = 40


def _match_seeded(mesh_x: Mesh, mesh_y: Mesh, shapes, kwargs: dict) -> MatchResult:
    """``refine='seeded'``: the eigenbasis map refined by ZoomOut (stage 1); seed pairs where it
    agrees both ways (:data:`SEEDED_SEEDS` farthest points of ``x`` sent to ``y`` and back by the
    orthogonal rule of ``C_xy`` and ``C_xyᵀ``, :func:`~torchfmap.seeds.consistent_seeds`);
    then the pair solved again with those seeds as landmarks (descriptors and constraints) in
    the eigenbasis and refined by ZoomOut, guarded by the geodesic distortion (stage 2). The
    result is stage 2's, with stage 1 as ``first_stage``; stage 1's when fewer than two seeds
    agree."""
    first = match(mesh_x, mesh_y, refine="zoomout", shapes=shapes, **kwargs)
    ctx = first._context
    bx, by, C = first.basis_x, first.basis_y, first.C_xy
    seeds = map_seeds(ctx.shape_x, C, C.T, bx.values, by.values, SEEDED_SEEDS)  # C_yx = C_xyᵀ
    if len(seeds) < 2:
        return first
    second = match(
        mesh_x, mesh_y, landmarks=seeds, basis="laplacian", refine="zoomout",
        shapes=(ctx.shape_x, ctx.shape_y), **kwargs,
    )  # fmt: skip
    timings = {f"stage1:{k}": v for k, v in first.timings.items()} | second.timings
    return dataclasses.replace(second, timings=timings, first_stage=first, seeds=seeds)
