"""What :func:`torchfmap.match` returns, and its refinement step.

:class:`MatchResult` holds the map, the bases it lives in and how it was chosen;
:func:`refine_result` refines an unrefined result (ICP or ZoomOut, as the basis kind says),
guarded by the geodesic distortion when landmarks were given.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from ._deprecation import module_aliases
from .bases import Basis
from .bases.prepared import PreparedShape, with_eigenpairs
from .errors import ParameterError
from .fmap.refine import Refined
from .kinds import BasisKind, get_kind
from .quality import distortion_anchors, geodesic_distortion

#: The refinements of :func:`torchfmap.match` (``refine=``).
RefineMethod = Literal["icp", "zoomout", "seeded"]

__all__ = ["MatchContext", "MatchResult", "RefineMethod", "refine_map", "refine_result"]

#: The name of earlier releases ("kind" names basis kinds only).
__getattr__ = module_aliases(__name__, {"RefineKind": "RefineMethod"})


@dataclass(frozen=True)
class MatchContext:
    """What :func:`refine_result` needs of the :func:`match` call that made a result."""

    shape_x: PreparedShape
    shape_y: PreparedShape
    kind: BasisKind
    k: int
    k_final: int | None
    mode: str
    n_fixed: int
    times: object
    zoomout_samples: int | None
    #: the anchors of the distortion score on ``shape_y`` (sampled once, on creation)
    anchors: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "anchors", distortion_anchors(self.shape_y))


def refine_result(result: MatchResult, refine: RefineMethod) -> MatchResult:
    """``result`` (of :func:`match`, unrefined) refined by ``'icp'`` or ``'zoomout'``
    (the kind's :meth:`~torchfmap.kinds.BasisKind.refine`; ZoomOut grows eigenfunctions to
    ``k_final``, default ``2k``, in kinds that grow). With landmarks, a refinement that raises the
    geodesic distortion is dropped: the result then keeps its map, with ``refined=False``.

    Raises:
        ParameterError: ``result`` did not come from :func:`match`, was refined already, an
            unknown refinement, or ``k_final < k`` for ZoomOut.
    """
    ctx = result._context
    if ctx is None or result.refined:
        raise ParameterError(
            "refine_result takes an unrefined result of match(). Fix: match(..., refine=None)."
        )
    if refine not in ("icp", "zoomout"):
        raise ParameterError(f"unknown refinement {refine!r}. Fix: 'icp', 'zoomout' or None.")
    t0 = time.perf_counter()
    kind = ctx.kind
    grow = refine == "zoomout" and kind.grows
    k_final = ctx.k_final if ctx.k_final is not None else (2 * ctx.k if grow else ctx.k)
    if grow:
        if k_final < ctx.k:
            raise ParameterError(f"k_final={k_final} is below k={ctx.k}: ZoomOut grows. Fix: k_final >= k.")
        for shape in (ctx.shape_x, ctx.shape_y):  # grown in place when ZoomOut needs more
            with_eigenpairs(shape, k_final)
    C, p2p, bx, by, seeds = kind.refine(
        result.C_xy, result.p2p_yx, ctx.shape_x, ctx.shape_y, result.basis_x, result.basis_y, refine,
        k_final=k_final, mode=ctx.mode, seeds=result.seeds, n_fixed=ctx.n_fixed,
        times=ctx.times, zoomout_samples=ctx.zoomout_samples,
    )  # fmt: skip
    timings = dict(result.timings)
    distortion = result.distortion
    if distortion is not None:
        after = geodesic_distortion(ctx.shape_x, ctx.shape_y, p2p, ctx.anchors)
        if after > distortion:  # the refinement made the map worse by the score: keep the start
            timings["refine"] = time.perf_counter() - t0
            return dataclasses.replace(result, timings=timings)
        distortion = after
    timings["refine"] = time.perf_counter() - t0
    return dataclasses.replace(
        result, p2p_yx=p2p, C_xy=C, basis_x=bx, basis_y=by, seeds=seeds, timings=timings,
        distortion=distortion, refined=True,
    )  # fmt: skip


def refine_map(C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, method, *, kind, **kwargs) -> Refined:
    """Deprecated: ``get_kind(kind).refine(C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y,
    method, **kwargs)`` (:meth:`torchfmap.kinds.BasisKind.refine`; each kind owns its
    refinement)."""
    warnings.warn(
        "refine_map is deprecated: each basis kind refines its own maps. Fix: "
        "torchfmap.kinds.get_kind(kind).refine(...) with the same arguments.",
        DeprecationWarning,
        stacklevel=2,
    )
    return get_kind(kind).refine(C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, method, **kwargs)


@dataclass
class MatchResult:
    """Output of :func:`match`: ``p2p_yx (V_y,)``, ``C_xy (K_y, K_x)``, the bases and timings;
    ``seeds`` ``(S, 2)`` are the corresponding seed pairs of feature-aware bases (else None);
    ``kind`` the name of the basis kind that ran. The bases are B-orthonormal in each mesh's
    unit-area frame (their ``mass`` is that of ``mesh.scaled(1 / sqrt(area))``), unless given.

    With landmarks, ``distortion`` is the map's :func:`~torchfmap.quality.geodesic_distortion`
    (units of ``sqrt(area)``; None without landmarks) and ``refined`` whether the refinement was
    kept (a refinement that raises the distortion is dropped: ``p2p_yx`` is then the initial
    map). The landmark default also fills ``candidates``: each kind it solved in
    (:data:`AUTO_KINDS`), by name, with its own result; ``skipped`` names the kinds that could
    not be built on these meshes, with the reason. With ``refine='seeded'``, ``first_stage`` is
    the stage-1 result (the ZoomOut map the seeds were read from) and ``seeds`` the seed pairs
    ``(S, 2)`` stage 2 was solved with (as landmarks). ``model`` names the trained network that
    made the map (:class:`torchfmap.nn.LearnedMatcher`; None for :func:`match`)."""

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
    first_stage: MatchResult | None = None
    model: str | None = None
    _context: MatchContext | None = field(default=None, repr=False, compare=False)

    def scores(self) -> str:
        """``'laplacian 0.051, hybrid 0.045*'``: each candidate's distortion, ``*`` the chosen
        one ('' when ``match`` did not choose)."""
        marks = {name: "*" if name == self.kind else "" for name in self.candidates}
        return ", ".join(f"{name} {c.distortion:.4f}{marks[name]}" for name, c in self.candidates.items())
