"""The Laplace-Beltrami eigenbasis (the usual functional-map basis), with a fixed sign convention.

``L φ = λ B φ``, ``φᵀ B φ = I``, ``λ`` ascending. Eigenvectors are defined up to sign; we fix it
so that the B-weighted third moment ``Σ_i B_ii φ_i³`` is positive (ties: the entry of largest
magnitude is positive). Both rules are invariant under rigid motion and vertex permutation.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as ssla

from .._checks import check_symmetric, lumped_diagonal
from ..errors import ParameterError
from ..mesh import Mesh
from ..operators.laplacian import Operators, laplacian
from ..operators.solvers import factorize
from .basis import Basis, Column

#: Below this many vertices the dense generalised eigensolver is used (exact and robust).
DENSE_LIMIT = 1500
#: ARPACK's relative accuracy of the Ritz values (``eigsh(tol=...)``; 0 means machine precision).
ARPACK_TOL = 1e-10


def fix_signs(phi: np.ndarray, mass) -> np.ndarray:
    """Flip columns so the B-weighted third moment is positive (else the largest entry)."""
    m = np.asarray(sp.csr_matrix(mass).sum(axis=1)).ravel()
    cols = np.arange(phi.shape[1])
    skew = m @ (phi * phi * phi)
    idx = np.argmax(np.abs(phi), axis=0)
    fallback = np.sign(phi[idx, cols])
    scale = np.abs(phi[idx, cols])
    sign = np.where(np.abs(skew) > 1e-8 * scale**3 * m.sum(), np.sign(skew), fallback)
    return phi * np.where(sign == 0, 1.0, sign)


def start_vector(n: int) -> np.ndarray:
    """A fixed ARPACK start vector, so that repeated runs give the same basis.

    ARPACK otherwise starts from a random vector: inside a degenerate eigenspace (symmetric
    shapes) the returned eigenvectors, and even which copies of a cluster converge, would differ
    from run to run.
    """
    return np.random.default_rng(0).standard_normal(n)


def eigenpairs(L, B, k: int, sigma: float = -1e-8) -> tuple[np.ndarray, np.ndarray]:
    """First ``k`` generalised eigenpairs: ``(λ (k,), φ (V, k))``, B-orthonormal, signs fixed.

    Dense ``scipy.linalg.eigh`` up to :data:`DENSE_LIMIT` vertices; beyond, ARPACK in
    shift-invert mode (``scipy.sparse.linalg.eigsh``) whose inverse ``(L - σB)⁻¹`` is our
    :func:`~torchfmap.operators.factorize` (a sparse Cholesky where one is installed, in place of
    eigsh's own SuperLU).

    The problem is solved in a scale-free frame: ``B`` is divided by its total (the area), so
    the shift ``sigma`` is relative to a unit-area surface and cost and accuracy do not depend
    on the mesh's units; the eigenpairs are scaled back. Raises :class:`ParameterError` when the
    area is not a finite positive float64 (a mesh so large or small that it overflows).
    """
    n = L.shape[0]
    if not 1 <= k <= n:
        raise ParameterError(f"k must be in [1, {n}] for a mesh of {n} vertices, got k={k}.")
    check_symmetric(L, "Laplacian eigenbases", "laplacian(mesh, kind='cotan') or kind='robust'")
    area = float(B.sum())
    if not np.isfinite(area) or area <= 0 or not np.isfinite(1.0 / area):
        raise ParameterError(
            f"the mass matrix sums to {area!r}: the mesh's scale over- or underflows float64. Fix: "
            "rescale it first, e.g. mesh.normalized() or mesh.scaled(alpha)."
        )
    lam, phi = _unit_area_eigenpairs(L, B / area, k, sigma)
    return lam / area, phi / np.sqrt(area)


def _unit_area_eigenpairs(L, B, k: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    n = L.shape[0]
    if n <= DENSE_LIMIT or k >= n - 1:
        lam, phi = sla.eigh(L.toarray(), B.toarray(), subset_by_index=(0, k - 1))
    else:
        L, B = sp.csc_matrix(L), sp.csc_matrix(B)
        fac = factorize(L - sigma * B, spd=True)  # CHOLMOD / cholespy where installed
        # ARPACK's restarts cost ~ V ncv^2: a Lanczos basis of 1.5k (scipy's default is 2k + 1)
        # needs as many solves and restarts more cheaply
        ncv = min(n, max(k + k // 2 + 1, k + 20))
        d = lumped_diagonal(B)
        if d is not None:
            # lumped mass: the standard problem D^-1/2 L D^-1/2 ψ = λ ψ, φ = D^-1/2 ψ, spares
            # ARPACK the B inner products (same eigenpairs, residuals at ARPACK_TOL)
            s = np.sqrt(d)
            A = sp.csc_matrix(sp.diags(1.0 / s) @ L @ sp.diags(1.0 / s))
            op_inv = ssla.LinearOperator((n, n), matvec=lambda x: s * fac.solve(s * x), dtype=np.float64)
            lam, psi = ssla.eigsh(
                A, k=k, sigma=sigma, which="LM", OPinv=op_inv, v0=start_vector(n), ncv=ncv, tol=ARPACK_TOL
            )
            phi = psi / s[:, None]
        else:
            op_inv = ssla.LinearOperator((n, n), matvec=fac.solve, dtype=np.float64)
            lam, phi = ssla.eigsh(
                L,
                k=k,
                M=B,
                sigma=sigma,
                which="LM",
                OPinv=op_inv,
                v0=start_vector(n),
                ncv=ncv,
                tol=ARPACK_TOL,
            )
        order = np.argsort(lam)
        lam, phi = lam[order], phi[:, order]
    lam = np.where(lam > -1e-10, np.maximum(lam, 0.0), lam)  # round-off below zero -> 0
    return lam, fix_signs(phi, B)


def laplacian_eigenbasis(mesh: Mesh, k: int, *, operators: Operators | None = None) -> Basis:
    """The first ``k`` Laplace-Beltrami eigenfunctions as a B-orthonormal :class:`Basis`.

    The eigenvalues are kept in ``basis.eigenvalues`` (``(k,)``, ascending).
    """
    L, B = operators if operators is not None else laplacian(mesh)
    lam, phi = eigenpairs(L, B, k)
    prov = [Column("laplacian", index=i) for i in range(k)]
    return Basis(phi, B, prov, orthonormal=True, stiffness=L, eigenvalues=lam)
