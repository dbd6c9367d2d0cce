"""The Laplace-Beltrami eigenbasis (:func:`~torchfmap.operators.eigen.eigenpairs` of ``L φ = λ B φ``)."""

from __future__ import annotations

from ..mesh import Mesh
from ..operators.eigen import eigenpairs
from ..operators.laplacian import Operators, laplacian
from .basis import Basis, Column


def laplacian_eigenbasis(mesh: Mesh, k: int, *, operators: Operators | None = None) -> Basis:
    """The first ``k`` Laplace-Beltrami eigenfunctions as a B-orthonormal :class:`Basis`, with
    ``eigenvalues`` ``(k,)`` ascending. Raises what :func:`~torchfmap.operators.eigen.eigenpairs`
    raises."""
    L, B = operators if operators is not None else laplacian(mesh)
    lam, phi = eigenpairs(L, B, k)
    prov = [Column("laplacian", index=i) for i in range(k)]
    return Basis(phi, B, prov, orthonormal=True, stiffness=L, eigenvalues=lam)
