"""The classical matching pipeline :func:`match`: bases -> descriptors -> functional map -> point map ->
refinement, for one kind, the landmark default or partial shapes."""

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
    """``partial``: False, True (``y`` a part of ``x``) or ``'both'`` (two overlapping parts).

    Raises:
        ParameterError: anything else."""
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
    """Match ``y`` to ``x``: a :class:`MatchResult` with ``p2p_yx`` ``(V_y,)`` and ``C_xy``.

    The steps: :func:`prepare_shape` -> :func:`match_bases` -> :func:`match_descriptors` ->
    :func:`~torchfmap.fmap.solve_fmap` -> :func:`~torchfmap.fmap.fmap_to_p2p` (together :func:`solve_pair`) ->
    the kind's refiner, dropped if it raises the geodesic distortion (:func:`refine_result`). Default basis:
    the Laplacian eigenbasis without landmarks, ``'auto'`` with them (:func:`match_landmark_default`: the
    least distorted map among :data:`AUTO_KINDS`).

    Args:
        landmarks: ``(L, 2)`` pairs ``(vertex on x, vertex on y)``; required by feature-aware bases.
        basis: a kind of :data:`torchfmap.kinds.KINDS`, or ``'auto'``.
        k: basis size (columns of every basis).
        refine: ``'icp'``, ``'zoomout'`` (the kind's; eigenbases grow to ``k_final``, default ``2k``) or None.
        n_descriptors, k_descriptors: see :func:`match_descriptors`.
        w_lap, w_orient, w_dcomm, w_lmk: weights of :func:`~torchfmap.fmap.solve_fmap` (defaults: the kind's,
            :data:`~torchfmap.fmap.defaults.W_DCOMM`, ``W_LMK``).
        w_prior: pull of feature-aware maps to ``C = I`` (default :data:`~torchfmap.fmap.defaults.W_PRIOR`).
        times: relative diffusion times of feature-aware bases (default :func:`~torchfmap.kinds.seed_time`).
        p2p_mode: conversion of :func:`~torchfmap.fmap.fmap_to_p2p` (default: the kind's).
        zoomout_samples: eigenbasis ZoomOut on ~this many samples a shape (None: past ``LOCAL_SEARCH_PAIRS``).
        bases: B-orthonormal ``(basis_x, basis_y)`` to solve in (columns not assumed to correspond; ``k``
            ignored but for eigenbasis ZoomOut), of kind ``basis`` (default ``'laplacian'`` or ``'stack'``).
        shapes: ``(prepare_shape(mesh_x, ...), prepare_shape(mesh_y, ...))`` to reuse across pairs; same maps.
        partial: True: ``y`` a part of ``x`` in the same units (:mod:`torchfmap.matching.partial`, sets
            ``overlap`` ``(V_x,)``); ``'both'``: two partly overlapping parts (a
            :class:`~torchfmap.matching.overlap.PairMatchResult`). Then ``refine`` is ``'zoomout'`` or None,
            and ``basis``, ``bases``, ``times``, ``p2p_mode``, ``zoomout_samples``, WKS settings are refused.
        progress: a status line on stderr naming each step.

    Raises:
        ParameterError: inputs that are not meshes, unknown basis or refinement, a feature-aware basis without
            landmarks, an invalid ``k``, given bases that do not fit the meshes or ``k_final``;
            :class:`~torchfmap.SeedError` for invalid landmarks; :class:`~torchfmap.MemoryEstimateError` for a
            ``k`` whose solve would not fit in memory."""
    with Steps("match", progress) as steps:
        t0 = time.perf_counter()
        check_meshes(mesh_x, mesh_y)
        partial = check_partial(partial)
        if not partial:
            warn_if_partial(mesh_x, mesh_y)
        refine = check_refine(refine)
        if times is not None:  # refused before any work
            relative_times(times, 1)
        pairs = None
        if landmarks is not None and len(np.atleast_1d(landmarks)):
            pairs = check_landmark_pairs(landmarks, mesh_x.n_vertices, mesh_y.n_vertices)
        n_max = min(mesh_x.n_vertices, mesh_y.n_vertices) - 1
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
        given_eigen = bases is not None and refine == "zoomout" and kind.grows and not kind.needs_landmarks
        if bases is not None and refine == "zoomout" and not given_eigen and not together:
            raise ParameterError(
                "ZoomOut grows nested bases: given bases only support it as eigenbases. Fix: "
                "refine='icp', or basis='laplacian' with eigenbasis files."
            )
        if bases is not None and not given_eigen:
            k = min(given_x.k, given_y.k)
        k = check_count(k, 1, n_max, "k (basis size)")
        check_count(k_descriptors, 2, 10**9, "k_descriptors")
        check_unused(kind, refine, k_final, times)
        check_zoomout_sizes(kind, refine, k, k_final)
        check_solve_memory(k, k)
        eigenbases = (given_x, given_y) if given_eigen else None
        if given_eigen:  # refused before any work
            check_eigenbases(eigenbases, k_final or 2 * k)
        grow_shapes = (k_final or 2 * k) if refine == "zoomout" and kind.grows and eigenbases is None else 0
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
