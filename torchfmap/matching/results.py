"""What :func:`torchfmap.match` returns (:class:`MatchResult`) and its refinement under the one guard
(:func:`refine_result`)."""

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
    """The one guard: kept unless the distortion rises by over :data:`~.quality.DISTORTION_RESOLUTION`."""
    return refined <= (1 + DISTORTION_RESOLUTION) * start


@dataclass(frozen=True)
class RefineCheck:
    """Why a refinement was kept or dropped: the geodesic distortion ``before`` and ``after`` (units of
    ``sqrt(area_x)``), the verdict, and ``held_out`` ``(raw, refined)`` landmark errors (or None)."""

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
    """Unrefined ``result`` refined by ``refiner(C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds)``,
    unless :func:`keeps_refinement` refuses it (then the start's map, ``refined=False``); ``held_out`` ``(raw,
    refined)`` is reported in ``refine_check``, with a :class:`~torchfmap.errors.MapWarning` if it rose.

    Raises:
        ParameterError: ``result`` was refined already; or as the refiner."""
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
    if not check.kept:
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
    distortion = after if result.distortion is not None else None
    return dataclasses.replace(
        result, p2p_yx=p2p, C_xy=C, basis_x=bx, basis_y=by, seeds=seeds, timings=timings,
        distortion=distortion, refined=True, refine_check=check,
    )  # fmt: skip


@dataclass
class MatchResult:
    """Output of :func:`match`: ``p2p_yx (V_y,)``, ``C_xy (K_y, K_x)``, the bases (B-orthonormal in unit-area
    frames unless given), timings, ``seeds`` ``(S, 2)`` of feature-aware bases (or None), the ``kind`` that
    ran. With landmarks, ``distortion`` (:func:`~torchfmap.matching.quality.geodesic_distortion`); ``refined``
    and ``refine_check`` (:class:`RefineCheck`). The landmark default fills ``candidates``, ``skipped`` and
    ``fold_scores``; ``model`` names a network (:class:`torchfmap.nn.LearnedMatcher`); partial maps set
    ``overlap`` ``(V_x,)``, and ``partial_rank``."""

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

    def scores(self) -> str:
        """``'laplacian 0.051, hybrid 0.045*'``: each candidate's distortion, ``*`` the chosen, then ``';
        held-out landmarks: ...'`` if cross-validated."""
        marks = {name: "*" if name == self.kind else "" for name in self.candidates}
        text = ", ".join(f"{name} {c.distortion:.4f}{marks[name]}" for name, c in self.candidates.items())
        if self.fold_scores:
            held = ", ".join(f"{name} {v:.4f}" for name, v in self.fold_scores.items())
            text += f"; held-out landmarks: {held}"
        return text
