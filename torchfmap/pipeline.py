"""The classical matching pipeline: bases -> descriptors -> functional map -> point map -> refinement.

Feature-aware bases (``harmonic``, ``diffusion``, ``stack``) are built on *both* shapes from
the same, corresponding landmarks (the seeds), so the same column means the same function on
both shapes; they therefore need landmarks. The Laplacian eigenbasis needs none.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from tqdm import tqdm

from .bases import (
    Basis,
    basis_stack,
    concatenate,
    diffusion_basis,
    harmonic_basis,
    laplacian_eigenbasis,
    orthonormalize,
    orthonormalize_pair,
)
from .descriptors import landmark_descriptors, normalize_descriptors, wks
from .errors import ParameterError
from .eval import shape_distance
from .fmap import check_landmark_pairs, fmap_to_p2p, icp_refine, solve_fmap, zoomout, zoomout_sequence
from .mesh import Mesh
from .operators.laplacian import Operators, laplacian
from .seeds import farthest_point_sampling

BasisKind = Literal["laplacian", "harmonic", "diffusion", "stack"]
RefineKind = Literal["icp", "zoomout"]
P2PMode = Literal["pullback", "orthogonal"]
BASIS_KINDS = ("laplacian", "harmonic", "diffusion", "stack")
#: Default Laplacian-commutativity weight per basis (the mask is normalised to mean 1), chosen
#: by ``python bench/weight_sweep.py`` (table in ``bench/results/weight_sweep.md``). Projected
#: Laplacians of small-t heat kernels have very large top eigenvalues, which dominate the
#: mask's mean, so diffusion bases need a larger weight than eigenbases.
W_LAP = {"laplacian": 0.1, "harmonic": 0.1, "diffusion": 1.0, "stack": 1.0}
#: Relative diffusion times of feature-aware bases, large (coarse) to small (fine).
MATCH_TIMES = (1e-1, 3e-2, 1e-2, 3e-3)


@dataclass
class MatchResult:
    """Output of :func:`match`: ``p2p_yx (V_y,)``, ``C_xy (K_y, K_x)``, the bases and timings."""

    p2p_yx: np.ndarray
    C_xy: np.ndarray
    basis_x: Basis
    basis_y: Basis
    p2p_yx_initial: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class PreparedShape:
    """Per-shape precomputation shared by every pair a shape takes part in.

    ``mesh``; ``operators`` ``(L, B)`` (``(V, V)`` sparse stiffness and lumped mass);
    ``eigenbasis``: the first ``n_eigen`` Laplacian eigenfunctions as a B-orthonormal
    :class:`~torchfmap.Basis` (``(V, n_eigen)`` values, eigenvalues ascending).
    """

    mesh: Mesh
    operators: Operators
    eigenbasis: Basis


def prepare_shape(mesh: Mesh, n_eigen: int) -> PreparedShape:
    """Operators and ``n_eigen`` eigenpairs of ``mesh`` (the work :func:`match` does per shape)."""
    ops = laplacian(mesh)
    return PreparedShape(mesh, ops, laplacian_eigenbasis(mesh, n_eigen, operators=ops))


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
        eig = shape.eigenbasis.truncated(min(k_descriptors, shape.eigenbasis.k))
        step = max(1, 100 // n_descriptors)
        parts = [wks(eig.eigenvalues, eig.values, 100)[:, ::step][:, :n_descriptors]]
        if landmarks is not None:
            parts.append(landmark_descriptors(landmarks[:, s], operators=shape.operators, times=(1e-2, 3e-2)))
        out.append(normalize_descriptors(np.hstack(parts), shape.operators[1]))
    return out[0], out[1]


def match_bases(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    kind: BasisKind,
    k: int,
    landmarks: np.ndarray | None = None,
    times=MATCH_TIMES,
) -> tuple[Basis, Basis]:
    """The pair of B-orthonormal bases :func:`match` solves in.

    ``'laplacian'``: the first ``k`` eigenfunctions of each prepared shape. Feature-aware kinds
    (``'harmonic'``, ``'diffusion'``, ``'stack'``) are built on both shapes from the same
    ``landmarks`` ``(L, 2)`` and orthonormalised together, so that column ``i`` is built from
    the same landmark and scale on both (raises :class:`ParameterError` without landmarks).
    """
    if kind == "laplacian":
        return shape_x.eigenbasis.truncated(k), shape_y.eigenbasis.truncated(k)
    if landmarks is None:
        raise ParameterError(
            f"the {kind} basis is built from corresponding landmarks on both shapes. Fix: pass "
            "landmarks (pairs of vertices), or use basis='laplacian'."
        )
    n_eigen = max(0, k - (len(times) + 1) * len(landmarks)) if kind == "stack" else 0
    raw = []
    for s, shape in enumerate((shape_x, shape_y)):
        mesh, ops, seeds = shape.mesh, shape.operators, landmarks[:, s]
        if kind == "harmonic":
            raw.append(harmonic_basis(mesh, seeds, operators=ops))
        elif kind == "diffusion":
            raw.append(diffusion_basis(mesh, seeds, times, operators=ops, tol=1e-6, local=False))
        else:
            raw.append(
                basis_stack(
                    mesh,
                    seeds,
                    times=times,
                    operators=ops,
                    heat_tol=1e-6,
                    local=False,
                    orthonormalization=None,
                )
            )
    bx, by = orthonormalize_pair(*raw)
    if n_eigen:  # eigenfunctions fill up to k; they do not correspond column by column
        bx = orthonormalize(concatenate([bx, shape_x.eigenbasis.truncated(n_eigen)]))
        by = orthonormalize(concatenate([by, shape_y.eigenbasis.truncated(n_eigen)]))
    return bx, by


def _coarse_to_fine(shape_x, shape_y, pairs: np.ndarray, kind: str, times) -> tuple[list[Basis], list[Basis]]:
    """Nested corresponding feature-aware bases for ZoomOut: growing scales (large to small t)."""
    shapes = (shape_x, shape_y)
    parts = [
        [
            diffusion_basis(sh.mesh, pairs[:, s], [t], operators=sh.operators, tol=1e-6, local=False)
            for t in times
        ]
        for s, sh in enumerate(shapes)
    ]
    if kind == "stack":
        for s, sh in enumerate(shapes):
            parts[s].append(harmonic_basis(sh.mesh, pairs[:, s], operators=sh.operators))
    seq_x, seq_y = [], []
    for j in range(len(parts[0])):
        bx, by = orthonormalize_pair(*(concatenate(p[: j + 1]) for p in parts))
        seq_x.append(bx)
        seq_y.append(by)
    if kind == "diffusion":  # the last level equals the matching basis
        seq_x, seq_y = seq_x[:-1], seq_y[:-1]
    return seq_x, seq_y


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
    landmarks: np.ndarray | None = None,
    times=MATCH_TIMES,
    zoomout_samples: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``(C_xy, p2p_yx)`` refined by ``'icp'`` or ``'zoomout'`` (the refinement step of :func:`match`).

    ICP works in ``basis_x, basis_y``. ZoomOut in the eigenbasis grows the prepared
    eigenbases up to ``k_final`` (on ``zoomout_samples`` farthest-point samples per shape if
    given); for feature-aware bases it runs over growing scales of corresponding kernels.
    """
    if method == "icp":
        return icp_refine(C_xy, basis_x, basis_y, mode=mode)
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
        return zoomout(C_xy, full_x, full_y, k_final, step=max(1, k // 10), mode=mode, subsample=samples)
    if kind == "harmonic":
        raise ParameterError(
            "ZoomOut needs nested bases that grow; a harmonic basis only grows with more "
            "corresponding seeds, and the landmarks are all there is. Fix: refine='icp', or "
            "basis='stack' / 'diffusion' (ZoomOut over growing scales)."
        )
    seq_x, seq_y = _coarse_to_fine(shape_x, shape_y, landmarks, kind, times)
    return zoomout_sequence(p2p_yx, seq_x + [basis_x], seq_y + [basis_y], mode=mode)


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
    w_orient: float = 1e-2,
    w_dcomm: float = 0.0,
    w_lmk: float = 1.0,
    times=MATCH_TIMES,
    p2p_mode: P2PMode | None = None,
    zoomout_samples: int | None = None,
) -> MatchResult:
    """Match ``y`` to ``x``: returns ``p2p_yx`` and ``C_xy``.

    The steps, each public for callers with their own bases or descriptors:
    :func:`prepare_shape` -> :func:`match_bases` -> :func:`match_descriptors` ->
    :func:`~torchfmap.fmap.solve_fmap` -> :func:`~torchfmap.fmap.fmap_to_p2p` ->
    :func:`refine_map`.

    Args:
        mesh_x, mesh_y: source and target.
        landmarks: ``(L, 2)`` corresponding pairs ``(vertex on x, vertex on y)``; required by
            the feature-aware bases, used as descriptors and constraints by all.
        basis: ``'laplacian'``, ``'harmonic'``, ``'diffusion'`` or ``'stack'`` (default:
            ``'stack'`` with landmarks, ``'laplacian'`` without).
        k: basis size (eigenfunctions; for stacks, the eigenfunctions fill up to ``k``).
        refine: ``'icp'`` or ``'zoomout'`` (eigenbasis: up to ``k_final``, default ``2k``;
            feature-aware: over growing scales), or None.
        n_descriptors, k_descriptors: see :func:`match_descriptors`.
        w_lap, w_orient, w_dcomm, w_lmk: weights of Laplacian commutativity (default
            :data:`W_LAP` of the basis), orientation preservation (tells left from right,
            which WKS alone cannot), descriptor commutativity and pointwise landmark
            preservation (see :func:`~torchfmap.fmap.solve_fmap`). With the last three at 0
            the solve is the exact row-wise one; otherwise preconditioned CG.
        p2p_mode: functional map -> point map conversion (:func:`~torchfmap.fmap.fmap_to_p2p`);
            default ``'orthogonal'`` for the eigenbasis, ``'pullback'`` for feature-aware bases.
        zoomout_samples: run eigenbasis ZoomOut on this many farthest-point samples per shape
            (the final point map uses every vertex).

    Raises:
        ParameterError: unknown basis or refinement, a feature-aware basis without landmarks,
            or an invalid ``k``; :class:`~torchfmap.SeedError` for invalid landmarks.
    """
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    pairs = None
    if landmarks is not None and len(np.atleast_1d(landmarks)):
        pairs = check_landmark_pairs(landmarks, mesh_x.n_vertices, mesh_y.n_vertices)
    kind = basis or ("stack" if pairs is not None else "laplacian")
    if kind not in BASIS_KINDS:
        raise ParameterError(f"unknown basis {kind!r}. Fix: one of {BASIS_KINDS}.")
    grow = refine == "zoomout" and kind == "laplacian"
    k_final = k_final if k_final is not None else (2 * k if grow else k)
    n_eigen = max(k_descriptors, k, k_final) if kind == "laplacian" else k_descriptors
    shape_x, shape_y = prepare_shape(mesh_x, n_eigen), prepare_shape(mesh_y, n_eigen)
    timings["operators+eigen"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    bx, by = match_bases(shape_x, shape_y, kind, k, pairs, times)
    timings["basis"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    desc_x, desc_y = match_descriptors(
        shape_x, shape_y, pairs, n_descriptors=n_descriptors, k_descriptors=k_descriptors
    )
    timings["descriptors"] = time.perf_counter() - t0

    t0 = time.perf_counter()
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
    )
    mode = p2p_mode or ("orthogonal" if kind == "laplacian" else "pullback")
    p2p = fmap_to_p2p(C, bx, by, mode=mode)
    timings["fmap+p2p"] = time.perf_counter() - t0
    initial = p2p

    t0 = time.perf_counter()
    if refine is not None:
        C, p2p = refine_map(
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
            landmarks=pairs,
            times=times,
            zoomout_samples=zoomout_samples,
        )
    timings["refine"] = time.perf_counter() - t0
    return MatchResult(p2p, C, bx, by, initial, timings)


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
    for i, j in tqdm(pairs, desc="shape pairs", disable=not progress):
        result = match(meshes[i], meshes[j], k=k, **match_kwargs)
        W_x, W_y = result.basis_x.projected_laplacian(), result.basis_y.projected_laplacian()
        D[i, j] = shape_distance(result.C_xy, W_x, W_y, kind=kind)
    return 0.5 * (D + D.T)
