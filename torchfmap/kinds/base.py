"""What every basis kind is: the settings the pipeline reads, how it builds its functions, and
how it refines a map in its bases.

A kind is a small frozen object in the registry :data:`torchfmap.kinds.KINDS`; the pipeline,
the command line, the datasets and the learned path read it instead of comparing strings. Each
field and method and who reads it: docs/architecture.md, "Basis kinds: one registry"; adding a
kind: "How to add ..." there (a subclass of :class:`SeededKind` or :class:`BasisKind`, one line
in ``kinds/__init__.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._util.checks import check_times
from ..bases.basis import Basis
from ..bases.orthonormalize import orthonormalize, orthonormalize_pair
from ..bases.prepared import PreparedShape
from ..errors import ParameterError
from ..fmap.convert import fmap_to_p2p
from ..fmap.defaults import W_ORIENT
from ..fmap.nearest import SurfaceSampling, nearest_neighbor, search_p2p
from ..seeds import corresponding_seeds, farthest_point_sampling
from .refiners import ICP, FixedSizeIterations, SeedMoves, check_refine

#: Bound on the passes that add seeds when orthonormalisation dropped dependent columns.
MAX_SEED_PASSES = 8


def seed_time(n_seeds: int) -> float:
    """Relative heat time whose kernel width matches the covering radius of ``n_seeds`` seeds.

    ``n`` seeds cover a surface of unit area with radius about ``sqrt(1 / n)``; the kernel
    ``exp(-d² / 4t)`` falls to ``1/e`` at ``d = sqrt(4t)``, so ``t = 1 / (4 n)``: each point is
    then told apart by the few kernels around it, without gaps between seeds.
    """
    return 1.0 / (4.0 * n_seeds)


def relative_times(times, n_seeds: int) -> tuple[float, ...]:
    """``times`` as a sorted tuple, or the default one time :func:`seed_time` of ``n_seeds``.

    Raises:
        ParameterError: an empty, non-finite or non-positive time list.
    """
    if times is None:
        return (seed_time(n_seeds),)
    return tuple(sorted(check_times(times, fix="e.g. times=[0.01]").tolist()))


def seeds_for(shape: PreparedShape, n_columns: int, per_seed: int, seeds=None, n_seeds: int | None = None):
    """``seeds`` ``(S_0,)`` then farthest-point seeds of ``shape``: ``n_seeds`` in all (default:
    enough for ``n_columns`` columns of ``per_seed`` each plus one spare), at least the given
    ones and at most the vertex count. Returns ``(S,)`` vertex indices."""
    given = np.zeros(0, dtype=np.int64) if seeds is None else np.atleast_1d(np.asarray(seeds))
    if n_seeds is None:
        n_seeds = -(-n_columns // per_seed) + 1
    n_seeds = min(max(len(given), n_seeds), shape.mesh.n_vertices)
    return farthest_point_sampling(shape.mesh, n_seeds, landmarks=given if len(given) else None)


@dataclass(frozen=True, kw_only=True)
class BasisKind:
    """A kind of basis: ``needs_landmarks`` (pair bases built at corresponding landmarks, the map
    pulled towards ``C = I``), ``w_lap`` / ``w_orient`` (the solve's weights), ``p2p_mode``
    (``'orthogonal'`` or ``'pullback'``), ``column_families`` (recognises a basis,
    :func:`torchfmap.kinds.kind_of`), ``learned`` (the torch layers train and predict in it)."""

    name: str
    summary: str
    needs_landmarks: bool
    w_lap: float
    p2p_mode: str
    column_families: frozenset[str] = frozenset()
    w_orient: float = W_ORIENT
    learned: bool = True
    #: whether ZoomOut grows the kind's eigenfunctions (the shapes then need ``k_final``
    #: eigenpairs, :func:`~torchfmap.bases.prepared.with_eigenpairs`)
    grows: bool = False

    def __post_init__(self) -> None:
        if not self.column_families:
            raise ParameterError(
                f"kind {self.name!r} names no column families. Fix: column_families=frozenset({{...}}), the "
                "Column families of its bases ('laplacian', 'harmonic', 'diffusion', 'custom')."
            )

    def n_eigen(self, k: int) -> int:
        """Eigenpairs each prepared shape needs for a basis of ``k`` columns of this kind."""
        return 0

    def pair_bases(
        self, shape_x: PreparedShape, shape_y: PreparedShape, k: int, landmarks=None, times=None
    ) -> tuple[Basis, Basis, np.ndarray | None]:
        """The two bases of exactly ``k`` columns that :func:`~torchfmap.match` solves in
        (B-orthonormal block by block, :meth:`block_bases`), and the seed pairs ``(S, 2)``
        they are built at (None if none correspond)."""
        raise NotImplementedError

    def shape_basis(self, shape: PreparedShape, k: int, *, seeds=None, times=None) -> Basis:
        """One shape's B-orthonormal basis of exactly ``k`` columns (datasets, ``torchfmap
        basis``, :class:`~torchfmap.nn.BasisModule`); ``seeds`` are placed first, farthest-point
        seeds fill the rest."""
        raise NotImplementedError

    def block_bases(self, basis: Basis) -> list[Basis]:
        """The blocks of a basis of this kind that are each B-orthonormal (the basis itself for
        every kind but a block kind such as ``'hybrid'``)."""
        return [basis]

    def recognises(self, basis: Basis) -> bool:
        """Whether ``basis`` is of this kind (:func:`~torchfmap.kinds.kind_of`): its kept
        columns' families are exactly :attr:`column_families`."""
        return self.column_families == frozenset(c.family for c in basis.columns)

    def uses_descriptors(self, w_prior: float) -> bool:
        """Whether :func:`torchfmap.match` solves this kind's map from descriptors: always for
        bases whose columns do not correspond; for corresponding ones unless the pull to the
        identity is infinite (then ``C = I``)."""
        return not (self.needs_landmarks and np.isinf(w_prior))

    def solve_map(self, basis_x: Basis, basis_y: Basis, solve_block, w_prior: float) -> np.ndarray:
        """``C_xy (K_y, K_x)`` in a pair of this kind's bases. ``solve_block(bx, by, prior)``
        solves one pair of B-orthonormal bases from the descriptors (``prior``: the map pulled
        towards, or None). Corresponding bases: ``I`` at ``w_prior = inf``, else solved with
        the identity as prior; others (and ``w_prior = 0``): solved without prior."""
        if not self.needs_landmarks or w_prior == 0:
            return solve_block(basis_x, basis_y, None)
        eye = np.eye(basis_y.k, basis_x.k)
        return eye if np.isinf(w_prior) else solve_block(basis_x, basis_y, eye)

    def embeddings(self, C_xy: np.ndarray, basis_x: Basis, basis_y: Basis):
        """``(E_x (V_x, D), E_y (V_y, D))`` whose nearest neighbours give the point map, or None
        for the classical conversion (:func:`~torchfmap.fmap.fmap_to_p2p` by ``p2p_mode``)."""
        return None

    def to_p2p(
        self,
        C_xy: np.ndarray,
        basis_x: Basis,
        basis_y: Basis,
        mode: str,
        rows: np.ndarray | None = None,
        samplings: tuple[SurfaceSampling, SurfaceSampling] | None = None,
    ) -> np.ndarray:
        """``p2p_yx (V_y,)`` of ``C_xy`` in a pair of this kind's bases: nearest neighbours of
        :meth:`embeddings` when the kind defines them, else
        :func:`~torchfmap.fmap.fmap_to_p2p` by ``mode``. ``rows`` ``(R,)``: only these
        vertices of ``y`` (``(R,)`` returned), e.g. held-out landmarks. ``samplings``: both
        shapes' :class:`~torchfmap.fmap.nearest.SurfaceSampling` ``(x, y)``: every vertex searched
        locally (:func:`~torchfmap.fmap.nearest.local_nearest`)."""
        pair = self.embeddings(C_xy, basis_x, basis_y)
        if pair is None:
            return fmap_to_p2p(C_xy, basis_x, basis_y, mode=mode, rows=rows, samplings=samplings)
        if rows is not None:
            return nearest_neighbor(pair[1][rows], pair[0], precision="single")
        return search_p2p(pair[1], pair[0], samplings)

    def refiner(
        self,
        method: str,
        *,
        k_final: int | None = None,
        mode: str | None = None,
        n_fixed: int = 0,
        times=None,
        zoomout_samples: int | None = None,
        eigenbases: tuple[Basis, Basis] | None = None,
        landmarks: np.ndarray | None = None,
        progress: bool = False,
    ):
        """This kind's refiner for ``method`` (:mod:`~torchfmap.kinds.refiners`): ``'icp'``
        (:class:`~torchfmap.kinds.refiners.ICP`, any kind) or ``'zoomout'`` (the kind's own,
        :meth:`zoomout_refiner`). ``mode``: the point-map rule (default the kind's
        ``p2p_mode``); ``k_final``: the size ZoomOut grows eigenfunctions to (default twice the
        start); ``n_fixed``: the leading seed pairs that are landmarks (never moved); ``times``:
        the heat times of seeded kinds; ``zoomout_samples``: surface samples per shape
        of eigenbasis ZoomOut; ``eigenbases``: given eigenbases to grow within (None: the
        prepared shapes' own); ``landmarks``: the checked ``(L, 2)`` pairs of the match, which
        eigenbasis ZoomOut keeps the map's distances to (seeded kinds hold them as seeds);
        ``progress``: a bar over ZoomOut's sizes where it grows bases.

        Raises:
            ParameterError: an unknown method (:func:`~torchfmap.kinds.refiners.check_refine`).
        """
        mode = self.p2p_mode if mode is None else mode
        if check_refine(method, optional=False) == "icp":
            return ICP(mode)
        return self.zoomout_refiner(
            k_final=k_final, mode=mode, n_fixed=n_fixed, times=times, zoomout_samples=zoomout_samples,
            eigenbases=eigenbases, landmarks=landmarks, progress=progress,
        )  # fmt: skip

    def zoomout_refiner(
        self, *, k_final, mode, n_fixed, times, zoomout_samples, eigenbases, landmarks, progress
    ):
        """The refiner of ``refine='zoomout'`` in this kind (arguments as :meth:`refiner`). By
        default the bases keep their size: :class:`~torchfmap.kinds.refiners.FixedSizeIterations`."""
        return FixedSizeIterations(mode)


@dataclass(frozen=True, kw_only=True)
class SeededKind(BasisKind):
    """A feature-aware kind: functions built at seed vertices (heat kernels, harmonic, ...).

    Subclasses define :meth:`columns_per_seed` and :meth:`functions`; pairs of bases are built
    at corresponding seeds (the landmarks, then farthest-point seeds placed on ``y`` by
    :func:`~torchfmap.seeds.corresponding_seeds`), so column ``i`` is the same function (same
    seed, same scale) on both shapes.
    """

    needs_landmarks: bool = True
    p2p_mode: str = "pullback"

    def columns_per_seed(self, times) -> int:
        """Columns each seed contributes with relative ``times`` (None: the default one time)."""
        raise NotImplementedError

    def functions(self, shape: PreparedShape, seeds: np.ndarray, times=None) -> Basis:
        """The raw (not orthonormalised) functions of ``shape`` at ``seeds`` ``(S,)``; ``times``
        relative diffusion times (default: :func:`seed_time` of ``S``)."""
        raise NotImplementedError

    def seed_bases(
        self, shape_x: PreparedShape, shape_y: PreparedShape, seeds: np.ndarray, times=None
    ) -> tuple[Basis, Basis]:
        """Corresponding bases at seed pairs ``(S, 2)``, orthonormalised together (every
        column; :meth:`pair_bases` cuts them to ``k``)."""
        raw_x = self.functions(shape_x, seeds[:, 0], times)
        return orthonormalize_pair(raw_x, self.functions(shape_y, seeds[:, 1], times))

    def pair_bases(self, shape_x, shape_y, k, landmarks=None, times=None):
        """Bases at ``S = ceil(k / columns per seed)`` corresponding seeds (at least the
        landmarks), orthonormalised together (landmark columns first) and cut to ``k``; if
        dependent columns were dropped, seeds are added until ``k`` columns remain (bounded by
        the vertex count).

        Raises:
            ParameterError: no landmarks, or fewer than ``k`` independent columns.
        """
        if landmarks is None:
            raise ParameterError(
                f"the {self.name} basis is built from corresponding landmarks on both shapes. Fix: pass "
                "landmarks (pairs of vertices), or use basis='laplacian'."
            )
        top = min(shape_x.mesh.n_vertices, shape_y.mesh.n_vertices)
        per_seed = self.columns_per_seed(times)
        n_seeds = max(len(landmarks), -(-k // per_seed))
        for _ in range(MAX_SEED_PASSES):  # bounded: each pass adds seeds for the missing columns
            seeds = corresponding_seeds(
                shape_x.mesh, shape_y.mesh, landmarks, min(n_seeds, top),
                distances=(shape_x.distances, shape_y.distances),
            )  # fmt: skip
            bx, by = self.seed_bases(shape_x, shape_y, seeds, times)
            if bx.k >= k or n_seeds >= top:
                break
            n_seeds += -(-(k - bx.k) // per_seed)
        if bx.k < k:
            raise ParameterError(
                f"only {bx.k} independent {self.name} columns could be built (k={k}). Fix: lower k or "
                "use more seeds."
            )
        return bx.truncated(k), by.truncated(k), seeds

    def shape_basis(self, shape, k, *, seeds=None, times=None):
        """``k`` columns at ``seeds`` then farthest-point seeds (one spare seed; more are added,
        a bounded number of times, if orthonormalisation drops dependent columns).

        Raises:
            ParameterError: fewer than ``k`` independent columns on this mesh.
        """
        per_seed = self.columns_per_seed(times)
        n = shape.mesh.n_vertices
        chosen = seeds_for(shape, k, per_seed, seeds)
        for _ in range(MAX_SEED_PASSES):
            basis = orthonormalize(self.functions(shape, chosen, times))
            if basis.k >= k or len(chosen) >= n:
                break
            chosen = seeds_for(shape, k, per_seed, seeds, len(chosen) + -(-(k - basis.k) // per_seed))
        if basis.k < k:
            raise ParameterError(
                f"the {self.name} basis has only {basis.k} independent functions, {k} asked. Fix: lower k."
            )
        return basis.truncated(k)

    def zoomout_refiner(
        self, *, k_final, mode, n_fixed, times, zoomout_samples, eigenbases, landmarks, progress
    ):
        """:class:`~torchfmap.kinds.refiners.SeedMoves` with this kind's :meth:`functions`: the
        fixed-size iterations, then the seeds of ``y`` moved and the bases rebuilt."""
        return SeedMoves(self.functions, mode, n_fixed, times)
