"""Refinement of functional maps: ICP and ZoomOut, in eigenbases and feature-aware bases.

Which applies where:

- **ICP** (Ovsjanikov et al. 2012): alternate nearest neighbours and the closest orthogonal
  ``C``. Any pair of B-orthonormal bases of equal size ``K`` in which isometries give
  orthogonal maps: eigenbases, and feature-aware bases built from *corresponding* seeds.
- **ZoomOut** (Melzi et al. 2019): alternate nearest neighbours and ``C = Φ_yᵀ B_y Φ_x[p2p]``
  while the basis grows. It needs *nested* bases. For an eigenbasis, the first ``k``
  eigenfunctions with ``k`` increasing. For feature-aware bases, pass a sequence of bases with
  growing spans (:func:`zoomout_sequence`): more scales (large to small ``t``) or more seeds
  (harmonic spans are nested in the seed set); or iterate at a fixed size, then move the seeds
  (:func:`refine_map`, the refinement of :func:`torchfmap.match`, which follows each basis
  kind's ``refinement``).
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np

from ..bases.basis import Basis
from ..bases.kinds import BasisKind, get_kind
from ..bases.kinds.hybrid import join_blocks, split_blocks
from ..bases.orthonormalize import orthonormalize_pair
from ..bases.prepared import PreparedShape
from ..errors import ParameterError
from ..seeds import farthest_point_sampling, replace_seeds
from .convert import check_p2p, fmap_to_p2p, nearest_neighbor, p2p_to_fmap
from .defaults import default_p2p_mode, zoomout_step

Mode = Literal["pullback", "orthogonal"]


def icp_refine(
    C_xy: np.ndarray,
    basis_x: Basis,
    basis_y: Basis,
    n_iter: int = 10,
    tol: float = 1e-10,
    *,
    mode: Mode | None = None,
):
    """ICP refinement; returns ``(C_xy, p2p_yx)``. ``C_xy`` must be square.

    ``mode`` is the point-map conversion (:func:`~torchfmap.fmap.fmap_to_p2p`): ``'orthogonal'``
    is the classical choice in eigenbases; ``'pullback'`` works in any basis; default
    :func:`~torchfmap.fmap.defaults.default_p2p_mode`.
    """
    mode = default_p2p_mode(basis_x, basis_y) if mode is None else mode
    C = np.asarray(C_xy, dtype=np.float64)
    if C.shape[0] != C.shape[1]:
        raise ParameterError(f"ICP needs a square map, got {C.shape}. Fix: use the same K on both shapes.")
    k = C.shape[0]
    p2p = fmap_to_p2p(C, basis_x, basis_y, mode=mode)
    for _ in range(n_iter):
        target = p2p_to_fmap(p2p, basis_x, basis_y, k, k)
        u, _, vt = np.linalg.svd(target)
        new = u @ vt
        p2p = fmap_to_p2p(new, basis_x, basis_y, mode=mode)
        change = np.linalg.norm(new - C) / max(np.linalg.norm(C), 1e-300)
        C = new
        if change < tol:
            break
    return C, p2p


def _check_samples(subsample, basis_x: Basis, basis_y: Basis) -> tuple[np.ndarray, np.ndarray] | None:
    if subsample is None:
        return None
    try:
        sx, sy = (np.asarray(s) for s in subsample)
    except (TypeError, ValueError) as err:
        raise ParameterError("subsample must be a pair (vertices of x, vertices of y).") from err
    for s, b, name in ((sx, basis_x, "x"), (sy, basis_y, "y")):
        if s.ndim != 1 or not len(s) or not np.issubdtype(s.dtype, np.integer):
            raise ParameterError(f"subsample of {name} must be a non-empty 1-D array of vertex indices.")
        if s.min() < 0 or s.max() >= b.n_vertices:
            raise ParameterError(f"subsample of {name} has vertices outside [0, {b.n_vertices}).")
    return sx.astype(np.int64), sy.astype(np.int64)


def _sample_step(C, bx: Basis, by: Basis, kx: int, ky: int, samples, mode: Mode):
    """One ZoomOut step on samples: match samples of y to samples of x with ``C``, then the
    least-squares map ``C (ky, kx)`` with ``Φ_y[S_y] C ≈ Φ_x[S_x[p2p]]`` (no mass on samples)."""
    sx, sy = samples
    cy, cx = C.shape
    phi_x, phi_y = bx.values[sx], by.values[sy]
    if mode == "pullback":
        p2p = nearest_neighbor(phi_y[:, :cy] @ C, phi_x[:, :cx], precision="single")
    else:
        p2p = nearest_neighbor(phi_y[:, :cy], phi_x[:, :cx] @ C.T, precision="single")
    return np.linalg.lstsq(phi_y[:, :ky], phi_x[p2p, :kx], rcond=None)[0]


def zoomout(
    C_xy: np.ndarray,
    basis_x: Basis,
    basis_y: Basis,
    k_final: int,
    step: int | None = None,
    *,
    mode: Mode | None = None,
    subsample=None,
    guard: bool = True,
):
    """ZoomOut by basis prefixes: from ``C_xy.shape`` up to ``(k_final, k_final)``.

    Meaningful when the first columns span nested, coarse-to-fine subspaces (eigenbases).

    ``guard``: ZoomOut never returns a map worse than its start by its own energy
    (:func:`zoomout_energy`, the orthogonality defect of the map's prefixes, Melzi et al. 2019
    Eq. 2): the point map of every iteration (with ``subsample``: the start and the end) is
    scored at ``k_final`` and the best one is returned, with its ``C`` of size ``k_final``.

    Args:
        step: eigenfunctions added per iteration (default
            :func:`~torchfmap.fmap.defaults.zoomout_step` of the start size).
        mode: point-map conversion (default :func:`~torchfmap.fmap.defaults.default_p2p_mode`:
            ``'orthogonal'``, the classical choice, for eigenbases).
        subsample: ``(vertices of x, vertices of y)``: run the iterations on these samples only
            (nearest neighbours between samples, least-squares maps), as in the ZoomOut
            paper's accelerated variant; only the final point map uses every vertex. The cost
            of an iteration drops from ``V_x V_y k`` to ``S_x S_y k``.

    Returns:
        ``(C_xy (k_final, k_final), p2p_yx (V_y,))``.
    """
    C = np.asarray(C_xy, dtype=np.float64)
    if k_final < min(C.shape):
        raise ParameterError(
            f"k_final={k_final} is below the map's size {min(C.shape)}: ZoomOut only grows. Fix: "
            "k_final >= the current K (or truncate C_xy first)."
        )
    if k_final > min(basis_x.k, basis_y.k):
        raise ParameterError(f"k_final={k_final} exceeds the bases' sizes {basis_x.k}, {basis_y.k}.")
    step = zoomout_step(min(C.shape)) if step is None else step
    if step < 1:
        raise ParameterError(f"step must be >= 1, got {step}.")
    samples = _check_samples(subsample, basis_x, basis_y)
    mode = default_p2p_mode(basis_x, basis_y) if mode is None else mode
    k = min(C.shape)
    sizes = list(range(k, k_final, step)) + [k_final]
    best = None  # (energy, p2p) of the best point map so far (guard)

    def keep(p2p: np.ndarray) -> None:
        nonlocal best
        if guard:
            energy = zoomout_energy(p2p, basis_x, basis_y, sizes)
            if best is None or energy < best[0]:
                best = (energy, p2p)

    if samples is None:
        p2p = fmap_to_p2p(C, basis_x, basis_y, mode=mode)
        keep(p2p)
        while k < k_final:
            k = min(k + step, k_final)
            C = p2p_to_fmap(p2p, basis_x, basis_y, k, k)
            p2p = fmap_to_p2p(C, basis_x, basis_y, mode=mode)
            keep(p2p)
    else:
        if guard:
            keep(fmap_to_p2p(C, basis_x, basis_y, mode=mode))
        while k < k_final:
            k = min(k + step, k_final)
            C = _sample_step(C, basis_x, basis_y, k, k, samples, mode)
        p2p = fmap_to_p2p(C, basis_x, basis_y, mode=mode)
        keep(p2p)
    if best is not None and best[1] is not p2p:
        p2p = best[1]
        C = p2p_to_fmap(p2p, basis_x, basis_y, k_final, k_final)
    return C, p2p


def zoomout_energy(p2p_yx: np.ndarray, basis_x: Basis, basis_y: Basis, sizes) -> float:
    """ZoomOut's energy of a point map (Melzi et al. 2019, Eq. 2): ``Σ_k ‖C_kᵀ C_k - I‖² / k``
    over the prefix sizes ``k`` in ``sizes``, ``C_k`` the ``(k, k)`` prefix of the map's
    ``C = Φ_yᵀ B_y Φ_x[p2p]`` at the largest size. Small for maps whose functional maps are
    orthogonal at every scale (near-isometries); a map mixing up parts raises it."""
    kf = max(sizes)
    C = p2p_to_fmap(p2p_yx, basis_x, basis_y, kf, kf)
    total = 0.0
    for k in sizes:
        Ck = C[:k, :k]
        total += float(np.sum((Ck.T @ Ck - np.eye(k)) ** 2)) / k
    return total


def zoomout_sequence(
    p2p_yx: np.ndarray,
    bases_x: list[Basis],
    bases_y: list[Basis],
    *,
    mode: Mode | None = None,
    subsample=None,
):
    """ZoomOut over explicit sequences of bases with growing spans (feature-aware bases).

    Starting from a point map, for each pair ``(bases_x[i], bases_y[i])``: project, then
    convert back. With ``subsample`` ``(vertices of x, vertices of y)``, only the first
    projection uses every vertex; the later steps match samples to samples and fit ``C`` by
    least squares (as :func:`zoomout`'s accelerated variant), and only the final point map
    is computed on every vertex. Returns ``(C_xy in the last pair, p2p_yx (V_y,))``.
    """
    if len(bases_x) != len(bases_y) or not bases_x:
        raise ParameterError("bases_x and bases_y must be non-empty sequences of the same length.")
    p2p = check_p2p(p2p_yx, bases_y[0].n_vertices, bases_x[0].n_vertices, "p2p_yx")
    samples = _check_samples(subsample, bases_x[0], bases_y[0])
    mode = default_p2p_mode(bases_x[-1], bases_y[-1]) if mode is None else mode
    C = None
    for bx, by in zip(bases_x, bases_y, strict=True):
        if samples is None or C is None:
            C = p2p_to_fmap(p2p, bx, by)
        else:
            C = _sample_step(C, bx, by, bx.k, by.k, samples, mode)
        if samples is None:
            p2p = fmap_to_p2p(C, bx, by, mode=mode)
    if samples is not None:
        p2p = fmap_to_p2p(C, bases_x[-1], bases_y[-1], mode=mode)
    return C, p2p


def map_to_p2p(
    C_xy: np.ndarray, basis_x: Basis, basis_y: Basis, kind: str | BasisKind, mode: Mode
) -> np.ndarray:
    """``p2p_yx (V_y,)`` of ``C_xy`` in a pair of ``kind``'s bases: nearest neighbours of the
    kind's embeddings (:meth:`~torchfmap.bases.kinds.BasisKind.embeddings`) when it defines
    them, else :func:`~torchfmap.fmap.fmap_to_p2p` by ``mode``."""
    pair = get_kind(kind).embeddings(C_xy, basis_x, basis_y)
    if pair is None:
        return fmap_to_p2p(C_xy, basis_x, basis_y, mode=mode)
    return nearest_neighbor(pair[1], pair[0], precision="single")


def hybrid_zoomout(
    p2p_yx: np.ndarray,
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    basis_x: Basis,
    basis_y: Basis,
    kind: BasisKind,
    k_final: int,
    step: int | None = None,
    *,
    guard: bool = True,
) -> tuple[np.ndarray, np.ndarray, Basis, Basis]:
    """ZoomOut of a hybrid pair of bases (:mod:`torchfmap.bases.kinds.hybrid`): the eigen block
    grows from its size to ``k_final - k_f`` eigenfunctions by ``step`` (default
    :func:`~torchfmap.fmap.defaults.zoomout_step` of its size) while the feature block keeps its
    ``k_f`` columns; at each size both blocks are refitted from the point map
    (``C = Φᵀ B_y Φ[p2p]`` per block) and the point map is recomputed from the joint embedding.

    ``guard``: as :func:`zoomout`'s, scored by :func:`zoomout_energy` of the eigen block (the
    feature block is not orthonormal, so it has no orthogonality energy): the start and every
    iterate are scored over the eigen sizes and the lowest-energy point map is returned, with
    both blocks refitted from it at the final size.

    Returns ``(C_xy, p2p_yx, basis_x, basis_y)`` in the grown bases.

    Raises:
        ParameterError: ``k_final`` not above the feature block, or too few eigenpairs.
    """
    (ex, fx), (_, fy) = split_blocks(basis_x), split_blocks(basis_y)
    k_e, k_f = ex.k, fx.k
    k_end = k_final - k_f
    if k_end < k_e:
        raise ParameterError(f"k_final={k_final} leaves fewer eigenfunctions than the start ({k_e}).")
    if shape_x.n_eigen < k_end or shape_y.n_eigen < k_end:
        raise ParameterError(f"hybrid ZoomOut needs {k_end} eigenpairs. Fix: prepare_shape(mesh, {k_end}).")
    step = zoomout_step(k_e) if step is None else step
    if step < 1:
        raise ParameterError(f"step must be >= 1, got {step}.")
    p2p = check_p2p(p2p_yx, basis_y.n_vertices, basis_x.n_vertices, "p2p_yx")
    sizes = list(range(k_e, k_end, step)) + [k_end]
    eig_x, eig_y = shape_x.eigenbasis, shape_y.eigenbasis

    def refit(p2p: np.ndarray, size: int) -> np.ndarray:
        C = np.zeros((size + k_f, size + k_f))
        C[:size, :size] = p2p_to_fmap(p2p, eig_x, eig_y, size, size)
        C[size:, size:] = p2p_to_fmap(p2p, fx, fy, k_f, k_f) if kind.refit else np.eye(k_f)
        return C

    best = (zoomout_energy(p2p, eig_x, eig_y, sizes), p2p) if guard else None
    for size in sizes:  # bounded: one pass per size
        bx = join_blocks(eig_x.truncated(size), fx)
        by = join_blocks(eig_y.truncated(size), fy)
        C = refit(p2p, size)
        p2p = map_to_p2p(C, bx, by, kind, "orthogonal")
        if guard:
            energy = zoomout_energy(p2p, eig_x, eig_y, sizes)
            if energy < best[0]:
                best = (energy, p2p)
    if guard and best[1] is not p2p:
        p2p = best[1]
        C = refit(p2p, k_end)
    return C, p2p, bx, by


#: Fixed-size refinement steps (point map <-> functional map) in feature-aware bases.
FEATURE_REFINE_STEPS = 5
#: Rounds of seed re-placement after the fixed-size refinement (:func:`~torchfmap.seeds.replace_seeds`).
FEATURE_SEED_MOVES = 2
#: Farthest-point samples per basis column for the iterations of feature-aware refinement (the
#: least-squares map of ``K`` columns is fitted on ``25 K`` sample rows; only the last point map
#: of each round uses every vertex), so the cost of an iteration does not grow with ``V²``
#: (accuracy against every-vertex iterations: ``bench/feature_accuracy.py``).
FEATURE_SAMPLES_PER_COLUMN = 25


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
    method: str,
    *,
    kind: str | BasisKind,
    k_final: int,
    mode: Mode,
    seeds: np.ndarray | None = None,
    n_fixed: int = 0,
    times=None,
    zoomout_samples: int | None = None,
) -> Refined:
    """The map refined by ``'icp'`` or ``'zoomout'`` (the refinement step of :func:`torchfmap.match`).

    ICP works in ``basis_x, basis_y``. ZoomOut follows the kind's ``refinement``
    (:data:`torchfmap.bases.KINDS`): ``'grow'`` grows the prepared eigenbases up to ``k_final``
    (:func:`zoomout`, on ``zoomout_samples`` farthest-point samples per shape if given);
    otherwise it starts from the current map and alternates ``C`` and the point map
    :data:`FEATURE_REFINE_STEPS` times at full size (on :data:`FEATURE_SAMPLES_PER_COLUMN`
    ``x K`` farthest-point samples per shape, the last point map on every vertex); then, for
    bases built at corresponding ``seeds`` (``(S, 2)``, the first ``n_fixed`` being landmarks)
    of a ``'reseed'`` kind, :data:`FEATURE_SEED_MOVES` times it moves the seeds to where the map
    puts them (:func:`~torchfmap.seeds.replace_seeds`), rebuilds the bases, restarts from
    ``C = I`` in them and alternates again.

    Raises:
        ParameterError: an unknown method or kind.
    """
    kind = get_kind(kind)
    if method == "icp":
        return Refined(*icp_refine(C_xy, basis_x, basis_y, mode=mode), basis_x, basis_y, seeds)
    if method != "zoomout":
        raise ParameterError(f"unknown refinement {method!r}. Fix: 'icp', 'zoomout' or None.")
    if kind.refinement == "grow":
        full_x, full_y = shape_x.eigenbasis, shape_y.eigenbasis
        samples = None
        if zoomout_samples is not None:
            samples = tuple(
                farthest_point_sampling(m, min(zoomout_samples, m.n_vertices), metric="euclidean")
                for m in (shape_x.mesh, shape_y.mesh)
            )
        C, p2p = zoomout(C_xy, full_x, full_y, k_final, mode=mode, subsample=samples)
        return Refined(C, p2p, full_x.truncated(k_final), full_y.truncated(k_final), None)
    if kind.refinement == "hybrid":
        C, p2p, bx, by = hybrid_zoomout(p2p_yx, shape_x, shape_y, basis_x, basis_y, kind, k_final)
        return Refined(C, p2p, bx, by, seeds)
    steps = FEATURE_REFINE_STEPS
    bx, by = basis_x, basis_y
    n_samples = min(FEATURE_SAMPLES_PER_COLUMN * bx.k, shape_x.mesh.n_vertices, shape_y.mesh.n_vertices)
    samples = tuple(
        farthest_point_sampling(s.mesh, n_samples, metric="euclidean") for s in (shape_x, shape_y)
    )
    C, p2p = zoomout_sequence(p2p_yx, [bx] * steps, [by] * steps, mode=mode, subsample=samples)
    if seeds is None or kind.refinement != "reseed":
        return Refined(C, p2p, bx, by, seeds)
    raw_x = kind.functions(shape_x, seeds[:, 0], times)  # x's seeds never move (kernels cached)
    for _ in range(FEATURE_SEED_MOVES):
        seeds = replace_seeds(shape_x.distances, shape_y.distances, seeds, p2p, n_fixed)
        raw_y = kind.functions(shape_y, seeds[:, 1], times)
        bx, by = (b.truncated(basis_x.k) for b in orthonormalize_pair(raw_x, raw_y))
        p2p = fmap_to_p2p(np.eye(by.k, bx.k), bx, by, mode=mode)
        C, p2p = zoomout_sequence(p2p, [bx] * steps, [by] * steps, mode=mode, subsample=samples)
    return Refined(C, p2p, bx, by, seeds)
