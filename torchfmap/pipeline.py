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
    Column,
    basis_stack,
    concatenate,
    diffusion_basis,
    harmonic_basis,
    laplacian_eigenbasis,
    orthonormalize,
    orthonormalize_pair,
)
from .bases.laplacian import eigenpairs
from .descriptors import landmark_descriptors, normalize_descriptors, wks
from .errors import ParameterError
from .eval import shape_distance
from .fmap import check_landmark_pairs, fmap_to_p2p, icp_refine, solve_fmap, zoomout, zoomout_sequence
from .mesh import Mesh
from .operators.laplacian import laplacian
from .seeds import farthest_point_sampling

BasisKind = Literal["laplacian", "harmonic", "diffusion", "stack"]
BASIS_KINDS = ("laplacian", "harmonic", "diffusion", "stack")
#: Default Laplacian-commutativity weight per basis (the mask is normalised to mean 1). Mean
#: error over cat0-cat1, cat2-cat8, wolf0-wolf1 and cat-lion (k=50, 10 or 20 landmarks,
#: ``python bench/weight_sweep.py``) for w_lap = 1e-3 / 0.1 / 1 / 10: laplacian
#: 0.026 / 0.022 / 0.025 / 0.029, harmonic 0.041 / 0.039 / 0.040 / 0.047, diffusion
#: 0.089 / 0.065 / 0.029 / 0.032, stack 0.122 / 0.075 / 0.028 / 0.029. Projected Laplacians of
#: small-t heat kernels have very large top eigenvalues, which dominate the mask's mean, so
#: diffusion bases need a larger weight (at 1e-3, cat-lion failed: 0.27 and 0.40).
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


def _feature_bases(sides, pairs: np.ndarray, kind: str, k: int, times) -> tuple[Basis, Basis]:
    """Corresponding feature-aware bases on both shapes, orthonormalised together so that
    column ``i`` is built from the same landmark and scale on both."""
    n_eigen = max(0, k - (len(times) + 1) * len(pairs)) if kind == "stack" else 0
    raw = []
    for s, (mesh, ops) in enumerate(sides):
        seeds = pairs[:, s]
        if kind == "harmonic":
            b = harmonic_basis(mesh, seeds, operators=ops)
        elif kind == "diffusion":
            b = diffusion_basis(mesh, seeds, times, operators=ops, tol=1e-6, local=False)
        else:
            b = basis_stack(
                mesh, seeds, times=times, operators=ops, heat_tol=1e-6, local=False, orthonormalization=None
            )
        b.stiffness = ops[0]
        raw.append(b)
    bx, by = orthonormalize_pair(*raw)
    if n_eigen:  # eigenfunctions fill up to k; they do not correspond column by column
        bx = _append_eigen(bx, *sides[0], n_eigen)
        by = _append_eigen(by, *sides[1], n_eigen)
    return bx, by


def _append_eigen(basis: Basis, mesh: Mesh, ops, n_eigen: int) -> Basis:
    stacked = concatenate([basis, laplacian_eigenbasis(mesh, n_eigen, operators=ops)])
    stacked.stiffness = ops[0]
    return orthonormalize(stacked)


def _coarse_to_fine(sides, pairs: np.ndarray, kind: str, times) -> tuple[list[Basis], list[Basis]]:
    """Nested corresponding feature-aware bases for ZoomOut: growing scales (large to small t)."""
    parts = [
        [diffusion_basis(mesh, pairs[:, s], [t], operators=ops, tol=1e-6, local=False) for t in times]
        for s, (mesh, ops) in enumerate(sides)
    ]
    if kind == "stack":
        for s, (mesh, ops) in enumerate(sides):
            parts[s].append(harmonic_basis(mesh, pairs[:, s], operators=ops))
    seq_x, seq_y = [], []
    for j in range(len(parts[0])):
        raw = [concatenate(p[: j + 1]) for p in parts]
        for b, (_, ops) in zip(raw, sides, strict=True):
            b.stiffness = ops[0]
        bx, by = orthonormalize_pair(*raw)
        seq_x.append(bx)
        seq_y.append(by)
    if kind == "diffusion":  # the last level equals the matching basis
        seq_x, seq_y = seq_x[:-1], seq_y[:-1]
    return seq_x, seq_y


def match(
    mesh_x: Mesh,
    mesh_y: Mesh,
    *,
    landmarks=None,
    basis: BasisKind | None = None,
    k: int = 50,
    refine: Literal["icp", "zoomout"] | None = None,
    k_final: int | None = None,
    n_descriptors: int = 20,
    k_descriptors: int = 100,
    w_lap: float | None = None,
    w_orient: float = 1e-2,
    w_dcomm: float = 0.0,
    w_lmk: float = 1.0,
    times=MATCH_TIMES,
    p2p_mode: Literal["pullback", "orthogonal"] | None = None,
    zoomout_samples: int | None = None,
) -> MatchResult:
    """Match ``y`` to ``x``: returns ``p2p_yx`` and ``C_xy``.

    Args:
        mesh_x, mesh_y: source and target.
        landmarks: ``(L, 2)`` corresponding pairs ``(vertex on x, vertex on y)``; required by
            the feature-aware bases, used as descriptors and constraints by all.
        basis: ``'laplacian'``, ``'harmonic'``, ``'diffusion'`` or ``'stack'`` (default:
            ``'stack'`` with landmarks, ``'laplacian'`` without).
        k: basis size (eigenfunctions; for stacks, the eigenfunctions fill up to ``k``).
        refine: ``'icp'`` or ``'zoomout'`` (eigenbasis: up to ``k_final``, default ``2k``;
            feature-aware: over growing scales / seeds).
        n_descriptors: WKS descriptors kept (100 energies from ``k_descriptors`` eigenpairs,
            subsampled evenly).
        w_lap, w_orient, w_dcomm, w_lmk: weights of Laplacian commutativity (default
            :data:`W_LAP` of the basis), orientation
            preservation (resolves the left-right flips that WKS alone cannot see; measured on
            cat0/cat1 with 10 landmarks: 0.040 mean error with it, 0.216 without), descriptor
            commutativity and pointwise landmark preservation (see
            :func:`~torchfmap.fmap.solve_fmap`). With all three at 0 the solve is the exact
            row-wise one; the others make it an iterative (preconditioned CG) solve.
        p2p_mode: functional map -> point map conversion (:func:`~torchfmap.fmap.fmap_to_p2p`);
            default ``'orthogonal'`` for the eigenbasis and ``'pullback'`` for feature-aware
            bases (measured on the 17K wolf pair at k=100: eigenbasis ZoomOut 0.0016 mean error
            with ``'orthogonal'``, 0.0084 with ``'pullback'``).
        zoomout_samples: run the eigenbasis ZoomOut iterations on this many farthest-point
            samples per shape (the final point map uses every vertex); much faster on large
            meshes (wolf pair, 2000 samples: 0.0027 vs 0.0016 mean error, about 10x faster).
    """
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    pairs = None
    if landmarks is not None and len(np.atleast_1d(landmarks)):
        pairs = check_landmark_pairs(landmarks, mesh_x.n_vertices, mesh_y.n_vertices)
    kind = basis or ("stack" if pairs is not None else "laplacian")
    if kind not in BASIS_KINDS:
        raise ParameterError(f"unknown basis {kind!r}. Fix: one of {BASIS_KINDS}.")
    if kind != "laplacian" and pairs is None:
        raise ParameterError(
            f"the {kind} basis is built from corresponding landmarks on both shapes. Fix: pass "
            "landmarks (pairs of vertices), or use basis='laplacian'."
        )
    ops_x, ops_y = laplacian(mesh_x), laplacian(mesh_y)
    k_eig = max(
        k, k_final or 0, 2 * k if (refine == "zoomout" and kind == "laplacian" and k_final is None) else 0
    )
    k_eig = max(k_eig, k_descriptors) if kind == "laplacian" else k_descriptors
    lam_x, phi_x = eigenpairs(*ops_x, k_eig)
    lam_y, phi_y = eigenpairs(*ops_y, k_eig)
    timings["operators+eigen"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    n_d = min(k_descriptors, k_eig)
    step = max(1, 100 // max(1, n_descriptors))
    desc_x = [wks(lam_x[:n_d], phi_x[:, :n_d], 100)[:, ::step][:, :n_descriptors]]
    desc_y = [wks(lam_y[:n_d], phi_y[:, :n_d], 100)[:, ::step][:, :n_descriptors]]
    if pairs is not None:
        desc_x.append(landmark_descriptors(pairs[:, 0], operators=ops_x, times=(1e-2, 3e-2)))
        desc_y.append(landmark_descriptors(pairs[:, 1], operators=ops_y, times=(1e-2, 3e-2)))
    desc_x = normalize_descriptors(np.hstack(desc_x), ops_x[1])
    desc_y = normalize_descriptors(np.hstack(desc_y), ops_y[1])
    timings["descriptors"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if kind == "laplacian":
        full_x = Basis(
            phi_x, ops_x[1], [Column("laplacian", index=i) for i in range(k_eig)], True, ops_x[0], lam_x
        )
        full_y = Basis(
            phi_y, ops_y[1], [Column("laplacian", index=i) for i in range(k_eig)], True, ops_y[0], lam_y
        )
        bx = Basis(phi_x[:, :k], ops_x[1], full_x.provenance[:k], True, ops_x[0], lam_x[:k])
        by = Basis(phi_y[:, :k], ops_y[1], full_y.provenance[:k], True, ops_y[0], lam_y[:k])
    else:
        bx, by = _feature_bases(((mesh_x, ops_x), (mesh_y, ops_y)), pairs, kind, k, times)
    timings["basis"] = time.perf_counter() - t0

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
    if refine == "icp":
        C, p2p = icp_refine(C, bx, by, mode=mode)
    elif refine == "zoomout":
        if kind == "laplacian":
            samples = None
            if zoomout_samples is not None:
                samples = tuple(
                    farthest_point_sampling(m, min(zoomout_samples, m.n_vertices), metric="euclidean")
                    for m in (mesh_x, mesh_y)
                )
            C, p2p = zoomout(
                C, full_x, full_y, k_final or 2 * k, step=max(1, k // 10), mode=mode, subsample=samples
            )
        else:
            if kind == "harmonic":
                raise ParameterError(
                    "ZoomOut needs nested bases that grow; a harmonic basis only grows with more "
                    "corresponding seeds, and the landmarks are all there is. Fix: refine='icp', or "
                    "basis='stack' / 'diffusion' (ZoomOut over growing scales)."
                )
            seq_x, seq_y = _coarse_to_fine(((mesh_x, ops_x), (mesh_y, ops_y)), pairs, kind, times)
            C, p2p = zoomout_sequence(p2p, seq_x + [bx], seq_y + [by], mode=mode)
    elif refine is not None:
        raise ParameterError(f"unknown refinement {refine!r}. Fix: 'icp', 'zoomout' or None.")
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
