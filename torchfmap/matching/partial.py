"""Partial-to-full matching of a part ``y`` to a whole ``x`` in the same units (Partial Functional Maps,
Rodolà et al. 2017); why each step: docs/guide.md, "Partial shapes"."""

from __future__ import annotations

import functools
import time

import numpy as np

from .._util.checks import check_landmark_pairs
from ..bases import Basis
from ..bases.prepared import PreparedShape
from ..descriptors import check_descriptors, landmark_descriptors, shot
from ..errors import ParameterError
from ..fmap import fmap_to_p2p, p2p_to_fmap, solve_fmap
from ..fmap.convert import check_p2p
from ..fmap.defaults import DEFAULT_K, W_DCOMM, W_LAP_SMOOTH, W_LMK, W_ORIENT, zoomout_step
from ..fmap.nearest import SurfaceSampling, search_p2p
from ..fmap.refine import Samples, SpectralStep, check_anchors, check_k_final, zoomout_iterations
from ..kinds.refiners import check_refine, landmark_coordinates, pair_samplings
from ..mesh import Mesh
from ..seeds import farthest_point_sampling
from .quality import geodesic_distortion
from .results import MatchResult, keeps_refinement

#: A part may be up to this much larger than the whole (noise); beyond it the shapes look swapped.
AREA_SLACK = 1.05
#: The smallest part, as a share of the whole's area, that a partial map is attempted for.
MIN_AREA_RATIO = 0.01
#: Seeds of the re-seeded pass (:func:`reseeded_map`), landmarks included.
RESEED_SEEDS = 100
#: Width ``σ`` of the re-seeded pass's functions ``exp(-d²/σ²)``, units of the whole's ``sqrt(area)``.
RESEED_WIDTH = 0.15

__all__ = [
    "common_frame", "families", "match_partial", "overlap_indicator", "partial_rank", "partial_zoomout",
    "reseeded_map",
]  # fmt: skip


def area_ratio(mesh_x: Mesh, mesh_y: Mesh) -> float:
    """``area(y) / area(x)`` in the meshes' own units, capped at 1.

    Raises:
        ParameterError: over :data:`AREA_SLACK` (swapped or different units) or under
            :data:`MIN_AREA_RATIO`."""
    a = mesh_y.area / mesh_x.area
    units = (
        "If the meshes are in different units (millimetres and metres make areas 1e6 apart), "
        "scale one (Mesh.scaled, or rewrite the file) so both share them"
    )
    if a > AREA_SLACK:
        swapped = "pass the whole shape first (match(whole, part, partial=True)). "
        if a > 1 / MIN_AREA_RATIO:  # no part of a whole in the same units is that much larger
            swapped = ""
        raise ParameterError(
            f"the part (mesh_y) has {a:.3g} times the area of the whole (mesh_x): a part is never "
            f"larger than its whole. Fix: {swapped}{units}."
        )
    if a < MIN_AREA_RATIO:
        raise ParameterError(
            f"the part (mesh_y) has {a:.3g} of the area of the whole (mesh_x), below "
            f"{MIN_AREA_RATIO:g}: fewer than one of its eigenfunctions would be matched. Fix: {units}; "
            "a part this small is matched by landmarks or descriptors, not by a partial functional map."
        )
    return min(a, 1.0)


def common_frame(basis: Basis, a: float) -> Basis:
    """The part's eigenbasis in the whole's unit-area frame (the part of area ``a``)."""
    return Basis(
        basis.values / np.sqrt(a), basis.mass * a, basis.provenance, orthonormal=basis.orthonormal,
        stiffness=basis.stiffness / a, eigenvalues=basis.eigenvalues / a,
    )  # fmt: skip


def partial_rank(eigenvalues_x: np.ndarray, eigenvalues_y: np.ndarray, k: int) -> int:
    """``r = #{j : λ_y,j <= λ_x,k}`` (in one frame, :func:`common_frame`), at least 1."""
    lam_max = float(eigenvalues_x[k - 1])
    return int(np.clip(np.sum(np.asarray(eigenvalues_y) <= lam_max * (1 + 1e-9)), 1, len(eigenvalues_y)))


#: SHOT's support radius in units of the whole's ``sqrt(area)`` (the same on the part).
SHOT_RADIUS = 0.08


def shot_descriptors(shape: PreparedShape, whole: PreparedShape | None = None) -> np.ndarray:
    """``(V, 352)`` SHOT of ``shape`` at :data:`SHOT_RADIUS` times ``sqrt(area)`` of ``whole`` (or own)."""
    radius = SHOT_RADIUS * np.sqrt((shape if whole is None else whole).mesh.area)
    return shape.derive(("shot", radius), lambda: shot(shape.mesh, radius))


def families(given: list[tuple[np.ndarray, np.ndarray]], mass) -> tuple[np.ndarray, np.ndarray]:
    """``(desc_x (V_x, D), desc_y (V_y, D))``: descriptor families ``[(F_x (V_x, D_i), F_y (V_y, D_i)), ...]``
    side by side, each column divided by its ``mass`` (``(V_x, V_x)``) norm on ``x``, then each family
    scaled by ``sqrt(max D_i / D_i)`` so that it weighs as the widest (64 learned features next to
    SHOT's 352 count as much as SHOT); one family: unit columns."""
    widest = max(fx.shape[1] for fx, _ in given)
    out_x, out_y = [], []
    for fx, fy in given:
        norms = np.sqrt(np.einsum("vd,vd->d", fx, mass @ fx))
        norms = np.where(norms > 0, norms, 1.0) / np.sqrt(widest / fx.shape[1])
        out_x.append(fx / norms)
        out_y.append(fy / norms)
    return np.hstack(out_x), np.hstack(out_y)


def overlap_indicator(C_xy: np.ndarray, full: Basis, part: Basis) -> np.ndarray:
    """``(V_x,)`` the part on the whole, ``Φ_x Cᵀ Φ_yᵀ B_y 1`` through ``C_xy`` ``(r, k)``, in ``[0, 1]``."""
    r, k = C_xy.shape
    ones = part.project(np.ones(part.n_vertices))[:r]
    return np.clip(full.values[:, :k] @ (C_xy.T @ ones), 0.0, 1.0)


def partial_zoomout(
    p2p_yx: np.ndarray,
    full: Basis,
    part: Basis,
    k: int,
    k_final: int,
    step: int | None = None,
    anchors: tuple[np.ndarray, np.ndarray] | None = None,
    samplings: tuple[SurfaceSampling, SurfaceSampling] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """ZoomOut for a part, ``k`` to ``k_final`` columns of the whole, each step on the part's first ``r(k)``
    eigenfunctions; ``anchors`` ``(A_x (V_x, m), A_y (V_y, m))``, ``samplings`` as
    :func:`~torchfmap.fmap.zoomout`. Returns ``(C_xy (r(k_final), k_final), p2p_yx (V_y,))``."""
    anchors = check_anchors(anchors, full, part)
    step = zoomout_step(k) if step is None else step
    sizes = list(range(k + step, k_final, step)) + [k_final]
    rank = functools.partial(partial_rank, full.eigenvalues, part.eigenvalues)
    spectral = SpectralStep(full, part, "orthogonal", anchors, rank=rank)
    samples = Samples.of_pair(samplings)
    p2p_yx = check_p2p(p2p_yx, part.n_vertices, full.n_vertices)
    return zoomout_iterations(spectral, sizes, p2p_yx=p2p_yx, samples=samples)


def reseeded_map(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    p2p_yx: np.ndarray,
    landmarks: np.ndarray | None = None,
    *,
    n_seeds: int = RESEED_SEEDS,
    width: float = RESEED_WIDTH,
) -> np.ndarray:
    """``(V_y,)`` map of the part ``y`` into the whole ``x`` re-seeded from ``p2p_yx``: seeds are the
    ``landmarks`` ``(L, 2)`` (whole, part), then farthest points of the part up to ``n_seeds`` with their
    ``p2p_yx`` images; each part vertex goes to the whole vertex whose functions ``exp(-(d / width)²)`` at the
    seeds (units of the whole's ``sqrt(area)``) are nearest.

    Raises:
        ParameterError: ``n_seeds`` < 1, ``width`` not > 0, ``p2p_yx`` not ``(V_y,)`` indices into ``x``,
            landmarks not ``(L, 2)``.
        SeedError: landmarks outside either mesh or repeated."""
    if n_seeds < 1 or not width > 0:
        raise ParameterError(f"reseeded_map needs n_seeds >= 1 and width > 0, got {n_seeds}, {width}.")
    n_x, n_y = shape_x.mesh.n_vertices, shape_y.mesh.n_vertices
    p2p_yx = check_p2p(p2p_yx, n_y, n_x, "p2p_yx")
    pairs = np.zeros((0, 2), np.int64) if landmarks is None else check_landmark_pairs(landmarks, n_x, n_y)
    n = int(min(max(n_seeds, len(pairs)), n_y))
    on_part = farthest_point_sampling(
        shape_y.mesh, n, landmarks=pairs[:, 1] if len(pairs) else None, start=0,
        distances=shape_y.distances,
    )  # fmt: skip
    on_whole = np.concatenate([pairs[:, 0], p2p_yx[on_part[len(pairs) :]]])
    unique, column = np.unique(on_whole, return_inverse=True)  # two seeds may share an image
    d_x = shape_x.distances.distances(unique).T[:, column]
    d_y = shape_y.distances.distances(on_part).T * np.sqrt(area_ratio(shape_x.mesh, shape_y.mesh))
    query, reference = np.exp(-((d_y / width) ** 2)), np.exp(-((d_x / width) ** 2))
    samplings = pair_samplings(shape_x, shape_y)  # dense pairs: searched near the first map
    coarse = None if samplings is None else samplings[0].cell[p2p_yx[samplings[1].index]]
    return search_p2p(query, reference, samplings, coarse=coarse, precision="double")


def match_partial(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    *,
    landmarks: np.ndarray | None = None,
    k: int = DEFAULT_K,
    refine: str | None = None,
    k_final: int | None = None,
    w_lap: float = W_LAP_SMOOTH,
    w_orient: float = W_ORIENT,
    w_dcomm: float = W_DCOMM,
    w_lmk: float = W_LMK,
    descriptors: tuple[np.ndarray, np.ndarray] | None = None,
    with_shot: bool = False,
) -> MatchResult:
    """Match the part ``y`` to the whole ``x`` on prepared shapes: a :class:`~torchfmap.MatchResult` (``kind``
    ``'partial'``) with ``C_xy`` ``(r, k)`` (refined: ``(r(k_final), k_final)``), ``overlap`` ``(V_x,)`` and
    ``partial_rank`` ``r``. ``refine``: None or ``'zoomout'`` (:func:`partial_zoomout`, default ``k_final =
    2k``, and :func:`reseeded_map`); ``landmarks``: ``(L, 2)`` checked pairs (whole, part); ``descriptors``:
    ``(V_x, D)``, ``(V_y, D)`` features instead of SHOT, or next to it with ``with_shot`` (:func:`families`).

    Raises:
        ParameterError: the part larger than the whole, ``refine`` not None or ``'zoomout'``, ``k_final < k``,
            shapes prepared with too few eigenpairs, or ``descriptors`` not one finite row per vertex."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    check_refine(refine, allowed=("zoomout",), what="partial matching")
    a = area_ratio(shape_x.mesh, shape_y.mesh)
    if refine:
        check_k_final(k, k_final)
    k_final = (2 * k if k_final is None else k_final) if refine else k
    n_x = k_final
    for name, shape in (("shape_x", shape_x), ("shape_y", shape_y)):
        if shape.eigenbasis is None or shape.eigenbasis.k < n_x:
            raise ParameterError(f"{name} needs {n_x} eigenpairs. Fix: prepare_shape(mesh, {n_x}).")
    full = shape_x.eigenbasis
    part = common_frame(shape_y.eigenbasis, a)
    r = partial_rank(full.eigenvalues, part.eigenvalues, k)
    timings["operators+eigen"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    given = []
    if descriptors is not None:
        given = [tuple(
            check_descriptors(d, s.mesh.n_vertices, f"descriptors[{i}]")
            for i, (d, s) in enumerate(zip(descriptors, (shape_x, shape_y), strict=True))
        )]  # fmt: skip
    if descriptors is None or with_shot:
        given.insert(0, (shot_descriptors(shape_x), shot_descriptors(shape_y, whole=shape_x)))
    desc_x, desc_y = families(given, full.mass)
    if landmarks is not None:  # heat kernels at the same physical times on both, in the common frame
        hx = landmark_descriptors(landmarks[:, 0], operators=shape_x.operators)
        hy = landmark_descriptors(landmarks[:, 1], operators=shape_y.operators, area=1.0 / a) / a
        hx, hy = families([(hx, hy)], full.mass)  # unit columns, each like one descriptor
        desc_x, desc_y = np.hstack([desc_x, hx]), np.hstack([desc_y, hy])
    timings["descriptors"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    bx, by = full.truncated(k), part.truncated(r)
    C = solve_fmap(
        bx, by, desc_x, desc_y, w_lap=w_lap, w_orient=w_orient, w_dcomm=w_dcomm,
        meshes=(shape_x.mesh, shape_y.mesh), landmarks=landmarks,
        w_lmk=w_lmk if landmarks is not None else 0.0,
    )  # fmt: skip
    samplings = pair_samplings(shape_x, shape_y)  # dense pairs: searched locally
    p2p = fmap_to_p2p(C, bx, by, mode="orthogonal", samplings=samplings)
    timings["fmap+p2p"] = time.perf_counter() - t0
    initial = p2p
    if refine:
        t0 = time.perf_counter()
        anchors = None
        if landmarks is not None:  # the part's distances in the whole's units
            ax, ay = landmark_coordinates(shape_x, shape_y, landmarks)
            anchors = (ax, ay * np.sqrt(a))
        p2p = partial_zoomout(p2p, full, part, k, k_final, anchors=anchors, samplings=samplings)[1]
        p2p = reseeded_map(shape_x, shape_y, p2p, landmarks)
        again = partial_zoomout(p2p, full, part, k, k_final, anchors=anchors, samplings=samplings)[1]
        before, after = (geodesic_distortion(shape_x, shape_y, q, area_ratio=a) for q in (p2p, again))
        if keeps_refinement(before, after):
            p2p = again
        p2p = reseeded_map(shape_x, shape_y, p2p, landmarks)  # last: ZoomOut blurs what seeds hold
        C = p2p_to_fmap(p2p, full, part, k_final, partial_rank(full.eigenvalues, part.eigenvalues, k_final))
        timings["refine"] = time.perf_counter() - t0
    r_final = C.shape[0]
    result = MatchResult(
        p2p, C, full.truncated(C.shape[1]), part.truncated(r_final), initial, timings, kind="partial",
        refined=refine is not None,
    )  # fmt: skip
    result.overlap = overlap_indicator(C, full, part)
    result.partial_rank = r_final
    return result
