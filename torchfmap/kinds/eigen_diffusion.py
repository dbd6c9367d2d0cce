"""The eigen + diffusion kind: the first ``k // 2`` eigenfunctions, then heat kernels at each
shape's own farthest-point seeds (columns do not correspond: solved from descriptors)."""

from __future__ import annotations

from dataclasses import dataclass

from ..bases.orthonormalize import orthonormalize
from ..bases.prepared import with_eigenpairs
from ..bases.stack import concatenate
from ..errors import ParameterError
from ..fmap.defaults import W_LAP_KERNELS
from .base import BasisKind, seeds_for
from .diffusion import DIFFUSION


@dataclass(frozen=True, kw_only=True)
class EigenDiffusionKind(BasisKind):
    """``k // 2`` eigenfunctions and ``k - k // 2`` diffusion columns, orthonormalised together."""

    def n_eigen(self, k: int) -> int:
        return k // 2

    def shape_basis(self, shape, k, *, seeds=None, times=None):
        """The eigenfunctions, then kernels at ``seeds`` and farthest-point seeds, orthonormalised
        and cut to ``k`` (ParameterError if fewer than ``k`` independent columns)."""
        eig = with_eigenpairs(shape, k // 2).eigenbasis
        chosen = seeds_for(shape, k - k // 2, DIFFUSION.columns_per_seed(times), seeds)
        parts = ([eig.truncated(k // 2)] if k // 2 else []) + [DIFFUSION.functions(shape, chosen, times)]
        basis = orthonormalize(concatenate(parts))
        if basis.k < k:
            raise ParameterError(
                f"the {self.name} basis has only {basis.k} independent functions, {k} asked. Fix: lower k."
            )
        return basis.truncated(k)

    def pair_bases(self, shape_x, shape_y, k, landmarks=None, times=None):
        """Each shape's :meth:`shape_basis` (landmarks seeded first); no seed pairs returned."""
        lx, ly = (None, None) if landmarks is None else (landmarks[:, 0], landmarks[:, 1])
        bx = self.shape_basis(shape_x, k, seeds=lx, times=times)
        return bx, self.shape_basis(shape_y, k, seeds=ly, times=times), None


EIGEN_DIFFUSION = EigenDiffusionKind(
    name="eigen_diffusion",
    summary="k/2 eigenfunctions + heat kernels at each shape's farthest points",
    needs_landmarks=False,
    w_lap=W_LAP_KERNELS,
    p2p_mode="pullback",
    column_families=frozenset({"laplacian", "diffusion"}),
    w_orient=1e-2,  # strong orientation (minimised by C = 0) collapses non-corresponding maps
)
