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
    """Eigenbases need no landmarks; their maps of near-isometries are near-orthogonal, so the
    point map is ``'orthogonal'`` and ZoomOut grows them (``grows``)."""

    def n_eigen(self, k: int) -> int:
        return k

    def pair_bases(self, shape_x, shape_y, k, landmarks=None, times=None):
        """The first ``k`` eigenfunctions of each prepared shape (no seeds).

        Raises:
            ParameterError: a shape prepared with fewer than ``k`` eigenpairs.
        """
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
        """:class:`~torchfmap.kinds.refiners.ZoomOut`: the eigenbases grown from the map's size to
        ``k_final`` (the shapes' own, or the given ``eigenbases``), on ``zoomout_samples``
        surface samples per shape if given (by default on dense pairs), keeping the distances
        to ``landmarks``."""
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
