"""The classical matching pipeline: bases -> descriptors -> functional map -> point map -> refinement.

Feature-aware bases (``harmonic``, ``diffusion``, ``stack``) are built on *both* shapes from
the same, corresponding landmarks (the seeds), so the same column means the same function on
both shapes; they therefore need landmarks. The Laplacian eigenbasis needs none.
"""

from __future__ import annotations

import multiprocessing
import os
import time
import warnings
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np
from tqdm import tqdm

from ._checks import check_count, check_seeds_cover_components, check_vertex_indices
from ._threads import thread_limit
from .bases import (
    Basis,
    Column,
    basis_stack,
    heat_kernels,
    laplacian_eigenbasis,
    orthonormalize_pair,
)
from .descriptors import landmark_descriptors, normalize_descriptors, wks
from .errors import ParameterError
from .eval import evaluate_map, landmarks_from_gt, shape_distance
from .fmap import check_landmark_pairs, fmap_to_p2p, icp_refine, solve_fmap, zoomout, zoomout_sequence
from .fmap.defaults import W_LAP, W_LMK, W_ORIENT
from .io import load_mesh
from .mesh import Mesh
from .operators.geodesic import DistanceRows
from .operators.laplacian import Operators, laplacian
from .seeds import corresponding_seeds, farthest_point_sampling

BasisKind = Literal["laplacian", "harmonic", "diffusion", "stack"]
RefineKind = Literal["icp", "zoomout"]
P2PMode = Literal["pullback", "orthogonal"]
BASIS_KINDS = ("laplacian", "harmonic", "diffusion", "stack")
#: Fixed-size refinement steps (point map <-> functional map) for feature-aware bases.
FEATURE_REFINE_STEPS = 5
#: Relative accuracy of the heat kernels of seed bases: far below the seeds' placement error
#: (a few percent of sqrt(area)), so a tighter tolerance changes no map, only the time.
SEED_HEAT_TOL = 1e-4
#: :func:`warn_if_off_by_one` warns when the shifted landmarks distort distances this much less.
OFF_BY_ONE_RATIO = 0.25
#: Rounds of seed re-placement after the fixed-size refinement (:func:`replace_seeds`).
FEATURE_SEED_MOVES = 2
#: Farthest-point samples per basis column for the iterations of feature-aware refinement (the
#: least-squares map of ``K`` columns is fitted on ``25 K`` sample rows; only the last point map
#: of each round uses every vertex). Measured equal in accuracy to every-vertex iterations
#: (``bench/feature_accuracy.py``), and the cost of an iteration no longer grows with ``V²``.
FEATURE_SAMPLES_PER_COLUMN = 25
#: Weight of the proximity-to-identity prior for feature-aware bases built at corresponding
#: seeds (relative to the descriptor term; ``inf``: ``C = I`` exactly, no descriptors needed).
W_PRIOR = float("inf")


def seed_time(n_seeds: int) -> float:
    """Relative heat time whose kernel width matches the covering radius of ``n_seeds`` seeds.

    ``n`` seeds cover a surface of unit area with radius about ``sqrt(1 / n)``; the kernel
    ``exp(-d² / 4t)`` falls to ``1/e`` at ``d = sqrt(4t)``, so ``t = 1 / (4 n)``: each point is
    then told apart by the few kernels around it, without gaps between seeds.
    """
    return 1.0 / (4.0 * n_seeds)


@dataclass
class MatchResult:
    """Output of :func:`match`: ``p2p_yx (V_y,)``, ``C_xy (K_y, K_x)``, the bases and timings;
    ``seeds`` ``(S, 2)`` are the corresponding seed pairs of feature-aware bases (else None)."""

    p2p_yx: np.ndarray
    C_xy: np.ndarray
    basis_x: Basis
    basis_y: Basis
    p2p_yx_initial: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    seeds: np.ndarray | None = None


@dataclass
class PreparedShape:
    """Per-shape precomputation shared by every pair a shape takes part in.

    ``mesh``; ``operators`` ``(L, B)`` (``(V, V)`` sparse stiffness and lumped mass);
    ``eigenbasis``: the first ``n_eigen`` Laplacian eigenfunctions as a B-orthonormal
    :class:`~torchfmap.Basis` (``(V, n_eigen)`` values, eigenvalues ascending; None when
    ``n_eigen = 0``); ``distances``: geodesic distance rows, computed on first use;
    ``kernels``: heat kernels of seed bases, ``(seed, relative time) -> (V,)``, computed on
    first use (a seed that refinement leaves in place is not solved again).
    """

    mesh: Mesh
    operators: Operators
    eigenbasis: Basis | None
    distances: DistanceRows
    kernels: dict[tuple[int, float], np.ndarray] = field(default_factory=dict)


def prepare_shape(mesh: Mesh, n_eigen: int) -> PreparedShape:
    """Operators and ``n_eigen`` eigenpairs of ``mesh`` (the work :func:`match` does per shape)."""
    ops = laplacian(mesh)
    eig = laplacian_eigenbasis(mesh, n_eigen, operators=ops) if n_eigen else None
    return PreparedShape(mesh, ops, eig, DistanceRows(mesh, normalized=True))


def landmark_distortion(shape_x: PreparedShape, shape_y: PreparedShape, landmarks: np.ndarray) -> float:
    """Mean ``|d_x(a_i, a_j) - d_y(b_i, b_j)|`` over landmark pairs ``(a_i, b_i)``, in units of
    ``sqrt(area)``: small for corresponding landmarks on near-isometric shapes, large for
    landmarks that do not correspond (e.g. read with the wrong index base)."""
    dx = shape_x.distances.rows(landmarks[:, 0])[:, landmarks[:, 0]]
    dy = shape_y.distances.rows(landmarks[:, 1])[:, landmarks[:, 1]]
    return float(np.mean(np.abs(dx - dy)))


def warn_if_off_by_one(shape_x: PreparedShape, shape_y: PreparedShape, landmarks: np.ndarray) -> None:
    """Warn (``UserWarning``) when the landmarks shifted by -1 fit the shapes far better than as
    given: the file was probably 1-based. Needs at least 3 landmarks; costs 2 geodesic solves
    per landmark, reused by the feature-aware bases."""
    if len(landmarks) < 3 or landmarks.min() < 1:
        return
    shifted = landmarks - 1
    if len(np.unique(shifted[:, 0])) < len(shifted) or len(np.unique(shifted[:, 1])) < len(shifted):
        return
    given = landmark_distortion(shape_x, shape_y, landmarks)
    other = landmark_distortion(shape_x, shape_y, shifted)
    if other < OFF_BY_ONE_RATIO * given:
        warnings.warn(
            f"the landmarks fit the shapes {given / max(other, 1e-12):.0f}x better shifted by -1 (mean "
            f"distance distortion {other:.3f} vs {given:.3f} sqrt(area)): were they read 1-based? "
            "Fix: landmarks are 0-based vertex indices; subtract 1 if the file is 1-based.",
            UserWarning,
            stacklevel=3,
        )


def match_descriptors(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    landmarks: np.ndarray | None = None,
    *,
    n_descriptors: int = 20,
    k_descriptors: int = 100,
) -> tuple[np.ndarray, np.ndarray]:
    """``(V_x, D)``, ``(V_y, D)`` descriptors of :func:`match`, normalised (unit B-norm columns).

    ``n_descriptors`` WKS columns (evenly subsampled from 100 energies computed on the first
    ``k_descriptors`` eigenpairs of each prepared shape), then, with ``landmarks`` ``(L, 2)``,
    two heat kernels per landmark (:func:`~torchfmap.descriptors.landmark_descriptors`).
    """
    if n_descriptors < 1:
        raise ParameterError(f"n_descriptors must be >= 1, got {n_descriptors}.")
    out = []
    for s, shape in enumerate((shape_x, shape_y)):
        if shape.eigenbasis is None:
            raise ParameterError("WKS descriptors need eigenpairs. Fix: prepare_shape(mesh, n_eigen > 0).")
        eig = shape.eigenbasis.truncated(min(k_descriptors, shape.eigenbasis.k))
        step = max(1, 100 // n_descriptors)
        parts = [wks(eig.eigenvalues, eig.values, 100)[:, ::step][:, :n_descriptors]]
        if landmarks is not None:
            parts.append(landmark_descriptors(landmarks[:, s], operators=shape.operators, times=(1e-2, 3e-2)))
        out.append(normalize_descriptors(np.hstack(parts), shape.operators[1]))
    return out[0], out[1]


def _columns_per_seed(kind: str, times) -> int:
    n_times = len(times) if times is not None else 1
    return {"harmonic": 1, "diffusion": n_times, "stack": n_times + 1}[kind]


def match_bases(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    kind: BasisKind,
    k: int,
    landmarks: np.ndarray | None = None,
    times=None,
) -> tuple[Basis, Basis, np.ndarray | None]:
    """The pair of B-orthonormal bases :func:`match` solves in, with exactly ``k`` columns each,
    and the corresponding seed pairs ``(S, 2)`` they are built at (None for the eigenbasis).

    ``'laplacian'``: the first ``k`` eigenfunctions of each prepared shape. Feature-aware kinds
    are built at ``S`` corresponding seeds (the landmarks, then farthest-point seeds placed on
    ``y`` by :func:`~torchfmap.seeds.corresponding_seeds`), so column ``i`` is the same
    function (same seed, same scale) on both shapes: ``'diffusion'`` heat kernels at each
    relative time in ``times`` (default: one time, :func:`seed_time` of ``S``), ``'harmonic'``
    harmonic functions, ``'stack'`` both. ``S = ceil(k / columns per seed)``; the two raw bases
    are orthonormalised together (:func:`~torchfmap.orthonormalize_pair`, landmark columns
    first) and cut to ``k``; if dependent columns were dropped, seeds are added until ``k``
    columns remain (bounded by the vertex count).

    Raises:
        ParameterError: a feature-aware kind without landmarks, or ``k`` outside its range.
    """
    if kind == "laplacian":
        if shape_x.eigenbasis is None or shape_y.eigenbasis is None:
            raise ParameterError("the eigenbasis needs eigenpairs. Fix: prepare_shape(mesh, n_eigen >= k).")
        return shape_x.eigenbasis.truncated(k), shape_y.eigenbasis.truncated(k), None
    if landmarks is None:
        raise ParameterError(
            f"the {kind} basis is built from corresponding landmarks on both shapes. Fix: pass "
            "landmarks (pairs of vertices), or use basis='laplacian'."
        )
    top = min(shape_x.mesh.n_vertices, shape_y.mesh.n_vertices)
    per_seed = _columns_per_seed(kind, times)
    n_seeds = max(len(landmarks), -(-k // per_seed))
    for _ in range(8):  # bounded: each pass adds seeds for the missing columns
        seeds = corresponding_seeds(
            shape_x.mesh,
            shape_y.mesh,
            landmarks,
            min(n_seeds, top),
            distances=(shape_x.distances, shape_y.distances),
        )
        bx, by = seed_bases(shape_x, shape_y, kind, seeds, times)
        if bx.k >= k or n_seeds >= top:
            break
        n_seeds += -(-(k - bx.k) // per_seed)
    if bx.k < k:
        raise ParameterError(
            f"only {bx.k} independent {kind} columns could be built (k={k}). Fix: lower k or use more seeds."
        )
    return bx.truncated(k), by.truncated(k), seeds


def seed_bases(
    shape_x: PreparedShape, shape_y: PreparedShape, kind: BasisKind, seeds: np.ndarray, times=None
) -> tuple[Basis, Basis]:
    """Corresponding feature-aware bases at seed pairs ``(S, 2)``, orthonormalised together
    (every column; :func:`match_bases` cuts them to ``k``). ``times``: relative diffusion times
    (default: one, :func:`seed_time` of ``S``)."""
    raw_x = _raw_seed_basis(shape_x, kind, seeds[:, 0], times)
    return orthonormalize_pair(raw_x, _raw_seed_basis(shape_y, kind, seeds[:, 1], times))


def _raw_seed_basis(shape: PreparedShape, kind: str, seeds: np.ndarray, times) -> Basis:
    """One shape's feature-aware functions at ``seeds`` (not orthonormalised).

    Heat kernels are independent per seed, so the ``'diffusion'`` kind solves only the
    ``(seed, time)`` pairs missing from ``shape.kernels`` and stores them there; harmonic
    functions depend on the whole seed set and are always rebuilt.
    """
    rel_times = tuple(float(t) for t in times) if times is not None else (seed_time(len(seeds)),)
    if kind != "diffusion":
        return basis_stack(
            shape.mesh,
            seeds,
            times=rel_times if kind != "harmonic" else (),
            harmonic=True,
            operators=shape.operators,
            heat_tol=SEED_HEAT_TOL,
            local=False,
            orthonormalization=None,
        )
    mesh = shape.mesh
    seeds = check_vertex_indices(seeds, mesh.n_vertices, "seeds")
    check_seeds_cover_components(mesh, seeds)
    rel_times = tuple(sorted(rel_times))
    for t in rel_times:
        missing = np.unique([int(s) for s in seeds if (int(s), t) not in shape.kernels])
        if len(missing):  # heat_kernels checks the time
            K = heat_kernels(shape.operators, missing, [t * mesh.area], tol=SEED_HEAT_TOL, local=False)[0]
            shape.kernels.update({(int(s), t): K[:, j] for j, s in enumerate(missing)})
    values = np.stack([shape.kernels[int(s), t] for t in rel_times for s in seeds], axis=1)
    prov = [Column("diffusion", int(s), t) for t in rel_times for s in seeds]  # time-major
    mass, stiffness = shape.operators[1], shape.operators[0]
    return Basis(values, mass, prov, stiffness=stiffness)


def replace_seeds(
    shape_x: PreparedShape, shape_y: PreparedShape, seeds: np.ndarray, p2p_yx: np.ndarray, n_fixed: int
) -> np.ndarray:
    """Seed pairs with their ``y`` side moved to where the current map sends them, within reason.

    Each seed ``s`` after the first ``n_fixed`` (the landmarks) goes to the ``y`` vertex whose
    image under ``p2p_yx`` is geodesically nearest to ``s``, but only if that moves it less
    than the seeds' covering radius ``sqrt(1 / S)`` (in units of ``sqrt(area)``) and keeps the
    seeds distinct; otherwise it stays. The map, refined in the seeds' own basis, corrects the
    small placement errors of trilateration; the radius keeps one wrong region of the map from
    dragging seeds across the shape.
    """
    radius = np.sqrt(1.0 / len(seeds))
    out = seeds.copy()
    used = {int(v) for v in seeds[:n_fixed, 1]}
    for i in range(n_fixed, len(seeds)):
        s, old = int(seeds[i, 0]), int(seeds[i, 1])
        order = np.argsort(shape_x.distances(s)[p2p_yx], kind="stable")
        new = next(int(v) for v in order if int(v) not in used)
        if shape_y.distances(old)[new] >= radius and old not in used:
            new = old
        out[i, 1] = new
        used.add(new)
    return out


class Refined(NamedTuple):
    """Result of :func:`refine_map`: the map, the bases it lives in and their seeds (or None)."""

    C_xy: np.ndarray
    p2p_yx: np.ndarray
    basis_x: Basis
    basis_y: Basis
    seeds: np.ndarray | None


def refine_map(
    C_xy: np.ndarray,
    p2p_yx: np.ndarray,
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    basis_x: Basis,
    basis_y: Basis,
    method: RefineKind,
    *,
    kind: BasisKind,
    k_final: int,
    mode: P2PMode,
    seeds: np.ndarray | None = None,
    n_fixed: int = 0,
    times=None,
    zoomout_samples: int | None = None,
) -> Refined:
    """The map refined by ``'icp'`` or ``'zoomout'`` (the refinement step of :func:`match`).

    ICP works in ``basis_x, basis_y``. ZoomOut in the eigenbasis grows the prepared
    eigenbases up to ``k_final`` (on ``zoomout_samples`` farthest-point samples per shape if
    given). In feature-aware bases built at ``seeds`` (``(S, 2)``, the first ``n_fixed`` being
    landmarks), whose columns correspond one to one, it starts from the current map,
    alternates ``C`` and the point map :data:`FEATURE_REFINE_STEPS` times at full size (on
    :data:`FEATURE_SAMPLES_PER_COLUMN` ``x K`` farthest-point samples per shape, the last point
    map on every vertex), then :data:`FEATURE_SEED_MOVES` times moves the seeds to where the map
    puts them (:func:`replace_seeds`), rebuilds the bases (:func:`seed_bases`), restarts from
    ``C = I`` in them and alternates again.
    """
    if method == "icp":
        return Refined(*icp_refine(C_xy, basis_x, basis_y, mode=mode), basis_x, basis_y, seeds)
    if method != "zoomout":
        raise ParameterError(f"unknown refinement {method!r}. Fix: 'icp', 'zoomout' or None.")
    if kind == "laplacian":
        full_x, full_y = shape_x.eigenbasis, shape_y.eigenbasis
        samples = None
        if zoomout_samples is not None:
            samples = tuple(
                farthest_point_sampling(m, min(zoomout_samples, m.n_vertices), metric="euclidean")
                for m in (shape_x.mesh, shape_y.mesh)
            )
        k = min(C_xy.shape)
        C, p2p = zoomout(C_xy, full_x, full_y, k_final, step=max(1, k // 10), mode=mode, subsample=samples)
        return Refined(C, p2p, full_x.truncated(k_final), full_y.truncated(k_final), None)
    steps = FEATURE_REFINE_STEPS
    bx, by = basis_x, basis_y
    n_samples = min(FEATURE_SAMPLES_PER_COLUMN * bx.k, shape_x.mesh.n_vertices, shape_y.mesh.n_vertices)
    samples = tuple(
        farthest_point_sampling(s.mesh, n_samples, metric="euclidean") for s in (shape_x, shape_y)
    )
    C, p2p = zoomout_sequence(p2p_yx, [bx] * steps, [by] * steps, mode=mode, subsample=samples)
    if seeds is None:
        return Refined(C, p2p, bx, by, None)
    raw_x = _raw_seed_basis(shape_x, kind, seeds[:, 0], times)  # x's seeds never move (cached)
    for _ in range(FEATURE_SEED_MOVES):
        seeds = replace_seeds(shape_x, shape_y, seeds, p2p, n_fixed)
        raw_y = _raw_seed_basis(shape_y, kind, seeds[:, 1], times)
        bx, by = (b.truncated(basis_x.k) for b in orthonormalize_pair(raw_x, raw_y))
        p2p = fmap_to_p2p(np.eye(by.k, bx.k), bx, by, mode=mode)
        C, p2p = zoomout_sequence(p2p, [bx] * steps, [by] * steps, mode=mode, subsample=samples)
    return Refined(C, p2p, bx, by, seeds)


def match(
    mesh_x: Mesh,
    mesh_y: Mesh,
    *,
    landmarks=None,
    basis: BasisKind | None = None,
    k: int = 50,
    refine: RefineKind | None = None,
    k_final: int | None = None,
    n_descriptors: int = 20,
    k_descriptors: int = 100,
    w_lap: float | None = None,
    w_orient: float = W_ORIENT,
    w_dcomm: float = 0.0,
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
    :func:`~torchfmap.fmap.solve_fmap` -> :func:`~torchfmap.fmap.fmap_to_p2p` ->
    :func:`refine_map`.

    With landmarks the default is the feature-aware ``'diffusion'`` basis: ``k`` heat kernels
    at corresponding seeds (see :func:`match_bases`), whose map is close to the identity; the
    solve is then pulled to ``C = I`` with weight ``w_prior`` (default :data:`W_PRIOR`; at
    ``inf`` the identity is the map and no descriptors are computed).

    Args:
        mesh_x, mesh_y: source and target.
        landmarks: ``(L, 2)`` corresponding pairs ``(vertex on x, vertex on y)``; required by
            the feature-aware bases, used as descriptors and constraints by the eigenbasis.
        basis: ``'laplacian'``, ``'harmonic'``, ``'diffusion'`` or ``'stack'`` (default:
            ``'diffusion'`` with landmarks, ``'laplacian'`` without).
        k: basis size; every basis has exactly ``k`` columns.
        refine: ``'icp'`` or ``'zoomout'`` (eigenbasis: up to ``k_final``, default ``2k``;
            feature-aware: fixed-size iterations from the current map), or None.
        n_descriptors, k_descriptors: see :func:`match_descriptors`.
        w_lap, w_orient, w_dcomm, w_lmk: weights of Laplacian commutativity (default
            :data:`W_LAP` of the basis), orientation preservation (tells left from right,
            which WKS alone cannot), descriptor commutativity and pointwise landmark
            preservation (see :func:`~torchfmap.fmap.solve_fmap`). With the last three at 0
            the solve is the exact row-wise one; otherwise preconditioned CG.
        w_prior: proximity-to-identity weight for feature-aware bases (see above).
        times: relative diffusion times of feature-aware bases (default: :func:`seed_time`).
        p2p_mode: functional map -> point map conversion (:func:`~torchfmap.fmap.fmap_to_p2p`);
            default ``'orthogonal'`` for the eigenbasis, ``'pullback'`` for feature-aware bases.
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
    kind = basis or ("diffusion" if pairs is not None else "laplacian")
    if bases is not None:
        given_x, given_y = _check_given_bases(bases, mesh_x, mesh_y)
        eigen_only = all(c.kind == "laplacian" for b in (given_x, given_y) for c in b.columns if c.kept)
        kind = basis or ("laplacian" if eigen_only else "stack")
        k = min(given_x.k, given_y.k)
        if refine == "zoomout" and kind != "laplacian":
            raise ParameterError(
                "ZoomOut grows nested bases: given bases only support it as eigenbases. Fix: "
                "refine='icp', or basis='laplacian' with eigenbasis files."
            )
    if kind not in BASIS_KINDS:
        raise ParameterError(f"unknown basis {kind!r}. Fix: one of {BASIS_KINDS}.")
    n_max = min(mesh_x.n_vertices, mesh_y.n_vertices) - 1
    k = check_count(k, 1, n_max, "k (basis size)")
    k_descriptors = min(check_count(k_descriptors, 2, 10**9, "k_descriptors"), n_max)  # small meshes
    grow = refine == "zoomout" and kind == "laplacian"
    k_final = k_final if k_final is not None else (2 * k if grow else k)
    if grow and k_final < k:
        raise ParameterError(f"k_final={k_final} is below k={k}: ZoomOut grows the basis. Fix: k_final >= k.")
    prior = kind != "laplacian" and bases is None  # given bases: columns need not correspond
    w_prior = (W_PRIOR if w_prior is None else w_prior) if prior else 0.0
    need_desc = not (prior and np.isinf(w_prior))
    n_eigen = max(k_descriptors, k, k_final) if kind == "laplacian" else (k_descriptors if need_desc else 0)
    if shapes is None:
        shape_x, shape_y = prepare_shape(mesh_x, n_eigen), prepare_shape(mesh_y, n_eigen)
    else:
        shape_x, shape_y = (
            _with_eigenpairs(s, m, n_eigen) for s, m in zip(shapes, (mesh_x, mesh_y), strict=True)
        )
    if pairs is not None:
        warn_if_off_by_one(shape_x, shape_y, pairs)
    timings["operators+eigen"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if bases is None:
        bx, by, seeds = match_bases(shape_x, shape_y, kind, k, pairs, times)
    else:
        bx, by, seeds = given_x.truncated(k), given_y.truncated(k), None
    timings["basis"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if need_desc:
        desc_x, desc_y = match_descriptors(
            shape_x, shape_y, pairs, n_descriptors=n_descriptors, k_descriptors=k_descriptors
        )
    timings["descriptors"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if need_desc:
        C = solve_fmap(
            bx,
            by,
            desc_x,
            desc_y,
            w_lap=W_LAP[kind] if w_lap is None else w_lap,
            w_orient=w_orient,
            w_dcomm=w_dcomm,
            meshes=(mesh_x, mesh_y),
            landmarks=pairs,
            w_lmk=w_lmk if pairs is not None else 0.0,
            prior=np.eye(by.k, bx.k) if prior else None,
            w_prior=w_prior,
        )
    else:
        C = np.eye(by.k, bx.k)
    mode = p2p_mode or ("orthogonal" if kind == "laplacian" else "pullback")
    p2p = fmap_to_p2p(C, bx, by, mode=mode)
    timings["fmap+p2p"] = time.perf_counter() - t0
    initial = p2p

    t0 = time.perf_counter()
    if refine is not None:
        C, p2p, bx, by, seeds = refine_map(
            C,
            p2p,
            shape_x,
            shape_y,
            bx,
            by,
            refine,
            kind=kind,
            k_final=k_final,
            mode=mode,
            seeds=seeds,
            n_fixed=0 if pairs is None else len(pairs),
            times=times,
            zoomout_samples=zoomout_samples,
        )
    timings["refine"] = time.perf_counter() - t0
    return MatchResult(p2p, C, bx, by, initial, timings, seeds)


def _with_eigenpairs(shape: PreparedShape, mesh: Mesh, n_eigen: int) -> PreparedShape:
    """``shape`` (checked to be ``mesh``'s) with at least ``n_eigen`` eigenpairs."""
    if not isinstance(shape, PreparedShape) or shape.mesh is not mesh:
        raise ParameterError(
            "shapes must be (prepare_shape(mesh_x, n), prepare_shape(mesh_y, n)) of these meshes, in order."
        )
    if n_eigen and (shape.eigenbasis is None or shape.eigenbasis.k < n_eigen):
        shape.eigenbasis = laplacian_eigenbasis(mesh, n_eigen, operators=shape.operators)
    return shape


def _check_given_bases(bases, mesh_x: Mesh, mesh_y: Mesh) -> tuple[Basis, Basis]:
    try:
        bx, by = bases
    except (TypeError, ValueError) as err:
        raise ParameterError("bases must be a pair (basis_x, basis_y) of Basis objects.") from err
    for b, mesh, name in ((bx, mesh_x, "x"), (by, mesh_y, "y")):
        if not isinstance(b, Basis):
            raise ParameterError(f"basis_{name} is a {type(b).__name__}, not a Basis. Fix: Basis.load(path).")
        if b.n_vertices != mesh.n_vertices:
            raise ParameterError(
                f"basis_{name} has {b.n_vertices} vertices but mesh_{name} has {mesh.n_vertices}. Fix: "
                "pass the basis built on that mesh (bases in the order source, target)."
            )
    return bx, by


def shape_distance_matrix(
    meshes: list[Mesh], *, k: int = 20, kind: str = "area", progress: bool = False, **match_kwargs
) -> np.ndarray:
    """``(N, N)`` symmetric shape distances from the functional maps between all pairs.

    Each ordered pair is matched (:func:`match`, eigenbasis by default) and the map's
    shape difference is compared with the identity (:func:`~torchfmap.eval.shape_distance`);
    the two directions are averaged. Feed the result to
    :func:`~torchfmap.eval.retrieval_accuracy` with class labels.
    """
    n = len(meshes)
    D = np.zeros((n, n))
    pairs = [(i, j) for i in range(n) for j in range(n) if i != j]
    shapes = [prepare_shape(m, 0) for m in meshes]  # each shape's work done once, not per pair
    for i, j in tqdm(pairs, desc="shape pairs", disable=not progress):
        result = match(meshes[i], meshes[j], k=k, shapes=(shapes[i], shapes[j]), **match_kwargs)
        W_x, W_y = result.basis_x.projected_laplacian(), result.basis_y.projected_laplacian()
        D[i, j] = shape_distance(result.C_xy, W_x, W_y, kind=kind)
    return 0.5 * (D + D.T)


class PairResult(NamedTuple):
    """One evaluated pair of :func:`evaluate_pairs`: names, the report of
    :func:`~torchfmap.eval.evaluate_map`, its per-point errors and the match time (s)."""

    source: str
    target: str
    report: object
    errors: np.ndarray
    seconds: float


#: Distance rows :func:`evaluate_pairs` keeps for the current source mesh (bytes).
EVAL_ROWS_BYTES = 512 * 2**20
#: Cost of a source's scoring rows in units of one pair's match, for balancing a pool's chunks
#: (on 5K-vertex meshes, rows from every vertex cost several matches).
SOURCE_COST = 5.0

# The prepared shapes of a local pool's worker process, kept across the chunks it runs (so a
# worker prepares each mesh once); set by the pool's initializer in the worker, never in the
# calling process, and gone with the pool when evaluate_pairs returns.
_POOL_SHAPES: dict | None = None


def pool_threads(workers: int) -> int:
    """Threads per worker of a local pool when none are given: the CPUs shared out."""
    return max(1, (os.cpu_count() or 1) // workers)


def _init_pool_worker() -> None:
    global _POOL_SHAPES
    _POOL_SHAPES = {}


def _evaluate_chunk(
    pairs, gt_landmarks: int, max_points, match_kwargs: dict, shapes=None, on_pair=None, threads=None
) -> list[PairResult]:
    """Match and score ``pairs`` in order with ``threads`` threads (BLAS and torch:
    :func:`~torchfmap._threads.thread_limit`); each mesh is loaded and prepared once
    (``shapes``: path -> (mesh, PreparedShape), filled here); ``on_pair()`` is called after
    each pair."""
    if shapes is None:
        shapes = _POOL_SHAPES if _POOL_SHAPES is not None else {}
    with thread_limit(threads):
        out = []
        rows = None  # distance rows of the current source mesh, shared by its consecutive pairs
        for a, b, pa, pb, gt in pairs:
            for path in (pa, pb):
                if path not in shapes:
                    mesh = load_mesh(path)
                    shapes[path] = (mesh, prepare_shape(mesh, 0))
            (x, sx), (y, sy) = shapes[pa], shapes[pb]
            landmarks = landmarks_from_gt(x, gt, gt_landmarks) if gt_landmarks else None
            t0 = time.perf_counter()
            result = match(x, y, landmarks=landmarks, shapes=(sx, sy), **match_kwargs)
            seconds = time.perf_counter() - t0
            # errors are geodesic on x, from its ground-truth points: pairs with the same source
            # reuse its prefactored solver and the rows already solved (kept for one source at a time)
            if rows is None or rows.solver is not sx.distances.solver:
                rows = DistanceRows(x, sx.distances.solver, max_bytes=EVAL_ROWS_BYTES)
            report, errors = evaluate_map(x, y, result.p2p_yx, gt, max_points=max_points, solver=rows)
            out.append(PairResult(a, b, report, errors, seconds))
            if on_pair is not None:
                on_pair()
        return out


def _chunk_costs(pairs: list) -> np.ndarray:
    """Estimated cost of each pair in a run of ``pairs``: one match, plus :data:`SOURCE_COST`
    where the source mesh changes (its scoring rows are solved there)."""
    new_source = [i == 0 or pairs[i][2] != pairs[i - 1][2] for i in range(len(pairs))]
    return 1.0 + SOURCE_COST * np.asarray(new_source, dtype=float)


def _source_chunks(pairs: list, n_chunks: int) -> list[list]:
    """``pairs`` cut into at most ``n_chunks`` contiguous chunks of similar estimated cost
    (:func:`_chunk_costs`), cutting only where the source mesh changes (so a source's rows are
    solved in one chunk) when possible."""
    edges = [0] + [i for i in range(1, len(pairs)) if pairs[i][2] != pairs[i - 1][2]] + [len(pairs)]
    cumulative = np.concatenate([[0.0], np.cumsum(_chunk_costs(pairs))])
    target = np.linspace(0.0, cumulative[-1], n_chunks + 1)[1:-1]
    cuts = sorted({min(edges, key=lambda e, t=t: abs(cumulative[e] - t)) for t in target} - {0, len(pairs)})
    bounds = [0, *cuts, len(pairs)]
    return [pairs[lo:hi] for lo, hi in zip(bounds[:-1], bounds[1:], strict=True) if hi > lo]


def evaluate_pairs(
    pairs,
    *,
    gt_landmarks: int = 0,
    max_points: int | None = None,
    workers: int = 1,
    threads: int | None = None,
    executor: Executor | None = None,
    progress: bool = False,
    **match_kwargs,
) -> list[PairResult]:
    """Match and score every pair ``(name_x, name_y, path_x, path_y, gt)`` (as yielded by
    :func:`~torchfmap.eval.discover_pairs`), in the given order.

    Each mesh is loaded and prepared (:func:`prepare_shape`: operators, eigenpairs, geodesic
    rows, heat kernels) once per chunk of pairs and reused by every pair it takes part in. With
    ``workers > 1`` the pairs are split into contiguous chunks, cut where the source mesh
    changes when possible (its scoring rows are then solved once), run by a local process
    pool (spawned processes);
    ``executor`` runs them on any :class:`concurrent.futures.Executor` instead (e.g.
    ``dask.distributed.Client(...).get_executor()`` for a cluster).

    Every chunk runs with ``threads`` BLAS / OpenMP / torch threads. The thread count fixes
    the order of BLAS's and torch's parallel sums, and so the last bits of eigenvectors and
    maps (near-tied points may then match differently). For the same ``threads``, the results
    do not depend on ``workers`` or ``executor``: every map is computed from the same inputs
    by the same deterministic steps.

    Args:
        gt_landmarks: use this many ground-truth pairs per pair as landmarks
            (:func:`~torchfmap.eval.landmarks_from_gt`; 0: none).
        max_points: score at most this many points per pair.
        workers: local worker processes (1: this process).
        threads: threads per worker. ``None``: this process's threads as they are when
            ``workers == 1`` and no ``executor`` is given, else ``max(1, cpu_count // workers)``
            (:func:`pool_threads`; no oversubscription) or the executor's own setting. Pass it to
            compare runs with different ``workers`` bit for bit.
        match_kwargs: passed to :func:`match` (``basis``, ``k``, ``refine``, ...).

    Raises:
        ParameterError: ``workers < 1`` or ``threads < 1``.
    """
    pairs = list(pairs)
    workers = check_count(workers, 1, 4096, "workers")
    if threads is not None:
        threads = check_count(threads, 1, 4096, "threads")
    elif executor is None and workers > 1:
        threads = pool_threads(workers)
    bar = tqdm(total=len(pairs), desc="pairs", unit="pair", disable=not progress)
    if executor is None and workers == 1:
        try:
            return _evaluate_chunk(
                pairs, gt_landmarks, max_points, match_kwargs, on_pair=bar.update, threads=threads
            )
        finally:
            bar.close()
    own = executor is None
    # a few chunks per worker, balanced as they complete; a local pool's worker keeps the
    # meshes it prepared for its next chunks (an executor's chunks prepare them again)
    chunks = _source_chunks(pairs, min(len(pairs), 4 * workers))
    # spawned, not forked: a child forked after this process used torch's or BLAS's thread
    # pool waits forever on that pool's locks (torch.linalg.eigh hung this way)
    spawn = multiprocessing.get_context("spawn")
    pool = (
        ProcessPoolExecutor(max_workers=workers, mp_context=spawn, initializer=_init_pool_worker)
        if own
        else executor
    )
    # costliest chunks first (longest-processing-time order): the last ones to finish are short
    order = sorted(range(len(chunks)), key=lambda i: -float(_chunk_costs(chunks[i]).sum()))
    try:
        args = (gt_landmarks, max_points, match_kwargs)
        futures = {pool.submit(_evaluate_chunk, chunks[i], *args, threads=threads): i for i in order}
        done: dict[int, list[PairResult]] = {}
        for future in as_completed(futures):
            i = futures[future]
            done[i] = future.result()
            bar.update(len(chunks[i]))
    finally:
        bar.close()
        if own:
            pool.shutdown(cancel_futures=True)
    return [r for i in range(len(chunks)) for r in done[i]]
