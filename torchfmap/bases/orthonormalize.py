"""B-orthonormalisation dropping numerically dependent columns, in the given order: ``mgs``
(Gram-Schmidt twice) or ``cholqr`` (Cholesky-QR2; faster, resolves dependence only to 1e-7)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from .._util.checks import lumped_diagonal
from ..errors import ParameterError
from .basis import Basis, Column

SCHEMES = ("mgs", "cholqr")
#: Columns :func:`mgs` projects out of the earlier kept columns together, by matrix products.
MGS_PANEL = 32


class _Mass:
    """``B @ x`` for ``(V,)`` or ``(V, n)`` arrays, elementwise for a diagonal (lumped) mass."""

    def __init__(self, mass) -> None:
        diagonal = lumped_diagonal(mass)
        self.diagonal = None if diagonal is None else np.asarray(diagonal, dtype=np.float64)
        if diagonal is None:
            self.matrix = sp.csr_matrix(mass, dtype=np.float64)

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        if self.diagonal is None:
            return self.matrix @ x
        return self.diagonal * x if x.ndim == 1 else self.diagonal[:, None] * x


def mgs(F: np.ndarray, mass, tol: float = 1e-8) -> tuple[np.ndarray, np.ndarray]:
    """``(Q (V, R), kept (R,))``: B-orthonormal columns of ``F (V, K)`` (``mass`` ``(V, V)`` SPD or
    ``(V,)``) and the kept inputs, by Gram-Schmidt twice in panels of :data:`MGS_PANEL`. A column
    is dropped when its remainder's B-norm is below ``tol`` times its own."""
    B = _Mass(mass)
    F = np.asarray(F, dtype=np.float64)
    V, K = F.shape
    Q = np.empty((V, K), order="F")  # columns contiguous: the panel's column steps are BLAS-1
    kept: list[int] = []
    r = 0
    for p0 in range(0, K, MGS_PANEL):
        P = np.array(F[:, p0 : p0 + MGS_PANEL], order="F")
        norm0 = np.sqrt(np.maximum(np.einsum("ij,ij->j", P, B @ P), 0.0))
        for _ in range(2 if r else 0):
            P -= Q[:, :r] @ (Q[:, :r].T @ (B @ P))
        r0 = r
        for j in range(P.shape[1]):
            if norm0[j] == 0.0 or not np.isfinite(norm0[j]):
                continue
            v = P[:, j]
            for _ in range(2 if r > r0 else 0):
                v -= Q[:, r0:r] @ (Q[:, r0:r].T @ (B @ v))
            Bv = B @ v
            norm = np.sqrt(max(v @ Bv, 0.0))
            if norm <= tol * norm0[j]:
                continue
            Q[:, r] = v / norm
            kept.append(p0 + j)
            r += 1
        if r0 and r > r0:
            _polish(Q, B, r0, r)
    Q = Q[:, :r]
    return np.ascontiguousarray(Q), np.asarray(kept, dtype=np.int64)


def _polish(Q: np.ndarray, B, r0: int, r: int) -> None:
    """Columns ``r0:r`` of ``Q`` projected once more out of columns ``:r0`` and re-orthonormalised
    by one Cholesky-QR step, in place."""
    panel = Q[:, r0:r]
    panel -= Q[:, :r0] @ (Q[:, :r0].T @ (B @ panel))
    gram = panel.T @ (B @ panel)
    upper = np.linalg.cholesky(0.5 * (gram + gram.T)).T
    Q[:, r0:r] = sla.solve_triangular(upper, panel.T, trans="T", lower=False).T


def cholqr(F: np.ndarray, mass, tol: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
    """Cholesky-QR2 in the B inner product with in-order dropping; returns like :func:`mgs`."""
    B = _Mass(mass)
    F = np.asarray(F, dtype=np.float64)
    norms = np.sqrt(np.maximum(np.einsum("ij,ij->j", F, B @ F), 0.0))
    valid = np.flatnonzero((norms > 0) & np.isfinite(norms))
    Fs = F[:, valid] / norms[valid]  # unit B-norm columns: tolerance is relative
    G = Fs.T @ (B @ Fs)
    K = G.shape[0]
    R = np.zeros((K, K))
    keep: list[int] = []
    for j in range(K):  # Cholesky of the Gram matrix, skipping dependent columns
        rj = R[keep, j] = np.linalg.solve(R[np.ix_(keep, keep)].T, G[keep, j]) if keep else np.zeros(0)
        pivot = G[j, j] - rj @ rj
        if pivot <= tol**2:
            continue
        R[j, j] = np.sqrt(pivot)
        keep.append(j)
    Rk = R[np.ix_(keep, keep)]
    Q = np.linalg.solve(Rk.T, Fs[:, keep].T).T  # Q = F_keep R^{-1}
    for _ in range(2):  # CholQR passes restore orthogonality to machine precision
        G2 = Q.T @ (B @ Q)
        C = np.linalg.cholesky(0.5 * (G2 + G2.T))
        Q = np.linalg.solve(C, Q.T).T
    return Q, valid[np.asarray(keep, dtype=np.int64)]


#: Default drop tolerances; the Gram matrix of ``cholqr`` cannot resolve less than ~1e-7.
DEFAULT_TOL = {"mgs": 1e-8, "cholqr": 1e-7}
CHOLQR_MIN_TOL = 1e-7


def orthonormalize(basis: Basis, scheme: str = "mgs", tol: float | None = None) -> Basis:
    """A B-orthonormal :class:`Basis` spanning ``basis``'s kept columns (in order), dependent ones
    recorded as dropped; ``scheme``: ``'mgs'`` or ``'cholqr'``; ``tol``: relative drop tolerance
    (default :data:`DEFAULT_TOL`)."""
    tol = _check(scheme, tol)
    Q, kept = (mgs if scheme == "mgs" else cholqr)(basis.values, basis.mass, tol)
    return _with_kept(basis, Q, kept)


def _check(scheme: str, tol: float | None) -> float:
    if scheme not in SCHEMES:
        raise ParameterError(f"unknown orthonormalisation scheme {scheme!r}. Fix: use one of {SCHEMES}.")
    tol = DEFAULT_TOL[scheme] if tol is None else float(tol)
    if not 0 < tol < 1:
        raise ParameterError(f"tol must be in (0, 1), got {tol}.")
    if scheme == "cholqr" and tol < CHOLQR_MIN_TOL:
        raise ParameterError(
            f"cholqr resolves linear dependence only down to {CHOLQR_MIN_TOL:g} (its Gram matrix "
            f"squares the condition number), got tol={tol:g}. Fix: use tol >= {CHOLQR_MIN_TOL:g} or "
            "scheme='mgs'."
        )
    return tol


def _with_kept(basis: Basis, Q: np.ndarray, kept: np.ndarray) -> Basis:
    """``Q`` as a Basis whose provenance keeps the inputs ``kept`` (indices into the kept columns)."""
    kept_set = set(np.asarray(kept).tolist())
    prov: list[Column] = []
    col = 0
    for c in basis.provenance:
        if c.kept:
            prov.append(replace(c, kept=col in kept_set))
            col += 1
        else:
            prov.append(c)
    return type(basis)(Q, basis.mass, prov, orthonormal=True, stiffness=basis.stiffness)


def orthonormalize_pair(
    basis_x: Basis, basis_y: Basis, scheme: str = "mgs", tol: float | None = None
) -> tuple[Basis, Basis]:
    """Orthonormalise two bases of corresponding columns, keeping a column only where it is
    independent on both shapes: ``(Φ_x (V_x, R), Φ_y (V_y, R))``, identical provenance."""
    tol = _check(scheme, tol)
    if basis_x.k != basis_y.k:
        raise ParameterError(
            f"the bases have {basis_x.k} and {basis_y.k} columns; corresponding bases need the same "
            "columns. Fix: build both from the same seeds (landmark pairs) and parameters."
        )
    fn = mgs if scheme == "mgs" else cholqr
    active = np.arange(basis_x.k)
    while True:
        Qx, kx = fn(basis_x.values[:, active], basis_x.mass, tol)
        Qy, ky = fn(basis_y.values[:, active], basis_y.mass, tol)
        common = np.intersect1d(kx, ky)
        if len(common) == len(active):
            return _with_kept(basis_x, Qx, active), _with_kept(basis_y, Qy, active)
        active = active[common]  # fewer inputs: the remaining ones can only become more independent
