"""The classical matching pipeline: bases -> descriptors -> functional map -> point map -> refinement.

:func:`match` is the recipe; each step is public for callers with their own bases or
descriptors. What a basis *kind* means (whether it needs landmarks, how its functions are
built, its solver weight, point-map rule and refinement) lives in the registry
:data:`torchfmap.bases.KINDS`; this module reads it and never compares kind names.
Evaluating whole collections is :mod:`torchfmap.collection`.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from tqdm import tqdm

from ._checks import check_count
from .bases import Basis
from .bases.kinds import BasisKind, get_kind
from .bases.prepared import PreparedShape, check_prepared, prepare_shape, with_eigenpairs
from .descriptors import WKS_ENERGIES, landmark_descriptors, normalize_descriptors, wks
from .errors import MapWarning, ParameterError
from .eval import shape_distance
from .fmap import check_landmark_pairs, solve_fmap
from .fmap.defaults import W_DCOMM, W_LMK, W_PRIOR
from .fmap.refine import map_to_p2p, refine_map
from .mesh import Mesh

RefineKind = Literal["icp", "zoomout"]
P2PMode = Literal["pullback", "orthogonal"]
#: :func:`warn_if_off_by_one` warns when the shifted landmarks distort distances this much less.
OFF_BY_ONE_RATIO = 0.25

__all__ = [
    "MatchResult",
    "PreparedShape",
    "landmark_distortion",
    "match",
    "match_bases",
    "match_descriptors",
    "prepare_shape",
    "refine_map",
    "shape_distance_matrix",
    "warn_if_off_by_one",
]


@dataclass
class MatchResult:
    """Output of :func:`match`: ``p2p_yx (V_y,)``, ``C_xy (K_y, K_x)``, the bases and timings;
    ``seeds`` ``(S, 2)`` are the corresponding seed pairs of feature-aware bases (else None);
    ``kind`` the name of the basis kind that ran. The bases are B-orthonormal in each mesh's
    unit-area frame (their ``mass`` is that of ``mesh.scaled(1 / sqrt(area))``), unless given."""

    p2p_yx: np.ndarray
    C_xy: np.ndarray
    basis_x: Basis
    basis_y: Basis
    p2p_yx_initial: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    seeds: np.ndarray | None = None
    kind: str = ""


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
    refine: RefineKind | None = None,
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
    :func:`~torchfmap.fmap.solve_fmap` -> :func:`~torchfmap.fmap.fmap_to_p2p` ->
    :func:`refine_map`.

    The default basis is the Laplacian eigenbasis, with or without landmarks (landmarks then
    enter as descriptors and constraints). The feature-aware ``basis='diffusion'`` builds ``k``
    heat kernels at corresponding seeds (see :func:`match_bases`), whose map is close to the
    identity; its solve is pulled to ``C = I`` with weight ``w_prior`` (default
    :data:`~torchfmap.fmap.defaults.W_PRIOR`; at ``inf`` the identity is the map and no
    descriptors are computed).

    Args:
        mesh_x, mesh_y: source and target.
        landmarks: ``(L, 2)`` corresponding pairs ``(vertex on x, vertex on y)``; required by
            the feature-aware bases, used as descriptors and constraints by the eigenbasis.
        basis: a kind of :data:`torchfmap.bases.KINDS` (``'laplacian'``, ``'diffusion'``,
            ``'harmonic'``, ``'stack'``, ``'hybrid'``, ``'eigen_diffusion'``; default
            ``'laplacian'``).
        k: basis size; every basis has exactly ``k`` columns.
        refine: ``'icp'`` or ``'zoomout'`` (as the kind's ``refinement`` says: the eigenbasis
            grows up to ``k_final``, default ``2k``; feature-aware kinds iterate at a fixed
            size from the current map, then move their seeds), or None.
        n_descriptors, k_descriptors: see :func:`match_descriptors`.
        w_lap, w_orient, w_dcomm, w_lmk: weights of Laplacian commutativity (default
            the kind's ``w_lap``), orientation preservation (tells left from right,
            which WKS alone cannot), descriptor commutativity and pointwise landmark
            preservation (see :func:`~torchfmap.fmap.solve_fmap`; defaults: the kind's
            ``w_orient``, :data:`~torchfmap.fmap.defaults.W_DCOMM`, ``W_LMK``). With the last
            three at 0 the solve is the exact row-wise one; otherwise preconditioned CG.
        w_prior: proximity-to-identity weight for feature-aware bases (see above).
        times: relative diffusion times of feature-aware bases (default: one time,
            :func:`~torchfmap.bases.kinds.seed_time` of the seed count).
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
    name = basis or "laplacian"
    if bases is not None:
        given_x, given_y = _check_given_bases(bases, mesh_x, mesh_y)
        eigen_only = all(c.kind == "laplacian" for b in (given_x, given_y) for c in b.columns if c.kept)
        name = basis or ("laplacian" if eigen_only else "stack")
        k = min(given_x.k, given_y.k)
    kind = get_kind(name)
    if bases is not None and refine == "zoomout" and kind.refinement != "grow":
        raise ParameterError(
            "ZoomOut grows nested bases: given bases only support it as eigenbases. Fix: "
            "refine='icp', or basis='laplacian' with eigenbasis files."
        )
    n_max = min(mesh_x.n_vertices, mesh_y.n_vertices) - 1
    k = check_count(k, 1, n_max, "k (basis size)")
    k_descriptors = min(check_count(k_descriptors, 2, 10**9, "k_descriptors"), n_max)  # small meshes
    grow = refine == "zoomout" and kind.refinement in ("grow", "hybrid")
    k_final = k_final if k_final is not None else (2 * k if grow else k)
    if grow and k_final < k:
        raise ParameterError(f"k_final={k_final} is below k={k}: ZoomOut grows the basis. Fix: k_final >= k.")
    prior = kind.needs_landmarks and bases is None  # given bases: columns need not correspond
    w_prior = (W_PRIOR if w_prior is None else w_prior) if prior else 0.0
    need_desc = kind.uses_descriptors(w_prior)
    n_eigen = max(kind.n_eigen(k), k_final if grow else 0, k_descriptors if need_desc else 0)
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
        bx, by, seeds = given_x.truncated(k), given_y.truncated(k), None
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
    p2p = map_to_p2p(C, bx, by, kind, mode)
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
    warn_collapsed(p2p, mesh_x.n_vertices)
    return MatchResult(p2p, C, bx, by, initial, timings, seeds, kind.name)


#: A point map reaching under this fraction of the vertices it could reach (``min(V_x, V_y)``)
#: has collapsed (e.g. an extreme regulariser weight): :func:`match` warns.
COLLAPSE_COVERAGE = 0.05


def warn_collapsed(p2p_yx: np.ndarray, n_x: int, stacklevel: int = 3) -> None:
    """Warn (:class:`~torchfmap.errors.MapWarning`) when ``p2p_yx`` reaches under
    :data:`COLLAPSE_COVERAGE` of the ``min(V_x, V_y)`` source vertices it could reach."""
    reachable = min(n_x, len(p2p_yx))
    reached = len(np.unique(p2p_yx))
    if reachable > 1 and reached < COLLAPSE_COVERAGE * reachable:
        warnings.warn(
            f"the point map sends {len(p2p_yx)} target vertices to only {reached} source vertices "
            f"({100 * reached / reachable:.1f} % of the {reachable} it could reach): it has collapsed. "
            "Fix: check the weights (w_lap, w_orient), the landmarks and the meshes' scale and "
            "orientation; refine='zoomout' often spreads a collapsed start.",
            MapWarning,
            stacklevel=stacklevel,
        )


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
    seeded = any(c.seed >= 0 for b in (bx, by) for c in b.provenance)
    px, py = bx.pair_landmarks, by.pair_landmarks
    together = px is not None and py is not None and np.array_equal(px, py)
    if seeded and not together:
        warnings.warn(
            "the given bases have seeded columns but were not built together from the same "
            "landmark pairs, so their columns need not correspond and the map can be wrong. Fix: "
            "build them as a pair (`torchfmap basis SRC TGT --landmarks pairs.txt --out a.npz b.npz`, "
            "or match_bases()), or match with landmarks=... directly.",
            MapWarning,
            stacklevel=3,
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
