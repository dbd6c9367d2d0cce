"""The classical matching pipeline: bases -> descriptors -> functional map -> point map -> refinement.

:func:`match` is the recipe; each step is public for callers with their own bases or
descriptors. What a basis *kind* means (whether it needs landmarks, how its functions are
built, its solver weights, point-map rule and refiner) lives in the registry
:data:`torchfmap.kinds.KINDS`; this module reads it and never compares kind names.

:func:`match` dispatches: one kind (:func:`solve_pair` on shapes prepared once, then the kind's
refiner), or, with landmarks and no ``basis``, the landmark default
(:func:`match_landmark_default`: :func:`solve_pair` per candidate kind, the least distorted map
kept). Evaluating whole collections is :mod:`torchfmap.collection`.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Literal

import numpy as np

from ._checks import check_count
from .bases import Basis
from .bases.prepared import PreparedShape, check_prepared, prepare_shape, with_eigenpairs
from .descriptors import WKS_ENERGIES, landmark_descriptors, normalize_descriptors, wks
from .errors import ParameterError
from .fmap import check_landmark_pairs, solve_fmap
from .fmap.defaults import W_DCOMM, W_LMK, W_PRIOR
from .kinds import BasisKind, get_kind
from .kinds.refiners import check_eigenbases, check_refine
from .match_checks import check_k_final, check_unused, given_bases_kind
from .mesh import Mesh
from .quality import OFF_BY_ONE_RATIO, geodesic_distortion, landmark_distortion, warn_collapsed
from .quality import warn_if_off_by_one as warn_if_off_by_one
from .results import MatchResult, RefineMethod, refine_result

P2PMode = Literal["pullback", "orthogonal"]
#: The kinds the landmark default (``basis=None`` or ``'auto'`` with landmarks) solves in, in
#: order of preference: the eigenbasis first (optimal for isometries), then the feature-aware
#: ``hybrid``. ``diffusion`` is not a candidate: its maps are built by trilateration from the
#: landmarks, so they preserve geodesic distances by construction and score a lower distortion
#: than maps with lower error (python -m bench accuracy --case landmark_default: chosen on 1 of 6
#: near-isometric pairs
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
    "match_landmark_default",
    "prepare_shape",
    "refine_result",
    "solve_pair",
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
    correspond): ``KINDS[kind].pair_bases`` (:data:`torchfmap.kinds.KINDS`). The seed pairs are
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


def solve_pair(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    kind: str | BasisKind,
    k: int,
    *,
    landmarks: np.ndarray | None = None,
    bases: tuple[Basis, Basis] | None = None,
    seeds: np.ndarray | None = None,
    times=None,
    n_descriptors: int = 20,
    k_descriptors: int = 100,
    w_lap: float | None = None,
    w_orient: float | None = None,
    w_dcomm: float = W_DCOMM,
    w_lmk: float = W_LMK,
    w_prior: float | None = None,
    p2p_mode: P2PMode | None = None,
    n_eigen: int = 0,
) -> MatchResult:
    """The unrefined map of one kind on prepared shapes (the solve step :func:`match` and
    :func:`match_landmark_default` share): eigenpairs grown in place to what the kind, its
    descriptors and ``n_eigen`` (e.g. a later ZoomOut) need -> :func:`match_bases` (or the
    given ``bases``) -> :func:`match_descriptors` -> the kind's ``solve_map`` (each block by
    :func:`~torchfmap.fmap.solve_fmap` with the kind's weights unless given) -> the kind's
    ``to_p2p``.

    ``landmarks``: checked ``(L, 2)`` pairs, or None; ``bases``: given ``(basis_x, basis_y)`` of
    ``k`` columns, ``seeds`` their seed pairs ``(S, 2)`` if built together (then pulled to
    ``C = I``), else None; the rest as :func:`match`. Returns an unrefined :class:`MatchResult`
    (``distortion`` set with landmarks; timings ``operators+eigen``, ``basis``,
    ``descriptors``, ``fmap+p2p``).

    Raises:
        ParameterError: as the kind's bases, or ``k`` / ``k_descriptors`` out of range.
    """
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    kind = get_kind(kind)
    n_max = min(shape_x.mesh.n_vertices, shape_y.mesh.n_vertices) - 1
    k = check_count(k, 1, n_max, "k (basis size)")
    k_descriptors = min(check_count(k_descriptors, 2, 10**9, "k_descriptors"), n_max)  # small meshes
    prior = kind.needs_landmarks and (bases is None or seeds is not None)  # else columns need not correspond
    w_prior = (W_PRIOR if w_prior is None else w_prior) if prior else 0.0
    need_desc = kind.uses_descriptors(w_prior)
    n_eigen = max(kind.n_eigen(k), n_eigen, k_descriptors if need_desc else 0)
    for shape in (shape_x, shape_y):
        with_eigenpairs(shape, n_eigen)
    timings["operators+eigen"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if bases is None:
        bx, by, seeds = match_bases(shape_x, shape_y, kind, k, landmarks, times)
    else:
        bx, by = bases
    timings["basis"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if need_desc:
        desc_x, desc_y = match_descriptors(
            shape_x, shape_y, landmarks, n_descriptors=n_descriptors, k_descriptors=k_descriptors
        )
    timings["descriptors"] = time.perf_counter() - t0

    t0 = time.perf_counter()

    def solve_block(block_x: Basis, block_y: Basis, prior) -> np.ndarray:
        return solve_fmap(
            block_x, block_y, desc_x, desc_y, w_lap=kind.w_lap if w_lap is None else w_lap,
            w_orient=kind.w_orient if w_orient is None else w_orient, w_dcomm=w_dcomm,
            meshes=(shape_x.mesh, shape_y.mesh), landmarks=landmarks,
            w_lmk=w_lmk if landmarks is not None else 0.0, prior=prior,
            w_prior=w_prior if prior is not None else 0.0,
        )  # fmt: skip

    C = kind.solve_map(bx, by, solve_block, w_prior)
    p2p = kind.to_p2p(C, bx, by, p2p_mode or kind.p2p_mode)
    timings["fmap+p2p"] = time.perf_counter() - t0
    distortion = None
    if landmarks is not None:  # the score that chooses among kinds and guards the refinement
        distortion = geodesic_distortion(shape_x, shape_y, p2p)
    return MatchResult(p2p, C, bx, by, p2p, timings, seeds, kind.name, distortion)


def _shapes(mesh_x: Mesh, mesh_y: Mesh, shapes, n_eigen: int) -> tuple[PreparedShape, PreparedShape]:
    """``shapes`` checked (eigenpairs grown in place to ``n_eigen``), else both meshes prepared."""
    if shapes is None:
        return prepare_shape(mesh_x, n_eigen), prepare_shape(mesh_y, n_eigen)
    return tuple(with_eigenpairs(s, n_eigen) for s in check_prepared(shapes, (mesh_x, mesh_y)))


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
    :func:`~torchfmap.fmap.solve_fmap` -> :func:`~torchfmap.fmap.fmap_to_p2p` (together
    :func:`solve_pair`) -> the kind's refiner (:meth:`~torchfmap.kinds.BasisKind.refiner`,
    :func:`refine_result`).

    The default basis: without landmarks, the Laplacian eigenbasis. With landmarks, ``match``
    chooses without ground truth (``basis='auto'``, :func:`match_landmark_default`): the map of
    least geodesic distortion among the kinds of :data:`AUTO_KINDS`; ``kind``, ``distortion``
    and ``candidates`` of the result say what was chosen and why. With landmarks, a refinement
    that raises the distortion is dropped (the start is kept), for every kind. The
    feature-aware ``basis='diffusion'`` builds ``k`` heat kernels at corresponding seeds (see
    :func:`match_bases`), whose map is close to the identity; its solve is pulled to ``C = I``
    with weight ``w_prior`` (default :data:`~torchfmap.fmap.defaults.W_PRIOR`; at ``inf`` the
    identity is the map and no descriptors are computed).

    Args:
        mesh_x, mesh_y: source and target.
        landmarks: ``(L, 2)`` corresponding pairs ``(vertex on x, vertex on y)``; required by
            the feature-aware bases, used as descriptors and constraints by the eigenbasis.
        basis: a kind of :data:`torchfmap.kinds.KINDS` (``'laplacian'``, ``'diffusion'``,
            ``'harmonic'``, ``'stack'``, ``'hybrid'``, ``'eigen_diffusion'``), or ``'auto'``;
            default: ``'auto'`` with landmarks, ``'laplacian'`` without (see above).
        k: basis size; every basis has exactly ``k`` columns.
        refine: ``'icp'`` or ``'zoomout'`` (the kind's own refiner: the eigenbasis grows up to
            ``k_final``, default ``2k``; feature-aware kinds iterate at a fixed size from the
            current map, then move their seeds), or None.
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
            ``basis`` names their kind for the defaults (default: ``'laplacian'`` if every
            column is an eigenfunction, else ``'stack'``). The map is solved in all their
            columns (``k`` is ignored), except for ZoomOut of eigenbases: solved in their first
            ``k`` columns and grown within their own eigenfunctions to ``k_final`` (default
            ``2k``; they must hold that many). Other given bases refine by ICP, or, built
            together at corresponding seeds, by the kind's own refiner.
        shapes: ``(prepare_shape(mesh_x, ...), prepare_shape(mesh_y, ...))`` to reuse across
            pairs (operators, eigenpairs, geodesic rows and heat kernels are then computed once
            per shape, not once per pair); eigenpairs are extended in place when a call needs
            more. The maps are the same as without.

    Raises:
        ParameterError: unknown basis or refinement, a feature-aware basis without landmarks,
            an invalid ``k``, given bases that do not fit the meshes, or given eigenbases with
            fewer columns than ZoomOut's ``k_final``; :class:`~torchfmap.SeedError` for invalid
            landmarks.
    """
    t0 = time.perf_counter()
    refine = check_refine(refine)
    pairs = None
    if landmarks is not None and len(np.atleast_1d(landmarks)):
        pairs = check_landmark_pairs(landmarks, mesh_x.n_vertices, mesh_y.n_vertices)
    if basis == "auto" and (pairs is None or bases is not None):
        raise ParameterError(
            "basis='auto' chooses among bases built at landmarks. Fix: pass landmarks, or name a "
            "basis (e.g. basis='laplacian')."
        )
    solve = dict(
        n_descriptors=n_descriptors, k_descriptors=k_descriptors, w_lap=w_lap, w_orient=w_orient,
        w_dcomm=w_dcomm, w_lmk=w_lmk, w_prior=w_prior, p2p_mode=p2p_mode,
    )  # fmt: skip
    if basis in (None, "auto") and pairs is not None and bases is None:
        result = match_landmark_default(
            mesh_x, mesh_y, pairs, k=k, refine=refine, k_final=k_final, times=times,
            zoomout_samples=zoomout_samples, shapes=shapes, **solve,
        )  # fmt: skip
        warn_collapsed(result.p2p_yx, mesh_x.n_vertices)
        return result
    kind, together = get_kind(basis or "laplacian"), False
    if bases is not None:  # together: built as a pair at corresponding seeds (columns correspond)
        given_x, given_y, kind, together = given_bases_kind(bases, mesh_x, mesh_y, basis)
    # ZoomOut of given eigenbases grows within them (from their first k columns)
    given_eigen = bases is not None and refine == "zoomout" and kind.grows and not kind.needs_landmarks
    if bases is not None and refine == "zoomout" and not given_eigen and not together:
        raise ParameterError(
            "ZoomOut grows nested bases: given bases only support it as eigenbases. Fix: "
            "refine='icp', or basis='laplacian' with eigenbasis files."
        )
    if bases is not None and not given_eigen:
        k = min(given_x.k, given_y.k)
    n_max = min(mesh_x.n_vertices, mesh_y.n_vertices) - 1
    k = check_count(k, 1, n_max, "k (basis size)")
    check_count(k_descriptors, 2, 10**9, "k_descriptors")
    check_unused(kind, refine, k_final, times)
    check_k_final(kind, refine, k, k_final)
    grow = refine == "zoomout" and kind.grows
    eigenbases = (given_x, given_y) if given_eigen else None
    if given_eigen:  # refused before any work
        check_eigenbases(eigenbases, k_final or 2 * k)
    grow_shapes = (k_final or 2 * k) if grow and eigenbases is None else 0  # ZoomOut's eigenpairs
    shape_x, shape_y = _shapes(mesh_x, mesh_y, shapes, 0)
    if pairs is not None:
        warn_if_off_by_one(shape_x, shape_y, pairs)
    prep = time.perf_counter() - t0
    given = None if bases is None else (given_x.truncated(k), given_y.truncated(k))
    seeds = np.asarray(given_x.pair_landmarks) if together else None
    result = solve_pair(
        shape_x, shape_y, kind, k, landmarks=pairs, bases=given, seeds=seeds, times=times,
        n_eigen=grow_shapes, **solve,
    )  # fmt: skip
    result.timings["operators+eigen"] += prep
    if refine is not None:
        refiner = kind.refiner(
            refine, k_final=k_final, mode=p2p_mode, n_fixed=0 if pairs is None else len(pairs), times=times,
            zoomout_samples=zoomout_samples, eigenbases=eigenbases,
        )  # fmt: skip
        result = refine_result(result, refiner, shape_x, shape_y)
    warn_collapsed(result.p2p_yx, mesh_x.n_vertices)
    return result


def match_landmark_default(
    mesh_x: Mesh,
    mesh_y: Mesh,
    landmarks: np.ndarray,
    *,
    k: int = 50,
    refine: RefineMethod | None = None,
    k_final: int | None = None,
    times=None,
    zoomout_samples: int | None = None,
    shapes: tuple[PreparedShape, PreparedShape] | None = None,
    k_descriptors: int = 100,
    p2p_mode: P2PMode | None = None,
    **solve,
) -> MatchResult:
    """The landmark default of :func:`match` (``basis=None`` or ``'auto'`` with landmarks): each
    kind of :data:`AUTO_KINDS` solved (:func:`solve_pair`) on shapes prepared once, the
    eigenbasis refined as asked (ZoomOut is where it gains most) and the feature-aware kinds
    unrefined; the map of least geodesic distortion is kept (the eigenbasis within
    :data:`AUTO_MARGIN`), and a chosen feature-aware map is then refined (guarded by the same
    score), so only one feature-aware refinement runs. Kinds that cannot be built on these
    meshes (e.g. too few vertices for their columns) are skipped, with the reason
    (``skipped``); ``candidates`` holds each solved kind's result (:func:`match` warns if the
    chosen map collapsed). ``landmarks``: ``(L, 2)``
    pairs; ``solve``: the other solver settings of :func:`solve_pair`; the rest as :func:`match`.

    Raises:
        ParameterError: what the eigenbasis refuses (it refuses only what every kind would),
            or an unknown refinement.
    """
    t0 = time.perf_counter()
    refine = check_refine(refine)
    pairs = check_landmark_pairs(landmarks, mesh_x.n_vertices, mesh_y.n_vertices)
    n_max = min(mesh_x.n_vertices, mesh_y.n_vertices) - 1
    check_count(k, 1, n_max, "k (basis size)")  # the eigenbasis's own check, before any work
    need = [k, min(k_descriptors, n_max)]  # the eigenbasis: k, and its descriptors
    if refine == "zoomout":
        need.append(k_final or 2 * k)
    shape_x, shape_y = _shapes(mesh_x, mesh_y, shapes, min(max(need), n_max))
    prep = time.perf_counter() - t0
    pref = AUTO_KINDS[0]
    check_unused(get_kind(AUTO_KINDS[-1]), refine, k_final, None)
    check_k_final(get_kind(pref), refine, k, k_final)
    warn_if_off_by_one(shape_x, shape_y, pairs)
    candidates: dict[str, MatchResult] = {}
    skipped: dict[str, str] = {}

    def refined(result: MatchResult, kind: BasisKind) -> MatchResult:
        refiner = kind.refiner(
            refine, k_final=k_final, mode=p2p_mode, n_fixed=len(pairs),
            times=times if kind.needs_landmarks else None, zoomout_samples=zoomout_samples,
        )  # fmt: skip
        return refine_result(result, refiner, shape_x, shape_y)

    for name in AUTO_KINDS:
        kind = get_kind(name)
        first = name == pref
        try:
            grow = (k_final or 2 * k) if first and refine == "zoomout" and kind.grows else 0
            result = solve_pair(
                shape_x, shape_y, kind, k, landmarks=pairs, times=times if kind.needs_landmarks else None,
                n_eigen=grow, k_descriptors=k_descriptors, p2p_mode=p2p_mode, **solve,
            )  # fmt: skip
            candidates[name] = refined(result, kind) if first and refine is not None else result
        except ParameterError as err:
            if first:  # the eigenbasis refuses only what every kind would
                raise
            skipped[name] = str(err)
    best = min(candidates, key=lambda n: candidates[n].distortion)
    if candidates[best].distortion > (1 - AUTO_MARGIN) * candidates[pref].distortion:
        best = pref
    if refine is not None and best != pref:
        candidates[best] = refined(candidates[best], get_kind(best))
    chosen = candidates[best]
    timings = {"prepare": prep}
    for name, c in candidates.items():
        timings |= {f"{name}:{step}": t for step, t in c.timings.items()}
    return dataclasses.replace(chosen, timings=timings, candidates=candidates, skipped=skipped)
