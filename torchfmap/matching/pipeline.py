"""The classical matching pipeline: bases -> descriptors -> functional map -> point map -> refinement.

:func:`match` is the recipe; each step is public for callers with their own bases or
descriptors. What a basis *kind* means (whether it needs landmarks, how its functions are
built, its solver weights, point-map rule and refiner) lives in the registry
:data:`torchfmap.kinds.KINDS`; this module reads it and never compares kind names.

:func:`match` dispatches: one kind (:func:`solve_pair` on shapes prepared once, then the kind's
refiner), or, with landmarks and no ``basis``, the landmark default
(:func:`match_landmark_default`: :func:`solve_pair` per candidate kind, the least distorted map
kept). Evaluating whole collections is :mod:`torchfmap.evaluate.collection`.
"""

from __future__ import annotations

import time

import numpy as np

from .._util.checks import check_count
from .._util.progress import Steps
from ..bases import Basis
from ..bases.prepared import PreparedShape
from ..errors import ParameterError
from ..fmap import check_landmark_pairs
from ..fmap.defaults import DEFAULT_K, W_DCOMM, W_LMK
from ..fmap.refine import check_k_final
from ..fmap.solver import check_solve_memory
from ..kinds import BasisKind, get_kind
from ..kinds.base import relative_times
from ..kinds.refiners import RefineMethod, check_eigenbases, check_refine
from ..mesh import Mesh
from .checks import check_meshes, check_unused, check_zoomout_sizes, given_bases_kind, warn_if_partial
from .landmark_default import match_landmark_default, refine_guarded
from .overlap import match_partial_pair
from .partial import match_partial
from .quality import warn_collapsed
from .quality import warn_if_off_by_one as warn_if_off_by_one
from .results import MatchResult
from .solve import P2PMode, prepare_shapes, solve_pair

__all__ = ["match"]


def check_partial(partial) -> bool | str:
    """``partial`` as ``match`` takes it: False, True (``y`` a part of ``x``) or ``'both'`` (two
    overlapping parts).

    Raises:
        ParameterError: anything else.
    """
    if isinstance(partial, (bool, np.bool_)):
        return bool(partial)
    if isinstance(partial, str) and partial == "both":
        return partial
    raise ParameterError(
        f"partial is False, True (y a part of x) or 'both' (two parts of one whole, overlapping partly), "
        f"got {partial!r}."
    )


def match(
    mesh_x: Mesh,
    mesh_y: Mesh,
    *,
    landmarks=None,
    basis: BasisKind | None = None,
    k: int = DEFAULT_K,
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
    partial: bool | str = False,
    progress: bool = False,
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
    and ``candidates`` of the result say what was chosen and why. A refinement that raises the
    geodesic distortion is dropped (the start is kept), for every kind, with or without
    landmarks (:func:`~torchfmap.matching.results.refine_result`). The
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
        zoomout_samples: run eigenbasis ZoomOut on about this many surface samples per shape
            (:func:`~torchfmap.fmap.nearest.surface_sampling`; the final point map is every
            vertex's, searched locally). None: every vertex up to ``LOCAL_SEARCH_PAIRS``
            (``fmap.defaults``), surface samples past it (dense meshes).
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
        partial: ``y`` is a part of ``x`` (a cut, a scan of one side, a shape with holes), both
            in the same units: the partial functional map of :mod:`torchfmap.matching.partial` (the
            eigenbases in one frame, a rank-limited ``C_xy`` ``(r, k)``, ZoomOut within the
            part's rank, SHOT descriptors; ``result.overlap`` ``(V_x,)`` the estimated part on
            the whole). ``'both'``: ``x`` and ``y`` are two parts of one whole that overlap only
            partly (:mod:`torchfmap.matching.overlap`): the result is a
            :class:`~torchfmap.matching.overlap.PairMatchResult` with ``overlap`` ``(V_x,)`` and
            ``overlap_y`` ``(V_y,)``, the estimated overlap on each, and ``p2p_yx`` meant on
            ``overlap_y > 0.5``. Either way ``refine`` is ``'zoomout'`` or None; ``basis``,
            ``bases``, ``times``, ``p2p_mode``, ``zoomout_samples`` and the WKS settings do not
            apply.
        progress: a status line on stderr (tqdm) naming each step as it starts, with the time
            so far (dense meshes take minutes); the command line shows it unless ``--quiet``.

    Raises:
        ParameterError: inputs that are not meshes (e.g. paths: the fix names ``load_mesh``),
            unknown basis or refinement, a feature-aware basis without landmarks,
            an invalid ``k``, given bases that do not fit the meshes, or given eigenbases with
            fewer columns than ZoomOut's ``k_final``; :class:`~torchfmap.SeedError` for invalid
            landmarks; :class:`~torchfmap.MemoryEstimateError` (a ParameterError) for a ``k`` whose
            solve would not fit in the memory available (refused before any work).
    """
    with Steps("match", progress) as steps:  # a status line naming each step (progress=True)
        t0 = time.perf_counter()
        check_meshes(mesh_x, mesh_y)
        partial = check_partial(partial)
        if not partial:
            warn_if_partial(mesh_x, mesh_y)
        refine = check_refine(refine)
        if times is not None:  # every kind that reads them would refuse them; refused before any work
            relative_times(times, 1)
        pairs = None
        if landmarks is not None and len(np.atleast_1d(landmarks)):
            pairs = check_landmark_pairs(landmarks, mesh_x.n_vertices, mesh_y.n_vertices)
        if partial:
            given = {"basis": basis, "bases": bases, "times": times, "p2p_mode": p2p_mode,
                     "zoomout_samples": zoomout_samples}  # fmt: skip
            unused = [name for name, value in given.items() if value is not None]
            unused += ["refine='icp'"] if refine == "icp" else []
            unused += ["n_descriptors / k_descriptors"] if (n_descriptors, k_descriptors) != (20, 100) else []
            if unused:
                raise ParameterError(
                    f"partial={partial!r} solves in the eigenbases with SHOT descriptors and refines by "
                    f"ZoomOut, so {', '.join(unused)} would not be used. Fix: drop it, or match without "
                    f"partial={partial!r}."
                )
            n_max = min(mesh_x.n_vertices, mesh_y.n_vertices) - 1
            k = check_count(k, 1, n_max, "k (basis size)")
            if refine:
                check_k_final(k, k_final)
            k_final = check_count(k_final or 2 * k, k, n_max, "k_final") if refine else None
            check_solve_memory(k, k)
            steps("operators and eigenpairs")
            shape_x, shape_y = prepare_shapes(mesh_x, mesh_y, shapes, k_final or k)
            prep = time.perf_counter() - t0
            weights = {"w_lap": w_lap, "w_orient": w_orient, "w_dcomm": w_dcomm, "w_lmk": w_lmk}
            steps("partial functional map" + (" and ZoomOut" if refine else ""))
            solver = match_partial_pair if partial == "both" else match_partial
            result = solver(
                shape_x, shape_y, landmarks=pairs, k=k, refine=refine, k_final=k_final,
                **{name: w for name, w in weights.items() if w is not None},
            )  # fmt: skip
            result.timings["operators+eigen"] += prep
            warn_collapsed(result.p2p_yx, mesh_x.n_vertices)
            return result
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
                zoomout_samples=zoomout_samples, shapes=shapes, steps=steps, **solve,
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
        check_zoomout_sizes(kind, refine, k, k_final)
        check_solve_memory(k, k)
        grow = refine == "zoomout" and kind.grows
        eigenbases = (given_x, given_y) if given_eigen else None
        if given_eigen:  # refused before any work
            check_eigenbases(eigenbases, k_final or 2 * k)
        grow_shapes = (k_final or 2 * k) if grow and eigenbases is None else 0  # ZoomOut's eigenpairs
        steps("operators")
        shape_x, shape_y = prepare_shapes(mesh_x, mesh_y, shapes, 0)
        if pairs is not None:
            steps("landmark reading check")
            warn_if_off_by_one(shape_x, shape_y, pairs)
        prep = time.perf_counter() - t0
        given = None if bases is None else (given_x.truncated(k), given_y.truncated(k))
        seeds = np.asarray(given_x.pair_landmarks) if together else None
        result = solve_pair(
            shape_x, shape_y, kind, k, landmarks=pairs, bases=given, seeds=seeds, times=times,
            n_eigen=grow_shapes, steps=steps, **solve,
        )  # fmt: skip
        result.timings["operators+eigen"] += prep
        if refine is not None:

            def make_refiner(fold_pairs, bar=False):
                n_fixed = 0 if fold_pairs is None else len(fold_pairs)
                return kind.refiner(
                    refine, k_final=k_final, mode=p2p_mode, n_fixed=n_fixed, times=times,
                    zoomout_samples=zoomout_samples, eigenbases=eigenbases, landmarks=fold_pairs,
                    progress=bar,
                )  # fmt: skip

            # given bases are not re-solved per fold: their refinement is judged by the distortion
            result = refine_guarded(
                result, kind, shape_x, shape_y, pairs, k, make_refiner, cross_validate=bases is None,
                times=times, steps=steps, **solve,
            )  # fmt: skip
        warn_collapsed(result.p2p_yx, mesh_x.n_vertices)
        return result
