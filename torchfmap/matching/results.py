"""What :func:`torchfmap.match` returns, and its refinement step under the one guard.

:class:`MatchResult` holds the map, the bases it lives in and how it was chosen;
:func:`refine_result` refines an unrefined result with a refiner
(:mod:`torchfmap.kinds.refiners`, as its kind gives it: ``kind.refiner(...)``) under one rule
for every refinement (whole or partial, classical or learned, with or without landmarks): it is
kept unless it raises the geodesic distortion past the score's resolution
(:func:`keeps_refinement`). With :data:`~torchfmap.matching.landmark_default.CV_REFINE_MIN_LANDMARKS`
or more landmarks the refinement is also cross-validated (each fold's map, solved without some
landmarks, refined without them too: do they move towards their partners?) and the figures are
reported (:class:`RefineCheck`, and a warning when a kept refinement moved them away). They
are not a veto: measured as one on the dev pairs, they mostly vetoed refinements that lowered
the error (``docs/guide.md``, "The refinement guard").
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..bases import Basis
from ..bases.prepared import PreparedShape
from ..errors import MapWarning, ParameterError
from ..fmap.refine import Refined
from .quality import DISTORTION_RESOLUTION, geodesic_distortion

__all__ = ["MatchResult", "RefineCheck", "keeps_refinement", "refine_result"]


def keeps_refinement(start: float, refined: float) -> bool:
    """The one refinement guard: a refined map is kept unless its geodesic distortion
    (:func:`~torchfmap.matching.quality.geodesic_distortion`) exceeds its start's by more than
    :data:`~torchfmap.matching.quality.DISTORTION_RESOLUTION`, its noise on near-isometric
    pairs, where ZoomOut that raises it slightly mostly lowers the error."""
    return refined <= (1 + DISTORTION_RESOLUTION) * start


@dataclass(frozen=True)
class RefineCheck:
    """Why a refinement was kept or dropped: the geodesic distortion ``before`` and ``after`` it
    (units of ``sqrt(area_x)``), the verdict, and ``held_out`` ``(raw, refined)``: the
    cross-validated held-out landmark errors of the same refinement where the match had enough
    landmarks (reported, not a veto: see the module), else None."""

    before: float
    after: float
    kept: bool
    held_out: tuple[float, float] | None = None

    @property
    def held_out_worse(self) -> bool:
        """The refinement moved held-out landmarks away from their partners in the folds."""
        return self.held_out is not None and self.held_out[1] > self.held_out[0]

    def __str__(self) -> str:
        verdict = "kept" if self.kept else "dropped (the unrefined map is returned)"
        text = f"refinement {verdict}: geodesic distortion {self.before:.4f} -> {self.after:.4f}"
        if self.held_out is not None:
            text += f", held-out landmark error {self.held_out[0]:.4f} -> {self.held_out[1]:.4f}"
        return text


def refine_result(
    result: MatchResult,
    refiner,
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    held_out: tuple[float, float] | None = None,
) -> MatchResult:
    """``result`` (of :func:`~torchfmap.match`, unrefined) refined by ``refiner`` (called as
    ``refiner(C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds)``, e.g.
    ``get_kind(result.kind).refiner('zoomout', landmarks=pairs)``, as :func:`~torchfmap.match`
    builds it) on the prepared shapes it was solved on, under the one guard (see the module):
    kept unless the geodesic distortion of the start (``result.distortion`` where the match had
    landmarks, else computed) rises past its resolution (:func:`keeps_refinement`).
    ``held_out`` ``(raw, refined)``: the cross-validated held-out landmark errors of this refinement
    (:func:`~torchfmap.matching.landmark_default.refinement_scores`), reported in
    ``refine_check`` and, when the refinement is kept although they rose, by a
    :class:`~torchfmap.errors.MapWarning` with the figures. A dropped refinement returns the
    start's map with ``refined=False``; ``refine_check`` holds the evidence either way.

    Raises:
        ParameterError: ``result`` was refined already; or as the refiner.
    """
    if result.refined:
        raise ParameterError(
            "refine_result takes an unrefined result of match(). Fix: match(..., refine=None)."
        )
    t0 = time.perf_counter()
    timings = dict(result.timings)
    refined: Refined = refiner(
        result.C_xy, result.p2p_yx, shape_x, shape_y, result.basis_x, result.basis_y, result.seeds
    )
    before = result.distortion
    if before is None:
        before = geodesic_distortion(shape_x, shape_y, result.p2p_yx)
    after = geodesic_distortion(shape_x, shape_y, refined.p2p_yx)
    check = RefineCheck(before, after, keeps_refinement(before, after), held_out)
    timings["refine"] = time.perf_counter() - t0
    if not check.kept:  # worse by the distortion: the start
        return dataclasses.replace(result, timings=timings, refine_check=check)
    if check.held_out_worse:
        warnings.warn(
            f"the refinement moved held-out landmarks away from their partners in cross-validation "
            f"(mean error {held_out[0]:.4f} -> {held_out[1]:.4f} sqrt(area)) and was kept, as the geodesic "
            "distortion did not rise (on the dev pairs this signal rarely foretold a worse map). Fix: "
            "refine=None keeps the unrefined map (result.p2p_yx_initial holds it here).",
            MapWarning,
            stacklevel=4,
        )
    C, p2p, bx, by, seeds = refined
    distortion = after if result.distortion is not None else None  # set with landmarks, as solved
    return dataclasses.replace(
        result, p2p_yx=p2p, C_xy=C, basis_x=bx, basis_y=by, seeds=seeds, timings=timings,
        distortion=distortion, refined=True, refine_check=check,
    )  # fmt: skip


@dataclass
class MatchResult:
    """Output of :func:`match`: ``p2p_yx (V_y,)``, ``C_xy (K_y, K_x)``, the bases and timings;
    ``seeds`` ``(S, 2)`` are the corresponding seed pairs of feature-aware bases (else None);
    ``kind`` the name of the basis kind that ran. The bases are B-orthonormal in each mesh's
    unit-area frame (their ``mass`` is that of ``mesh.scaled(1 / sqrt(area))``), unless given.

    With landmarks, ``distortion`` is the map's :func:`~torchfmap.matching.quality.geodesic_distortion`
    (units of ``sqrt(area)``; None without landmarks) and ``refined`` whether the refinement was
    kept (one the guard drops leaves ``p2p_yx`` the initial map; ``refine_check``, a
    :class:`RefineCheck`, says by which score and its figures). The landmark
    default also fills ``candidates``: each kind it solved in
    (:data:`~torchfmap.matching.pipeline.AUTO_KINDS`), by name, with its own result; ``skipped`` names the
    kinds that could not be built on these meshes, with the reason, and ``fold_scores`` each
    cross-validated kind's held-out landmark error
    (:func:`~torchfmap.matching.landmark_default.landmark_scores`). ``model`` names the trained network
    that made the map (:class:`torchfmap.nn.LearnedMatcher`; None for :func:`match`). A partial match
    (``match(whole, part, partial=True)``, :mod:`torchfmap.matching.partial`) sets ``overlap`` ``(V_x,)``,
    the estimated part on the whole in ``[0, 1]``, and ``partial_rank``, the rows of ``C_xy``; a
    coordinate model's partial map (:class:`torchfmap.nn.LearnedMatcher`) names the ``placement``
    of the part on the whole it was solved at, with each placement tried in ``candidates``."""

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
    refine_check: RefineCheck | None = None
    placement: str | None = None

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
