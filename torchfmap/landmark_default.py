"""The landmark default of :func:`torchfmap.match` (``basis=None`` or ``'auto'`` with
landmarks): which basis to solve a pair in, chosen without ground truth.

Each kind of :data:`AUTO_KINDS` is solved on shapes prepared once (:func:`~torchfmap.solve.solve_pair`)
and the map that preserves geodesic distances best is kept (:data:`AUTO_MARGIN` in favour of the
eigenbasis).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ._checks import check_count
from .bases.prepared import PreparedShape
from .errors import ParameterError
from .fmap import check_landmark_pairs
from .kinds import BasisKind, get_kind
from .kinds.refiners import check_refine
from .match_checks import check_k_final, check_unused
from .mesh import Mesh
from .quality import warn_if_off_by_one
from .results import MatchResult, RefineMethod, refine_result
from .solve import P2PMode, prepare_shapes, solve_pair

#: The kinds the landmark default (``basis=None`` or ``'auto'`` with landmarks) solves in, in
#: order of preference: the eigenbasis first (optimal for isometries), then the feature-aware
#: ``hybrid``. ``diffusion`` is not a candidate: its maps are built by trilateration from the
#: landmarks, so they preserve geodesic distances by construction and score a lower distortion
#: than maps with lower error (bench/landmark_default.py: chosen on 1 of 6 near-isometric pairs
#: at 7 landmarks, 1.24x the eigenbasis's error there).
AUTO_KINDS = ("laplacian", "hybrid")
#: The landmark default keeps the eigenbasis unless a feature-aware map distorts geodesic
#: distances by this fraction less (:func:`~torchfmap.quality.geodesic_distortion`): on
#: near-isometric pairs the scores of good maps differ by discretisation noise, and there the
#: eigenbasis is the better basis.
AUTO_MARGIN = 0.1


def match_landmark_default(
    mesh_x: Mesh,
    mesh_y: Mesh,
    landmarks: np.ndarray,
    *,
    k: int = 50,
    refine: RefineMethod | None = None,
    k_final: int | None = None,
    times=None,
    zoomout_samples: int | None = None,
    shapes: tuple[PreparedShape, PreparedShape] | None = None,
    k_descriptors: int = 100,
    p2p_mode: P2PMode | None = None,
    **solve,
) -> MatchResult:
    """The landmark default of :func:`match` (``basis=None`` or ``'auto'`` with landmarks): each
    kind of :data:`AUTO_KINDS` solved (:func:`solve_pair`) on shapes prepared once, the
    eigenbasis refined as asked (ZoomOut is where it gains most) and the feature-aware kinds
    unrefined; the map of least geodesic distortion is kept (the eigenbasis within
    :data:`AUTO_MARGIN`), and a chosen feature-aware map is then refined (guarded by the same
    score), so only one feature-aware refinement runs. Kinds that cannot be built on these
    meshes (e.g. too few vertices for their columns) are skipped, with the reason
    (``skipped``); ``candidates`` holds each solved kind's result (:func:`match` warns if the
    chosen map collapsed). ``landmarks``: ``(L, 2)``
    pairs; ``solve``: the other solver settings of :func:`solve_pair`; the rest as :func:`match`.

    Raises:
        ParameterError: what the eigenbasis refuses (it refuses only what every kind would),
            or an unknown refinement.
    """
    t0 = time.perf_counter()
    refine = check_refine(refine)
    pairs = check_landmark_pairs(landmarks, mesh_x.n_vertices, mesh_y.n_vertices)
    n_max = min(mesh_x.n_vertices, mesh_y.n_vertices) - 1
    check_count(k, 1, n_max, "k (basis size)")  # the eigenbasis's own check, before any work
    need = [k, min(k_descriptors, n_max)]  # the eigenbasis: k, and its descriptors
    if refine == "zoomout":
        need.append(k_final or 2 * k)
    shape_x, shape_y = prepare_shapes(mesh_x, mesh_y, shapes, min(max(need), n_max))
    prep = time.perf_counter() - t0
    pref = AUTO_KINDS[0]
    check_unused(get_kind(AUTO_KINDS[-1]), refine, k_final, None)
    check_k_final(get_kind(pref), refine, k, k_final)
    warn_if_off_by_one(shape_x, shape_y, pairs)
    candidates: dict[str, MatchResult] = {}
    skipped: dict[str, str] = {}

    def refined(result: MatchResult, kind: BasisKind) -> MatchResult:
        refiner = kind.refiner(
            refine, k_final=k_final, mode=p2p_mode, n_fixed=len(pairs),
            times=times if kind.needs_landmarks else None, zoomout_samples=zoomout_samples,
        )  # fmt: skip
        return refine_result(result, refiner, shape_x, shape_y)

    for name in AUTO_KINDS:
        kind = get_kind(name)
        first = name == pref
        try:
            grow = (k_final or 2 * k) if first and refine == "zoomout" and kind.grows else 0
            result = solve_pair(
                shape_x, shape_y, kind, k, landmarks=pairs, times=times if kind.needs_landmarks else None,
                n_eigen=grow, k_descriptors=k_descriptors, p2p_mode=p2p_mode, **solve,
            )  # fmt: skip
            candidates[name] = refined(result, kind) if first and refine is not None else result
        except ParameterError as err:
            if first:  # the eigenbasis refuses only what every kind would
                raise
            skipped[name] = str(err)
    best = min(candidates, key=lambda n: candidates[n].distortion)
    if candidates[best].distortion > (1 - AUTO_MARGIN) * candidates[pref].distortion:
        best = pref
    if refine is not None and best != pref:
        candidates[best] = refined(candidates[best], get_kind(best))
    chosen = candidates[best]
    timings = {"prepare": prep}
    for name, c in candidates.items():
        timings |= {f"{name}:{step}": t for step, t in c.timings.items()}
    return dataclasses.replace(chosen, timings=timings, candidates=candidates, skipped=skipped)
