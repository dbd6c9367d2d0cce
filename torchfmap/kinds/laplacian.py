"""The Laplacian eigenbasis kind: the first ``k`` Laplace-Beltrami eigenfunctions of each shape."""

from __future__ import annotations

from dataclasses import dataclass

from ..bases.prepared import with_eigenpairs
from ..errors import ParameterError
from ..fmap.defaults import W_LAP_SMOOTH
from ..fmap.refine import Refined, zoomout
from ..seeds import farthest_point_sampling
from .base import BasisKind


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

    def zoomout_refine(
        self, C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, *, k_final, mode, seeds, n_fixed, times,
        zoomout_samples,
    ) -> Refined:  # fmt: skip
        """ZoomOut in the prepared eigenbases, grown from ``C_xy``'s size to ``k_final``
        (:func:`~torchfmap.fmap.zoomout`; the shapes need ``k_final`` eigenpairs), on
        ``zoomout_samples`` farthest-point samples per shape if given."""
        samples = None
        if zoomout_samples is not None:
            samples = tuple(
                farthest_point_sampling(m, min(zoomout_samples, m.n_vertices), metric="euclidean")
                for m in (shape_x.mesh, shape_y.mesh)
            )
        full_x, full_y = shape_x.eigenbasis, shape_y.eigenbasis
        C, p2p = zoomout(C_xy, full_x, full_y, k_final, mode=mode, subsample=samples)
        return Refined(C, p2p, full_x.truncated(k_final), full_y.truncated(k_final), None)


LAPLACIAN = EigenKind(
    name="laplacian",
    summary="first k Laplace-Beltrami eigenfunctions (no landmarks needed)",
    needs_landmarks=False,
    w_lap=W_LAP_SMOOTH,
    p2p_mode="orthogonal",
    grows=True,
    column_families=frozenset({"laplacian"}),
)
