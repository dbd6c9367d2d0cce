"""Scores of a point map without ground truth, which :func:`torchfmap.match` chooses and guards by, and
warnings on misread landmarks and collapsed maps."""

from __future__ import annotations

import warnings

import numpy as np

from ..bases.prepared import PreparedShape
from ..errors import MapWarning, ParameterError
from ..fmap.convert import check_p2p
from ..mesh import Mesh
from ..seeds import farthest_point_sampling

#: Anchors of :func:`geodesic_distortion` (farthest points on ``y``).
N_ANCHORS = 64
#: Relative resolution of :func:`geodesic_distortion`: maps whose scores differ by less are not told apart.
DISTORTION_RESOLUTION = 0.1
#: :func:`warn_if_off_by_one` judges landmark files of at least this many pairs ...
MISREAD_MIN_LANDMARKS = 5
#: ... and warns when the pairs shifted by -1 distort distances by this factor less than given ...
OFF_BY_ONE_RATIO = 0.7
#: ... or by this factor less on :data:`OFF_BY_ONE_MANY` pairs or more (a steadier mean) ...
OFF_BY_ONE_RATIO_MANY = 0.85
OFF_BY_ONE_MANY = 10
#: ... or the pairs with swapped columns by this factor less ...
SWAPPED_RATIO = 0.5
#: ... judging each reading on at most this many pairs, evenly spread (bounds the geodesic solves).
MISREAD_MAX_LANDMARKS = 20

__all__ = [
    "COLLAPSE_COVERAGE", "N_ANCHORS", "distortion_anchors", "geodesic_distortion", "landmark_distortion",
    "orientation_agreement", "warn_collapsed", "warn_if_off_by_one",
]  # fmt: skip


def distortion_anchors(shape_y: PreparedShape, n_anchors: int = N_ANCHORS) -> np.ndarray:
    """``(A,)`` anchors of :func:`geodesic_distortion`: ``min(n_anchors, V_y)`` farthest points of ``y``."""
    n = min(n_anchors, shape_y.mesh.n_vertices)
    return shape_y.derive(
        ("anchors", n), lambda: farthest_point_sampling(shape_y.mesh, n, metric="euclidean")
    )


def geodesic_distortion(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    p2p_yx,
    anchors: np.ndarray | None = None,
    *,
    area_ratio: float = 1.0,
) -> float:
    """``mean_{a, v} |s d_y(a, v) - d_x(p(a), p(v))|`` over ``anchors`` ``a`` and vertices ``v`` of ``y``, ``p
    = p2p_yx``, in units of ``sqrt(area)``; ``s = sqrt(area_ratio)`` for a part ``y`` of ``x``. ``0`` for an
    isometry.

    Raises:
        ParameterError: ``p2p_yx`` not ``(V_y,)`` indices into ``x``; ``area_ratio`` not > 0."""
    p2p = check_p2p(p2p_yx, shape_y.mesh.n_vertices, shape_x.mesh.n_vertices, "p2p_yx")
    if not area_ratio > 0:
        raise ParameterError(f"area_ratio must be > 0 (the part's area over the whole's), got {area_ratio}.")
    anchors = distortion_anchors(shape_y) if anchors is None else np.asarray(anchors, dtype=np.int64)
    d_y = shape_y.distances.distances(anchors) * np.sqrt(area_ratio)
    images, inverse = np.unique(p2p[anchors], return_inverse=True)
    d_x = shape_x.distances.distances(images)[inverse]
    return float(np.mean(np.abs(d_y - d_x[:, p2p])))


def orientation_agreement(mesh_x: Mesh, mesh_y: Mesh, p2p_yx) -> float:
    """``2 s - 1`` in ``[-1, 1]``, ``s`` the area share of ``y``'s faces whose image on ``x`` turns as ``x``'s
    normals (degenerate images left out; 0.0 if all are).

    Raises:
        ParameterError: ``p2p_yx`` not ``(V_y,)`` indices into ``x``."""
    p2p = check_p2p(p2p_yx, mesh_y.n_vertices, mesh_x.n_vertices, "p2p_yx")
    a, b, c = (p2p[mesh_y.faces[:, i]] for i in range(3))
    kept = (a != b) & (b != c) & (a != c)
    X, N = mesh_x.vertices, mesh_x.vertex_normals
    normal = np.cross(X[b] - X[a], X[c] - X[a])
    sign = np.sign(np.einsum("ij,ij->i", normal, N[a] + N[b] + N[c]))
    weight = mesh_y.face_areas * kept
    total = weight.sum()
    return float((sign * weight).sum() / total) if total > 0 else 0.0


def landmark_distortion(shape_x: PreparedShape, shape_y: PreparedShape, landmarks: np.ndarray) -> float:
    """Mean ``|d_x(a_i, a_j) - d_y(b_i, b_j)|`` over landmark pairs ``(L, 2)``, in units of ``sqrt(area)``."""
    dx = shape_x.distances.distances(landmarks[:, 0])[:, landmarks[:, 0]]
    dy = shape_y.distances.distances(landmarks[:, 1])[:, landmarks[:, 1]]
    return float(np.mean(np.abs(dx - dy)))


def warn_if_off_by_one(shape_x: PreparedShape, shape_y: PreparedShape, landmarks: np.ndarray) -> None:
    """Warn (``UserWarning``) when the landmark pairs shifted by -1 or with swapped columns fit far better
    than as given (:func:`landmark_distortion`; thresholds: :data:`OFF_BY_ONE_RATIO` and kin)."""
    if len(landmarks) < MISREAD_MIN_LANDMARKS:
        return
    one_based = landmarks.min() >= 1
    nx, ny = shape_x.mesh.n_vertices, shape_y.mesh.n_vertices
    swappable = landmarks[:, 1].max() < nx and landmarks[:, 0].max() < ny
    if len(landmarks) > MISREAD_MAX_LANDMARKS:
        landmarks = landmarks[np.linspace(0, len(landmarks) - 1, MISREAD_MAX_LANDMARKS).round().astype(int)]
    given = landmark_distortion(shape_x, shape_y, landmarks)
    readings = []
    if one_based:
        fix = "landmarks are 0-based vertex indices; subtract 1 if the file is 1-based"
        ratio = OFF_BY_ONE_RATIO_MANY if len(landmarks) >= OFF_BY_ONE_MANY else OFF_BY_ONE_RATIO
        readings.append(("shifted by -1 (were they read 1-based?)", landmarks - 1, ratio, fix))
    if swappable:
        fix = "each line is 'source_vertex target_vertex'; swap the columns"
        readings.append(("with their columns swapped", landmarks[:, ::-1].copy(), SWAPPED_RATIO, fix))
    for what, other, ratio, fix in readings:
        if len(np.unique(other[:, 0])) < len(other) or len(np.unique(other[:, 1])) < len(other):
            continue
        score = landmark_distortion(shape_x, shape_y, other)
        if score < ratio * given:
            warnings.warn(
                f"the landmarks fit the shapes {given / max(score, 1e-12):.1f}x better {what}: mean "
                f"distance distortion {score:.3f} vs {given:.3f} sqrt(area) as given. Fix: {fix}.",
                UserWarning,
                stacklevel=3,
            )
            return


#: A point map reaching under this fraction of the ``min(V_x, V_y)`` vertices it could reach has collapsed.
COLLAPSE_COVERAGE = 0.05


def warn_collapsed(p2p_yx: np.ndarray, n_x: int, stacklevel: int = 3) -> None:
    """Warn (:class:`~torchfmap.errors.MapWarning`) if ``p2p_yx`` reaches under :data:`COLLAPSE_COVERAGE`."""
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
