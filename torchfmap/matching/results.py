"""What :func:`torchfmap.match` returns, and its refinement step.

:class:`MatchResult` holds the map, the bases it lives in and how it was chosen;
:func:`refine_result` refines an unrefined result with a refiner
(:mod:`torchfmap.kinds.refiners`, as its kind gives it: ``kind.refiner(...)``), guarded by the
geodesic distortion when landmarks were given (:func:`keeps_refinement`).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from ..bases import Basis
from ..bases.prepared import PreparedShape
from ..errors import ParameterError
from ..fmap.refine import Refined
from .quality import DISTORTION_RESOLUTION, geodesic_distortion

__all__ = ["MatchResult", "keeps_refinement", "refine_result"]


def keeps_refinement(start: float | None, refined: float | None) -> bool:
    """The guard of every refinement with landmarks: a refined map is kept unless it raises the
    geodesic distortion (:func:`~torchfmap.matching.quality.geodesic_distortion`) of its start by more
    than the score's resolution (:data:`~torchfmap.matching.quality.DISTORTION_RESOLUTION`; ``start``
    None: no landmarks, no score, always kept). A smaller rise is noise, and ZoomOut that
    raises it slightly mostly lowers the error (``python3 -m bench accuracy --case
    refine_guard``)."""
    return start is None or refined <= (1 + DISTORTION_RESOLUTION) * start


def refine_result(
    result: MatchResult, refiner, shape_x: PreparedShape, shape_y: PreparedShape
) -> MatchResult:
    """``result`` (of :func:`~torchfmap.match`, unrefined) refined by ``refiner`` (called as
    ``refiner(C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds)``, e.g.
    ``get_kind(result.kind).refiner('zoomout', landmarks=pairs)``, as :func:`~torchfmap.match`
    builds it) on the prepared shapes it was solved on. With
    landmarks (``result.distortion`` set), a refinement that raises the geodesic distortion is
    dropped (:func:`keeps_refinement`): the result then keeps its map, with ``refined=False``.

    Raises:
        ParameterError: ``result`` was refined already; or as the refiner.
    """
    if result.refined:
        raise ParameterError(
            "refine_result takes an unrefined result of match(). Fix: match(..., refine=None)."
        )
    t0 = time.perf_counter()
    refined: Refined = refiner(
        result.C_xy, result.p2p_yx, shape_x, shape_y, result.basis_x, result.basis_y, result.seeds
    )
    timings = dict(result.timings)
    after = None
    if result.distortion is not None:
        after = geodesic_distortion(shape_x, shape_y, refined.p2p_yx)
    timings["refine"] = time.perf_counter() - t0
    if not keeps_refinement(result.distortion, after):  # worse by the score: keep the start
        return dataclasses.replace(result, timings=timings)
    C, p2p, bx, by, seeds = refined
    return dataclasses.replace(
        result, p2p_yx=p2p, C_xy=C, basis_x=bx, basis_y=by, seeds=seeds, timings=timings,
        distortion=after, refined=True,
    )  # fmt: skip


@dataclass
class MatchResult:
    """Output of :func:`match`: ``p2p_yx (V_y,)``, ``C_xy (K_y, K_x)``, the bases and timings;
    ``seeds`` ``(S, 2)`` are the corresponding seed pairs of feature-aware bases (else None);
    ``kind`` the name of the basis kind that ran. The bases are B-orthonormal in each mesh's
    unit-area frame (their ``mass`` is that of ``mesh.scaled(1 / sqrt(area))``), unless given.

    With landmarks, ``distortion`` is the map's :func:`~torchfmap.matching.quality.geodesic_distortion`
    (units of ``sqrt(area)``; None without landmarks) and ``refined`` whether the refinement was
    kept (a refinement that raises the distortion is dropped: ``p2p_yx`` is then the initial
    map). The landmark default also fills ``candidates``: each kind it solved in
    (:data:`~torchfmap.matching.pipeline.AUTO_KINDS`), by name, with its own result; ``skipped`` names the
    kinds that could not be built on these meshes, with the reason, and ``fold_scores`` each
    cross-validated kind's held-out landmark error
    (:func:`~torchfmap.matching.landmark_default.landmark_scores`). ``model`` names the trained network
    that made the map (:class:`torchfmap.nn.LearnedMatcher`; None for :func:`match`). A partial match
    (``match(whole, part, partial=True)``, :mod:`torchfmap.matching.partial`) sets ``overlap`` ``(V_x,)``,
    the estimated part on the whole in ``[0, 1]``, and ``partial_rank``, the rows of ``C_xy``."""

    p2p_yx: np.ndarray
    C_xy: np.ndarray
    basis_x: Basis
    basis_y: Basis
    p2p_yx_initial: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    seeds: np.ndarray | None = None
    kind: str = ""
    distortion: float | None = None
    refined: bool = False
    candidates: dict[str, MatchResult] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    model: str | None = None
    fold_scores: dict[str, float] = field(default_factory=dict)
    overlap: np.ndarray | None = None
    partial_rank: int | None = None

    def scores(self) -> str:
        """``'laplacian 0.051, hybrid 0.045*'``: each candidate's distortion, ``*`` the chosen
        one ('' when ``match`` did not choose); then, after the landmark cross-validation,
        ``'; held-out landmarks: laplacian 0.031, hybrid 0.029, diffusion 0.052'``."""
        marks = {name: "*" if name == self.kind else "" for name in self.candidates}
        text = ", ".join(f"{name} {c.distortion:.4f}{marks[name]}" for name, c in self.candidates.items())
        if self.fold_scores:
            held = ", ".join(f"{name} {v:.4f}" for name, v in self.fold_scores.items())
            text += f"; held-out landmarks: {held}"
        return text
