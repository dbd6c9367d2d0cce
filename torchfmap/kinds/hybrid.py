"""The hybrid kind (after Bastian et al., CVPR 2024): eigenfunctions, then heat kernels at
corresponding seeds, each block B-orthonormal; the map is block-diagonal, ``diag(C_e, I)``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..bases.basis import Basis
from ..bases.prepared import PreparedShape, with_eigenpairs
from ..bases.stack import concatenate
from ..errors import ParameterError
from ..fmap.convert import check_p2p
from ..fmap.defaults import W_LAP_SMOOTH, W_ORIENT, zoomout_step
from ..fmap.nearest import SurfaceSampling
from ..fmap.refine import EnergyGuard, Refined, Samples, SpectralStep, zoomout_iterations
from .base import BasisKind
from .diffusion import DIFFUSION
from .refiners import grown_eigenbases, pair_samplings


def join_blocks(eigen: Basis, feature: Basis) -> Basis:
    """One basis ``(V, k_e + k_f)``: the eigen block's columns, then the feature block's
    (``orthonormal=False``)."""
    return concatenate([eigen, feature])


def split_blocks(basis: Basis) -> tuple[Basis, Basis]:
    """``(eigen block, feature block)``: the leading eigenfunctions, the rest (ParameterError if
    either is empty)."""
    families = basis.families()
    eigen = families == "laplacian"
    k_e = int(np.argmax(~eigen)) if (~eigen).any() else len(families)
    if k_e == 0 or k_e == len(families) or eigen[k_e:].any():
        raise ParameterError(
            "a hybrid basis is eigenfunctions followed by feature-aware columns. Fix: build it with "
            "KINDS['hybrid'].pair_bases or shape_basis."
        )
    cols = basis.columns

    def block(sl: slice) -> Basis:
        return Basis(basis.values[:, sl], basis.mass, cols[sl], True, basis.stiffness)

    return block(slice(0, k_e)), block(slice(k_e, None))


@dataclass(frozen=True, kw_only=True)
class HybridKind(BasisKind):
    """Eigen block + feature-aware block: ``feature_share`` of the ``k`` columns (at least one of
    each) in the feature block, weighted ``feature_weight`` ``w`` in point maps."""

    feature_share: float = 0.3
    feature_weight: float = 1.0

    def blocks(self, k: int) -> tuple[int, int]:
        """``(k_e, k_f)`` of a basis of ``k`` columns (ParameterError if ``k < 2``)."""
        if k < 2:
            raise ParameterError(f"a hybrid basis needs k >= 2 (one column per block), got {k}.")
        k_f = min(max(1, round(self.feature_share * k)), k - 1)
        return k - k_f, k_f

    def n_eigen(self, k: int) -> int:
        return self.blocks(k)[0]

    def pair_bases(self, shape_x, shape_y, k, landmarks=None, times=None):
        """``k_e`` eigenfunctions and ``k_f`` diffusion columns at corresponding seeds, joined.
        Raises ParameterError: no landmarks, or ``k < 2``."""
        k_e, k_f = self.blocks(k)
        if landmarks is None:
            raise ParameterError(
                "the hybrid basis builds its feature block at corresponding landmarks. Fix: pass "
                "landmarks (pairs of vertices), or use basis='laplacian'."
            )
        fx, fy, seeds = DIFFUSION.pair_bases(shape_x, shape_y, k_f, landmarks, times)
        ex, ey = (with_eigenpairs(s, k_e).eigenbasis.truncated(k_e) for s in (shape_x, shape_y))
        return join_blocks(ex, fx), join_blocks(ey, fy), seeds

    def shape_basis(self, shape, k, *, seeds=None, times=None):
        """``k_e`` eigenfunctions then ``k_f`` heat kernels at ``seeds`` and farthest points."""
        k_e, k_f = self.blocks(k)
        eigen = with_eigenpairs(shape, k_e).eigenbasis.truncated(k_e)
        return join_blocks(eigen, DIFFUSION.shape_basis(shape, k_f, seeds=seeds, times=times))

    def block_bases(self, basis: Basis) -> list[Basis]:
        return list(split_blocks(basis))

    def recognises(self, basis: Basis) -> bool:
        """Eigenfunctions and heat kernels, not orthonormal together (else ``eigen_diffusion``)."""
        return super().recognises(basis) and not basis.orthonormal

    def uses_descriptors(self, w_prior: float) -> bool:
        return True  # the eigen block is always solved from descriptors

    def solve_map(self, basis_x, basis_y, solve_block, w_prior: float) -> np.ndarray:
        """``diag(C_e, I)``: ``C_e = solve_block(eigen_x, eigen_y, None)``."""
        (ex, fx), (ey, fy) = split_blocks(basis_x), split_blocks(basis_y)
        C = np.zeros((basis_y.k, basis_x.k))
        C[: ey.k, : ex.k] = solve_block(ex, ey, None)
        C[ey.k :, ex.k :] = np.eye(fy.k, fx.k)
        return C

    def embeddings(self, C_xy, basis_x, basis_y) -> tuple[np.ndarray, np.ndarray]:
        """``(E_x (V_x, K_y), E_y (V_y, K_y))``: ``[Φ_e C_eᵀ, w Φ_f C_fᵀ]`` and ``[Φ_e, w Φ_f]``
        (off-diagonal blocks of ``C_xy`` unused)."""
        (ex, fx), (ey, fy) = split_blocks(basis_x), split_blocks(basis_y)
        side_y, side_x = HybridStep(ex, ey, fx, fy, self.feature_weight).embed(C_xy, ex.k, None)
        return side_x, side_y

    def zoomout_refiner(
        self, *, k_final, mode, n_fixed, times, zoomout_samples, eigenbases, landmarks, progress
    ):
        """:class:`HybridZoomOut` to ``k_final`` columns in the eigen blocks of ``eigenbases``."""
        if eigenbases is not None:
            eigenbases = tuple(split_blocks(b)[0] for b in eigenbases)
        return HybridZoomOut(self, k_final, eigenbases, progress)


@dataclass(frozen=True)
class HybridZoomOut:
    """``refine='zoomout'`` in hybrid bases: :func:`hybrid_zoomout` to ``k_final`` (default: twice
    the start)."""

    kind: HybridKind
    k_final: int | None = None
    eigenbases: tuple[Basis, Basis] | None = None
    progress: bool = False

    def __call__(self, C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds=None) -> Refined:
        k_final = self.k_final if self.k_final is not None else 2 * basis_x.k
        C, p2p, bx, by = hybrid_zoomout(
            p2p_yx, shape_x, shape_y, basis_x, basis_y, self.kind, k_final, eigenbases=self.eigenbases,
            samplings=pair_samplings(shape_x, shape_y), progress=self.progress,
        )  # fmt: skip
        return Refined(C, p2p, bx, by, seeds)


def hybrid_zoomout(
    p2p_yx: np.ndarray,
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    basis_x: Basis,
    basis_y: Basis,
    kind: HybridKind,
    k_final: int,
    step: int | None = None,
    *,
    guard: bool = True,
    eigenbases: tuple[Basis, Basis] | None = None,
    samplings: tuple[SurfaceSampling, SurfaceSampling] | None = None,
    progress: bool = False,
) -> tuple[np.ndarray, np.ndarray, Basis, Basis]:
    """ZoomOut of a hybrid pair: the eigen block grows to ``k_final - k_f`` by ``step`` in
    ``eigenbases`` (None: the shapes' own), the feature block keeps ``k_f``; both are refitted at
    each size. ``guard`` scores the eigen block; ``samplings`` as in
    :func:`~torchfmap.fmap.refine.zoomout_iterations`.

    Returns ``(C_xy, p2p_yx, basis_x, basis_y)`` in the grown bases.

    Raises:
        ParameterError: ``k_final`` not above the feature block, or given ``eigenbases`` with
            too few eigenfunctions.
    """
    (ex, fx), (_, fy) = split_blocks(basis_x), split_blocks(basis_y)
    k_e, k_f = ex.k, fx.k
    k_end = k_final - k_f
    if k_end < k_e:
        raise ParameterError(f"k_final={k_final} leaves fewer eigenfunctions than the start ({k_e}).")
    eig_x, eig_y = grown_eigenbases(shape_x, shape_y, eigenbases, k_end)
    step = zoomout_step(k_e) if step is None else step
    if step < 1:
        raise ParameterError(f"step must be >= 1, got {step}.")
    p2p = check_p2p(p2p_yx, basis_y.n_vertices, basis_x.n_vertices, "p2p_yx")
    sizes = list(range(k_e, k_end, step)) + [k_end]
    best = EnergyGuard(eig_x, eig_y, sizes, enabled=guard)
    samples = Samples.of_pair(samplings)
    step = HybridStep(eig_x, eig_y, fx, fy, kind.feature_weight)
    C, p2p = zoomout_iterations(step, sizes, p2p_yx=p2p, guard=best, samples=samples, progress=progress)
    bx, by = join_blocks(eig_x.truncated(k_end), fx), join_blocks(eig_y.truncated(k_end), fy)
    return C, p2p, bx, by


@dataclass(frozen=True)
class HybridStep:
    """ZoomOut's step in hybrid bases: ``C = diag(C_e (size, size), C_f (k_f, k_f))``."""

    eig_x: Basis
    eig_y: Basis
    feat_x: Basis
    feat_y: Basis
    weight: float

    def fit(self, p2p_yx, size, rows):
        k_f = self.feat_x.k
        C = np.zeros((size + k_f, size + k_f))
        eigen = (self.eig_x, self.eig_y, slice(0, size), size)
        for bx, by, sl, k in (eigen, (self.feat_x, self.feat_y, slice(size, None), k_f)):
            C[sl, sl] = SpectralStep(bx, by).fit(p2p_yx, k, rows)
        return C

    def embed(self, C, size, rows):
        k_f = self.feat_x.k
        size = len(C) - k_f
        ex, ey, fx, fy = (b.values for b in (self.eig_x, self.eig_y, self.feat_x, self.feat_y))
        if rows is not None:
            ex, fx, ey, fy = ex[rows.x], fx[rows.x], ey[rows.y], fy[rows.y]
        C_e, C_f, w = C[:size, :size], C[size:, size:], self.weight
        side_x = np.hstack([ex[:, :size] @ C_e.T, w * (fx @ C_f.T)])
        return np.hstack([ey[:, :size], w * fy]), side_x


HYBRID = HybridKind(
    name="hybrid",
    summary="eigenfunctions + heat kernels at corresponding seeds, block-diagonal map",
    needs_landmarks=True,
    w_lap=W_LAP_SMOOTH,
    w_orient=W_ORIENT,
    p2p_mode="orthogonal",
    grows=True,
    column_families=frozenset({"laplacian", "diffusion"}),
    learned=False,  # the torch solver is not block-diagonal
)
