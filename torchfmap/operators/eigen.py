"""Generalised eigensolvers for ``L φ = λ B φ``: B-orthonormal pairs, ``λ`` ascending, each sign fixed
so that ``Σ_i B_ii φ_i³ > 0`` (ties: the largest-magnitude entry positive). Dense ``eigh`` on small
meshes, else ARPACK or block Lanczos (:func:`block_lanczos`) on a shift-inverted factorisation."""

from __future__ import annotations

import warnings

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as ssla

from .._util.checks import check_memory, check_symmetric, lumped_diagonal
from .._util.threads import blas_threads
from ..errors import ConvergenceError, CostWarning, ParameterError
from .solvers import factorize

#: Up to this many vertices the dense generalised eigensolver is used.
DENSE_LIMIT = 1500
#: Above this many eigenpairs of a mesh beyond :data:`DENSE_LIMIT` vertices, :func:`eigenpairs` warns.
MANY_EIGENPAIRS = 300
#: ARPACK's relative accuracy of the Ritz values (``eigsh(tol=...)``).
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
    """A fixed ``(n,)`` ARPACK start vector, so that repeated runs give the same basis."""
    return np.random.default_rng(0).standard_normal(n)


#: ``solver='auto'`` uses block Lanczos when ``V · k`` reaches this (and ``k >= 20``).
BLOCK_MIN_WORK = 3_000_000
#: Below this many vertices block Lanczos runs with one BLAS thread.
BLOCK_ONE_THREAD_BELOW = 100_000
#: Shift ``s`` of the block Lanczos factorisation ``L + s B`` on a unit-area surface.
BLOCK_SHIFT = 1e-2
#: Restart cycles of block Lanczos before :class:`ConvergenceError`.
BLOCK_MAX_CYCLES = 60


def eigenpairs(L, B, k: int, sigma: float = -1e-8, *, solver: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """First ``k`` generalised eigenpairs: ``(λ (k,), φ (V, k))``, float64, B-orthonormal, signs fixed.

    Dense ``eigh`` up to :data:`DENSE_LIMIT` vertices; beyond, ``solver='block'``
    (:func:`block_lanczos`), ``'arpack'`` (``eigsh``, shift ``sigma``) or ``'auto'``
    (:func:`auto_solver`). Solved on ``B`` scaled to unit area, then scaled back. Warns
    :class:`~torchfmap.errors.CostWarning` above :data:`MANY_EIGENPAIRS` pairs of a large mesh.

    Raises:
        ParameterError: ``k`` outside ``[1, V]``, an unknown ``solver``, a non-symmetric ``L``, an area
            that is not finite and positive, or more memory than available.
        ConvergenceError: block Lanczos did not converge in :data:`BLOCK_MAX_CYCLES` restarts.
    """
    n = L.shape[0]
    if not 1 <= k <= n:
        raise ParameterError(f"k must be in [1, {n}] for a mesh of {n} vertices, got k={k}.")
    check_memory(n, k, "eigenpairs")
    if solver not in ("auto", "block", "arpack"):
        raise ParameterError(f"unknown eigensolver {solver!r}. Fix: 'auto', 'block' or 'arpack'.")
    check_symmetric(L, "Laplacian eigenbases", "laplacian(mesh, scheme='cotan') or scheme='robust'")
    area = float(B.sum())
    if not np.isfinite(area) or area <= 0 or not np.isfinite(1.0 / area):
        raise ParameterError(
            f"the mass matrix sums to {area!r}: the mesh's scale over- or underflows float64. Fix: "
            "rescale it first, e.g. mesh.normalized() or mesh.scaled(alpha)."
        )
    if n > DENSE_LIMIT and k > MANY_EIGENPAIRS:
        warnings.warn(
            f"computing {k} eigenpairs of a {n}-vertex mesh: the time grows as V·k², so this takes "
            f"minutes (and {8 * n * k * 3 / 1e9:.1f} GB or more), where k <= {MANY_EIGENPAIRS} takes "
            "seconds. Fix: a smaller k (functional maps use 30-200 eigenfunctions), or let it run.",
            CostWarning,
            stacklevel=2,
        )
    if solver == "auto":
        solver = auto_solver(n, k)
    lam, phi = _unit_area_eigenpairs(L, B / area, k, sigma, solver)
    return lam / area, phi / np.sqrt(area)


def auto_solver(n: int, k: int) -> str:
    """The solver ``eigenpairs(..., solver='auto')`` uses for ``k`` pairs of ``n`` vertices."""
    return "block" if k >= 20 and n * k >= BLOCK_MIN_WORK else "arpack"


def _unit_area_eigenpairs(L, B, k: int, sigma: float, solver: str) -> tuple[np.ndarray, np.ndarray]:
    n = L.shape[0]
    block = _block_size(k)
    if n <= DENSE_LIMIT or k >= n - 1:
        lam, phi = sla.eigh(L.toarray(), B.toarray(), subset_by_index=(0, k - 1))
    elif (
        solver == "block"
        and _block_dimension(k, block) + block <= n
        and (d := lumped_diagonal(B)) is not None
    ):
        lam, phi = _block_eigenpairs(L, B, k, block, d)
    else:
        lam, phi = _arpack_eigenpairs(L, B, k, sigma)
    if not (n <= DENSE_LIMIT or k >= n - 1):
        # Rayleigh quotients: Φᵀ L Φ = diag(λ) to round-off, independent of the ARPACK build
        lam = np.einsum("vk,vk->k", phi, L @ phi) / np.einsum("vk,vk->k", phi, B @ phi)
        order = np.argsort(lam, kind="stable")
        lam, phi = lam[order], phi[:, order]
    lam = np.where(lam > -1e-10, np.maximum(lam, 0.0), lam)  # round-off below zero -> 0
    return lam, fix_signs(phi, B)


def _arpack_eigenpairs(L, B, k: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    n = L.shape[0]
    L, B = sp.csc_matrix(L), sp.csc_matrix(B)
    fac = factorize(L - sigma * B, spd=True)
    # a Lanczos basis of 1.5k (scipy's default is 2k + 1): cheaper restarts
    ncv = min(n, max(k + k // 2 + 1, k + 20))
    d = lumped_diagonal(B)
    if d is not None:
        # lumped mass: the standard problem D^-1/2 L D^-1/2 ψ = λ ψ, φ = D^-1/2 ψ
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
            L, k=k, M=B, sigma=sigma, which="LM", OPinv=op_inv, v0=start_vector(n), ncv=ncv, tol=ARPACK_TOL
        )
    order = np.argsort(lam)
    return lam[order], phi[:, order]


def _block_size(k: int) -> int:
    return int(min(16, max(4, k // 12)))


def _block_dimension(k: int, block: int) -> int:
    """Largest Lanczos basis of :func:`block_lanczos` for ``k`` pairs (a multiple of ``block``)."""
    keep = -(-(k + block) // block) * block
    return max(keep + 2 * block, -(-(2 * k + 2 * block) // block) * block)


def _block_eigenpairs(L, B, k: int, block: int, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Block Lanczos on ``D^1/2 (L + s D)⁻¹ D^1/2`` (lumped mass ``D = diag(d)``, ``s`` =
    :data:`BLOCK_SHIFT`): the standard form of the problem, ``φ = D^-1/2 ψ``."""
    fac = factorize(sp.csc_matrix(L + BLOCK_SHIFT * B), spd=True)
    s = np.sqrt(d)[:, None]
    with blas_threads(1 if L.shape[0] < BLOCK_ONE_THREAD_BELOW else None):
        theta, psi = block_lanczos(lambda X: s * fac.solve(s * X), L.shape[0], k, block)
    lam = 1.0 / theta - BLOCK_SHIFT
    order = np.argsort(lam)
    return lam[order], (psi / s)[:, order]


def _block_qr(W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``W = Q R`` for a tall ``(n, b)`` block: Cholesky QR twice, Householder when ill-conditioned."""
    R = np.eye(W.shape[1])
    Q = W
    for _ in range(2):
        try:
            c = np.linalg.cholesky(Q.T @ Q)
        except np.linalg.LinAlgError:
            return np.linalg.qr(W)
        d = np.abs(np.diag(c))
        if d.min() <= 1e-6 * d.max():
            return np.linalg.qr(W)
        Q = Q @ sla.solve_triangular(c, np.eye(len(c)), lower=True, check_finite=False).T
        R = c.T @ R
    return Q, R


def block_lanczos(op, n: int, k: int, block: int, tol: float = ARPACK_TOL, seed: int = 0):
    """The ``k`` largest eigenpairs of a symmetric positive semi-definite operator (thick restarts).

    Args:
        op: ``X (n, b) -> op(X) (n, b)``, symmetric. block: columns per operator call.
        tol: a pair is converged when ``‖op(y) - θ y‖ <= tol · θ``. seed: of the start block.

    Returns:
        ``(θ (k,) descending, Y (n, k) orthonormal)``.

    Raises:
        ParameterError: ``n`` too small for ``k`` and ``block``.
        ConvergenceError: not converged after :data:`BLOCK_MAX_CYCLES` restarts.
    """
    b = block
    m = _block_dimension(k, b)
    keep = -(-(k + b) // b) * b
    if m + b > n:
        raise ParameterError(f"block Lanczos needs n > {m + b} for k={k}, block={b}; got n={n}.")
    Q = np.empty((n, m + b))
    T = np.zeros((m + b, m + b))
    Q[:, :b] = np.linalg.qr(np.random.default_rng(seed).standard_normal((n, b)))[0]
    filled = b
    restarted = 0  # the block coupled to all vectors before it
    worst = np.inf
    for _ in range(BLOCK_MAX_CYCLES):
        while filled < m + b:
            j0 = filled - b
            W = op(Q[:, j0:filled])
            Qa = Q[:, :filled]
            # a pass against the blocks W couples to in exact arithmetic, then one full pass
            lo = 0 if j0 == restarted else max(0, j0 - b)
            C = np.zeros((filled, b))
            C[lo:] = Q[:, lo:filled].T @ W
            W -= Q[:, lo:filled] @ C[lo:]
            C2 = Qa.T @ W
            W -= Qa @ C2
            C += C2
            T[:filled, j0:filled] = C
            T[j0:filled, :filled] = C.T
            Qn, R = _block_qr(W)
            diag = np.abs(np.diag(R))
            if diag.min() <= 1e-8 * max(diag.max(), 1e-300):  # (near) breakdown: new directions
                Qn -= Qa @ (Qa.T @ Qn)
                Qn, R2 = np.linalg.qr(Qn)
                R = R2 @ R
            Q[:, filled : filled + b] = Qn
            T[filled : filled + b, j0:filled] = R
            T[j0:filled, filled : filled + b] = R.T
            filled += b
        a = m  # Rayleigh-Ritz on the first m vectors; the last block carries the residuals
        theta, U = np.linalg.eigh((T[:a, :a] + T[:a, :a].T) / 2)
        theta, U = theta[::-1], U[:, ::-1]
        coupling = T[a : a + b, :a] @ U[:, :keep]  # op(Y) - Y diag(θ) = Q_last coupling
        residual = np.linalg.norm(coupling, axis=0)
        worst = float(np.max(residual[:k] / np.abs(theta[:k])))
        if worst <= tol:
            return theta[:k], Q[:, :a] @ U[:, :k]
        last = Q[:, a : a + b].copy()
        Q[:, :keep] = Q[:, :a] @ U[:, :keep]
        Q[:, keep : keep + b] = last
        T[:] = 0.0
        T[:keep, :keep] = np.diag(theta[:keep])
        T[keep : keep + b, :keep] = coupling
        T[:keep, keep : keep + b] = coupling.T
        filled, restarted = keep + b, keep
    raise ConvergenceError(
        f"block Lanczos did not converge in {BLOCK_MAX_CYCLES} restarts (largest relative residual "
        f"{worst:.1e}, tolerance {tol:.0e}). Fix: eigenpairs(..., solver='arpack')."
    )
