"""The Laplacian eigenbasis kind: the first ``k`` Laplace-Beltrami eigenfunctions of each shape."""

from __future__ import annotations

from dataclasses import dataclass

from ..bases.prepared import with_eigenpairs
from ..errors import ParameterError
from ..fmap.defaults import W_LAP_SMOOTH
from .base import BasisKind
from .refiners import ZoomOut


@dataclass(frozen=True, kw_only=True)
class EigenKind(BasisKind):
    """Eigenbases: no landmarks, ``'orthogonal'`` point maps, grown by ZoomOut."""

    def n_eigen(self, k: int) -> int:
        return k

    def pair_bases(self, shape_x, shape_y, k, landmarks=None, times=None):
        """The first ``k`` eigenfunctions of each shape (ParameterError if a shape holds fewer)."""
        if shape_x.n_eigen < k or shape_y.n_eigen < k:
            raise ParameterError("the eigenbasis needs eigenpairs. Fix: prepare_shape(mesh, n_eigen >= k).")
        return shape_x.eigenbasis.truncated(k), shape_y.eigenbasis.truncated(k), None

    def shape_basis(self, shape, k, *, seeds=None, times=None):
        """The first ``k`` eigenfunctions (computed on ``shape`` if it holds fewer); ``seeds`` and
        ``times`` are not used."""
        return with_eigenpairs(shape, k).eigenbasis.truncated(k)

    def zoomout_refiner(
        self, *, k_final, mode, n_fixed, times, zoomout_samples, eigenbases, landmarks, progress
    ):
        """:class:`~torchfmap.kinds.refiners.ZoomOut` to ``k_final`` (arguments as :meth:`refiner`)."""
        return ZoomOut(k_final, mode, zoomout_samples, eigenbases, landmarks, progress=progress)


LAPLACIAN = EigenKind(
    name="laplacian",
    summary="first k Laplace-Beltrami eigenfunctions (no landmarks needed)",
    needs_landmarks=False,
    w_lap=W_LAP_SMOOTH,
    p2p_mode="orthogonal",
    grows=True,
    column_families=frozenset({"laplacian"}),
)
