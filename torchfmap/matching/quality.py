"""How good is a point map, without ground truth: scores that :func:`torchfmap.match` chooses by.

- :func:`geodesic_distortion`: how much the map changes geodesic distances. Anchors spread over
  ``y`` (farthest points) and their images on ``x`` are compared by their distances to every
  vertex: ``mean |d_y(a, v) - d_x(p(a), p(v))|`` in units of ``sqrt(area)``. A correct map of
  an isometry scores the discretisation noise only; maps that tear a part off, send a leg to
  another leg or scatter vertices score more, and so do correct maps of non-isometric pairs, but
  the *same* amount for every candidate of one pair, so scores of one pair compare maps. It is
  blind to intrinsic symmetries (a left-right swap preserves distances).
- :func:`orientation_agreement`: the area share of ``y``'s triangles whose image on ``x`` keeps
  its orientation, as ``2 share - 1`` in ``[-1, 1]``: near 1 for smooth orientation-preserving
  maps, near -1 for mirror images, near 0 for scattered ones. Reported beside the distortion.
- :func:`landmark_distortion`: distances among landmark pairs compared on the two shapes
  (landmarks read with the wrong index base or swapped columns stand out);
  :func:`warn_if_off_by_one` warns on that;
- :func:`warn_collapsed`: a map that reaches only a few source vertices.
"""

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
#: The resolution of :func:`geodesic_distortion` as a judge: maps whose scores differ by less than
#: this fraction are not told apart (on near-isometric pairs good maps differ by discretisation
#: noise). The landmark default's choice and every refinement's guard read it.
DISTORTION_RESOLUTION = 0.1
#: :func:`warn_if_off_by_one` reads landmark files of at least this many pairs (fewer distances
#: among them do not tell readings apart: 3 landmarks give 3 distances).
MISREAD_MIN_LANDMARKS = 5
#: ... and warns when the pairs shifted by -1 distort distances by this factor less than given,
#: judged on fewer than :data:`OFF_BY_ONE_MANY` pairs (a shift by one vertex often lands near the
#: intended vertex: a weaker signal than a swap, and few distances among few pairs are noisy) ...
OFF_BY_ONE_RATIO = 0.7
#: ... or by this factor less on :data:`OFF_BY_ONE_MANY` pairs or more (the mean over their
#: distances is steadier: on dev pairs, SMAL_r across species, TOSCA with stretched copies, FAUST_r,
#: correct files shifted by -1 never scored below 0.89 of as given, 1-based ones mostly below 0.85).
OFF_BY_ONE_RATIO_MANY = 0.85
OFF_BY_ONE_MANY = 10
#: ... or the pairs with swapped columns by this factor less.
SWAPPED_RATIO = 0.5
#: ... judging each reading on at most this many of the pairs, evenly spread over the file's
#: order (190 distances among them; a misreading shifts most of them): the check costs two
#: distance solves (each ``O(V)``) per pair judged and reading, bounded whatever the file holds.
MISREAD_MAX_LANDMARKS = 20

__all__ = [
    "COLLAPSE_COVERAGE",
    "N_ANCHORS",
    "distortion_anchors",
    "geodesic_distortion",
    "landmark_distortion",
    "orientation_agreement",
    "warn_collapsed",
    "warn_if_off_by_one",
]


def distortion_anchors(shape_y: PreparedShape, n_anchors: int = N_ANCHORS) -> np.ndarray:
    """``(A,)`` anchors of :func:`geodesic_distortion` on ``y``: ``min(n_anchors, V_y)``
    Euclidean farthest points (deterministic: they start from vertex 0's farthest point)."""
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
    """``mean_{a, v} |s d_y(a, v) - d_x(p(a), p(v))|`` over anchors ``a`` on ``y`` (default
    :func:`distortion_anchors`) and every vertex ``v`` of ``y``, ``p = p2p_yx``, in units of
    ``sqrt(area)`` (prepared shapes live in their unit-area frame). ``s = sqrt(area_ratio)``:
    for a part ``y`` of ``x`` (area ratio ``a``, :mod:`torchfmap.matching.partial`), ``y``'s distances in
    ``x``'s units. Lower is better; ``0`` for an exact isometry. Distance rows are computed by,
    and kept in, each shape's ``distances``.

    Raises:
        ParameterError: ``p2p_yx`` not ``(V_y,)`` indices into ``x``; ``area_ratio`` not > 0.
    """
    p2p = check_p2p(p2p_yx, shape_y.mesh.n_vertices, shape_x.mesh.n_vertices, "p2p_yx")
    if not area_ratio > 0:
        raise ParameterError(f"area_ratio must be > 0 (the part's area over the whole's), got {area_ratio}.")
    anchors = distortion_anchors(shape_y) if anchors is None else np.asarray(anchors, dtype=np.int64)
    d_y = shape_y.distances.distances(anchors) * np.sqrt(area_ratio)
    images, inverse = np.unique(p2p[anchors], return_inverse=True)
    d_x = shape_x.distances.distances(images)[inverse]
    return float(np.mean(np.abs(d_y - d_x[:, p2p])))


def orientation_agreement(mesh_x: Mesh, mesh_y: Mesh, p2p_yx) -> float:
    """``2 s - 1`` where ``s`` is the area share of ``y``'s faces whose image triangle on ``x``
    (vertices ``p2p_yx[face]``) turns the same way as ``x``'s vertex normals there; faces whose
    image has a repeated vertex are left out (0.0 if every face is). In ``[-1, 1]``.

    Raises:
        ParameterError: ``p2p_yx`` not ``(V_y,)`` indices into ``x``.
    """
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
    """Mean ``|d_x(a_i, a_j) - d_y(b_i, b_j)|`` over landmark pairs ``(a_i, b_i)``, in units of
    ``sqrt(area)``: small for corresponding landmarks on near-isometric shapes, large for
    landmarks that do not correspond (e.g. read with the wrong index base)."""
    dx = shape_x.distances.distances(landmarks[:, 0])[:, landmarks[:, 0]]
    dy = shape_y.distances.distances(landmarks[:, 1])[:, landmarks[:, 1]]
    return float(np.mean(np.abs(dx - dy)))


def warn_if_off_by_one(shape_x: PreparedShape, shape_y: PreparedShape, landmarks: np.ndarray) -> None:
    """Warn (``UserWarning``) when another reading of the landmark pairs fits the shapes far
    better than the given one, by :func:`landmark_distortion` (distances among landmarks agree
    on corresponding points): the pairs shifted by -1 (a 1-based file; at least
    :data:`MISREAD_MIN_LANDMARKS` pairs, better by :data:`OFF_BY_ONE_RATIO`, or by
    :data:`OFF_BY_ONE_RATIO_MANY` on :data:`OFF_BY_ONE_MANY` pairs or more) or with their
    columns swapped (target vertex first; better by :data:`SWAPPED_RATIO`). Judged on at most
    :data:`MISREAD_MAX_LANDMARKS` pairs: at most ``6 · MISREAD_MAX_LANDMARKS`` geodesic solves
    (those of the given pairs reused by the feature-aware bases)."""
    if len(landmarks) < MISREAD_MIN_LANDMARKS:
        return
    one_based = landmarks.min() >= 1  # of every pair: one 0 rules the shifted reading out
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
