"""What every basis kind is: the settings the pipeline reads, how it builds its functions and how it
refines a map (docs/architecture.md, "Basis kinds: one registry")."""

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
    """Relative heat time ``1 / (4 n)`` whose kernel width matches the covering radius of ``n_seeds``
    seeds on a unit-area surface."""
    return 1.0 / (4.0 * n_seeds)


def relative_times(times, n_seeds: int) -> tuple[float, ...]:
    """``times`` as a sorted tuple, or ``(seed_time(n_seeds),)``. Raises ParameterError for an
    empty, non-finite or non-positive time list."""
    if times is None:
        return (seed_time(n_seeds),)
    return tuple(sorted(check_times(times, fix="e.g. times=[0.01]").tolist()))


def seeds_for(shape: PreparedShape, n_columns: int, per_seed: int, seeds=None, n_seeds: int | None = None):
    """``(S,)`` vertices: ``seeds`` then farthest-point seeds, ``n_seeds`` in all (default: enough
    for ``n_columns`` columns of ``per_seed`` plus one spare), at most the vertex count."""
    given = np.zeros(0, dtype=np.int64) if seeds is None else np.atleast_1d(np.asarray(seeds))
    if n_seeds is None:
        n_seeds = -(-n_columns // per_seed) + 1
    n_seeds = min(max(len(given), n_seeds), shape.mesh.n_vertices)
    return farthest_point_sampling(shape.mesh, n_seeds, landmarks=given if len(given) else None)


@dataclass(frozen=True, kw_only=True)
class BasisKind:
    """A kind of basis: ``needs_landmarks`` (bases at corresponding landmarks, map pulled to ``I``),
    ``w_lap`` / ``w_orient`` (solve weights), ``p2p_mode``, ``column_families`` (recognises a
    basis), ``learned`` (the torch layers solve in it)."""

    name: str
    summary: str
    needs_landmarks: bool
    w_lap: float
    p2p_mode: str
    column_families: frozenset[str] = frozenset()
    w_orient: float = W_ORIENT
    learned: bool = True
    #: whether ZoomOut grows the kind's eigenfunctions (the shapes then need ``k_final`` eigenpairs)
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
        """The two bases of exactly ``k`` columns :func:`~torchfmap.match` solves in (B-orthonormal
        per :meth:`block_bases`), and their seed pairs ``(S, 2)`` (None if none correspond)."""
        raise NotImplementedError

    def shape_basis(self, shape: PreparedShape, k: int, *, seeds=None, times=None) -> Basis:
        """One shape's B-orthonormal basis of exactly ``k`` columns; ``seeds`` first, farthest-point
        seeds fill the rest."""
        raise NotImplementedError

    def block_bases(self, basis: Basis) -> list[Basis]:
        """The B-orthonormal blocks of a basis of this kind (the basis itself but for ``'hybrid'``)."""
        return [basis]

    def recognises(self, basis: Basis) -> bool:
        """Whether ``basis``'s kept columns' families are exactly :attr:`column_families`."""
        return self.column_families == frozenset(c.family for c in basis.columns)

    def uses_descriptors(self, w_prior: float) -> bool:
        """Whether :func:`torchfmap.match` solves this kind's map from descriptors (not for
        corresponding bases at ``w_prior = inf``: ``C = I``)."""
        return not (self.needs_landmarks and np.isinf(w_prior))

    def solve_map(self, basis_x: Basis, basis_y: Basis, solve_block, w_prior: float) -> np.ndarray:
        """``C_xy (K_y, K_x)`` by ``solve_block(bx, by, prior)`` (``prior``: a map or None).
        Corresponding bases: ``I`` at ``w_prior = inf``, else the identity as prior (none at 0)."""
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
        """``p2p_yx (V_y,)`` of ``C_xy``: by :meth:`embeddings` if defined, else
        :func:`~torchfmap.fmap.fmap_to_p2p` by ``mode``; ``rows``/``samplings`` as there."""
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
        """This kind's refiner for ``method``: ``'icp'`` (:class:`~torchfmap.kinds.refiners.ICP`)
        or ``'zoomout'`` (:meth:`zoomout_refiner`); ``mode`` defaults to ``p2p_mode``, ``k_final``
        to twice the start; ``n_fixed``: seed pairs never moved; ``eigenbases``: to grow within;
        ``landmarks``: ``(L, 2)``. Raises ParameterError for an unknown method."""
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
        """``refine='zoomout'``'s refiner (arguments as :meth:`refiner`); by default
        :class:`~torchfmap.kinds.refiners.FixedSizeIterations`."""
        return FixedSizeIterations(mode)


@dataclass(frozen=True, kw_only=True)
class SeededKind(BasisKind):
    """A feature-aware kind: :meth:`functions` at seed vertices, :meth:`columns_per_seed` each;
    pairs are built at corresponding seeds, so column ``i`` corresponds on both shapes."""

    needs_landmarks: bool = True
    p2p_mode: str = "pullback"

    def columns_per_seed(self, times) -> int:
        """Columns each seed contributes with relative ``times`` (None: the default one time)."""
        raise NotImplementedError

    def functions(self, shape: PreparedShape, seeds: np.ndarray, times=None) -> Basis:
        """The raw functions of ``shape`` at ``seeds (S,)`` (``times``: default :func:`seed_time`)."""
        raise NotImplementedError

    def seed_bases(
        self, shape_x: PreparedShape, shape_y: PreparedShape, seeds: np.ndarray, times=None
    ) -> tuple[Basis, Basis]:
        """Corresponding bases at seed pairs ``(S, 2)``, orthonormalised together (not cut to ``k``)."""
        raw_x = self.functions(shape_x, seeds[:, 0], times)
        return orthonormalize_pair(raw_x, self.functions(shape_y, seeds[:, 1], times))

    def pair_bases(self, shape_x, shape_y, k, landmarks=None, times=None):
        """Bases at ``ceil(k / columns per seed)`` corresponding seeds (at least the landmarks),
        orthonormalised together and cut to ``k`` (seeds added while columns are missing). Raises
        ParameterError: no landmarks, or fewer than ``k`` independent columns."""
        if landmarks is None:
            raise ParameterError(
                f"the {self.name} basis is built from corresponding landmarks on both shapes. Fix: pass "
                "landmarks (pairs of vertices), or use basis='laplacian'."
            )
        top = min(shape_x.mesh.n_vertices, shape_y.mesh.n_vertices)
        per_seed = self.columns_per_seed(times)
        n_seeds = max(len(landmarks), -(-k // per_seed))
        for _ in range(MAX_SEED_PASSES):
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
        """``k`` columns at ``seeds`` then farthest-point seeds. Raises ParameterError if fewer
        than ``k`` independent columns can be built."""
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
        """:class:`~torchfmap.kinds.refiners.SeedMoves` with this kind's :meth:`functions`."""
        return SeedMoves(self.functions, mode, n_fixed, times)
