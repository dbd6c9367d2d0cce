"""Shift-and-invert Lanczos for the heat action ``exp(-t A) X``, ``A = B⁻¹ L`` (the ``krylov`` method
of :func:`~torchfmap.operators.heat.heat_apply`): Krylov spaces of ``(B + γL)⁻¹ B`` built in
lock-step for a block of columns, one sparse Cholesky of ``B + γL`` per group of times; each column
stops when every time has converged to ``tol`` (relative, in the B-norm)."""

from __future__ import annotations

import contextlib

import numpy as np
from scipy.linalg import blas

from .._util.checks import lumped_diagonal
from .._util.threads import blas_limiter
from .solvers import factorize

#: Memory budget (bytes) of one block of Krylov vectors.
KRYLOV_BLOCK_BYTES = 3 * 2**30
#: Most seeds per Krylov block.
KRYLOV_BLOCK_COLUMNS = 8
#: Lanczos vectors per column the work buffer starts with (it grows when more are needed).
KRYLOV_STORE = 48
#: Shift of the Krylov factorisation ``B + γL``, as a fraction of the smallest time it serves.
KRYLOV_SHIFT = 0.3
#: Times up to this factor above the smallest of a group share its Krylov space.
KRYLOV_SPAN = 50.0
#: ``γ = KRYLOV_SHIFT · t_min · (t_max / t_min)^KRYLOV_SHIFT_SPAN_EXP``.
KRYLOV_SHIFT_SPAN_EXP = 0.15


def _sub_scaled(W: np.ndarray, Q: np.ndarray, c: np.ndarray) -> None:
    """``W -= Q · diag(c)`` in place for ``(n, s)`` blocks (one ``dgemm`` pass when ``W`` is C-ordered)."""
    if not W.flags.c_contiguous:
        W -= Q * c
        return
    blas.dgemm(-1.0, np.diag(c), Q.T, 1.0, W.T, overwrite_c=True)


def _dots(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Column-wise dot products of two ``(n, s)`` blocks."""
    return np.einsum("ij,ij->j", X, Y)


def krylov_block(
    fac, B, X, times, gamma, tol, max_iter, store=None, small=None, out=None
) -> tuple[np.ndarray, int]:
    """Lock-step shift-and-invert Lanczos for the columns of ``X (n, s)``; ``fac`` factorises ``B + γL``.

    ``store``: optional ``(cap, n, >= s)`` work buffer reused across blocks; ``small``: a context
    manager factory around the tiny ``(s, k, k)`` eigenproblems; ``out``: optional ``(T, n, s)`` array
    (any strides) written into. Returns ``((T, n, s) approximations, iterations)``.
    """
    small = small if small is not None else contextlib.nullcontext
    n, s = X.shape
    d = lumped_diagonal(B)

    def bmul(v: np.ndarray, res: np.ndarray) -> None:  # res = B v
        if d is not None:
            np.multiply(v, d[:, None], out=res)
        else:
            res[...] = B @ v

    if store is None or store.shape[1] != n or store.shape[2] < s:
        store = np.empty((min(max_iter, KRYLOV_STORE) + 1, n, s))  # store[m]: the m-th Lanczos vectors
    store = store[:, :, :s]
    if not store.flags.c_contiguous:  # a narrower last block: its own contiguous buffer
        store = np.empty((store.shape[0], n, s))
    Bq = np.empty((n, s))
    bmul(X, Bq)
    beta0 = np.sqrt(np.maximum(_dots(X, Bq), 0.0))
    beta0[beta0 == 0] = 1.0
    q = store[0]
    np.divide(X, beta0, out=q)
    Bq /= beta0
    alpha = np.zeros((s, max_iter))
    beta = np.zeros((s, max_iter))
    prev = None
    times = np.asarray(times, dtype=np.float64)
    # each column keeps the coefficients of its converged iteration: independent of its block-mates
    final = np.zeros((len(times), s, max_iter))
    done = np.zeros(s, dtype=bool)
    for m in range(max_iter):
        if m + 2 > store.shape[0]:
            grow = min(store.shape[0], max_iter + 1 - store.shape[0])
            store = np.concatenate([store, np.empty((grow, n, s))], axis=0)
            q = store[m]
        w = fac.solve(Bq, out=store[m + 1])
        if m > 0:
            _sub_scaled(w, store[m - 1], beta[:, m - 1])
        a = _dots(w, Bq)
        _sub_scaled(w, q, a)
        alpha[:, m] = a
        if d is not None:
            nb = np.sqrt(np.maximum(np.einsum("ij,ij,i->j", w, w, d), 0.0))
        else:
            bmul(w, Bq)
            nb = np.sqrt(np.maximum(_dots(w, Bq), 0.0))
        beta[:, m] = nb
        safe = np.where(nb > 0, nb, 1.0)
        w /= safe
        q = w
        if d is not None:
            bmul(q, Bq)
        else:
            Bq /= safe
        k = m + 1
        T = np.zeros((s, k, k))
        idx = np.arange(k)
        T[:, idx, idx] = alpha[:, :k]
        T[:, idx[1:], idx[:-1]] = beta[:, : k - 1]
        T[:, idx[:-1], idx[1:]] = beta[:, : k - 1]
        with small():
            theta, U = np.linalg.eigh(T)  # eigenvalues of (I + gamma A)^{-1}: in (0, 1]
        theta = np.clip(theta, 1e-300, 1.0)
        lam = (1.0 / theta - 1.0) / gamma  # (s, k) Ritz values of A
        f = np.exp(-times[:, None, None] * lam[None])  # (T, s, k)
        y = np.einsum("sij,tsj,sj->tsi", U, f, U[:, 0, :])  # (T, s, k) small-space coefficients
        if prev is not None:
            diff = y.copy()
            diff[:, :, :m] -= prev
            err = np.linalg.norm(diff, axis=2) / np.maximum(np.linalg.norm(y, axis=2), 1e-300)
            # an exhausted Krylov space (beta = 0) is exact
            new = ~done & ((err.max(axis=0) < 0.2 * tol) | (nb < 1e-14))
            final[:, new, : m + 1] = y[:, new]
            done |= new
            if done.all():
                break
        prev = y
    k = y.shape[2]
    final[:, ~done, :k] = y[:, ~done]  # max_iter reached: the last approximation
    coef = (final[:, :, :k] * beta0[None, :, None]).transpose(1, 2, 0)  # (s, k, T)
    out = np.empty((len(times), n, s)) if out is None else out
    # out[t, r, j] = sum_m coef[j, m, t] store[m, r, j], on row chunks of ~2 MiB read in place
    coef_t = np.ascontiguousarray(coef.transpose(0, 2, 1))  # (s, T, k)
    rows = max(1, 2**18 // (k * s))
    for r0 in range(0, n, rows):
        chunk = store[:k, r0 : r0 + rows].transpose(2, 0, 1)  # (s, k, r), a view
        out[:, r0 : r0 + rows] = np.matmul(coef_t, chunk).transpose(1, 2, 0)
    return out, k


def block_columns(n: int, s_total: int, cap: int) -> int:
    """Columns per Krylov block (``n`` rows, ``cap`` stored vectors each): at least one, at most
    :data:`KRYLOV_BLOCK_COLUMNS` and ``s_total``, within :data:`KRYLOV_BLOCK_BYTES`."""
    return max(1, min(s_total, KRYLOV_BLOCK_COLUMNS, int(KRYLOV_BLOCK_BYTES // (8 * n * cap))))


def krylov_heat(
    L, B, X, times, tol, max_iter: int = 150, shift: float | None = None, factors: dict | None = None
) -> np.ndarray:
    """``exp(-t B⁻¹L) X`` for ``X (n, S)``; times within a factor :data:`KRYLOV_SPAN` share one
    factorisation of ``B + γL``. ``factors``: a caller-kept dict ``γ -> factorisation``, read and
    filled. Returns ``(T, n, S)``, a view of a C-ordered ``(n, T, S)`` array."""
    times = np.asarray(times, dtype=np.float64)
    n, s_total = X.shape
    order = np.argsort(times)
    groups: list[list[int]] = []
    for i in order:
        if groups and times[i] <= KRYLOV_SPAN * times[groups[-1][0]]:
            groups[-1].append(int(i))
        else:
            groups.append([int(i)])
    cap = min(max_iter, KRYLOV_STORE) + 1
    block = block_columns(n, s_total, cap)
    store = np.empty((cap, n, block))
    out = np.empty((n, len(times), s_total)).transpose(1, 0, 2)
    one_thread = blas_limiter(1)

    for group in groups:
        t_lo, t_hi = float(times[group[0]]), float(times[group[-1]])
        gamma = KRYLOV_SHIFT * t_lo * (t_hi / t_lo) ** KRYLOV_SHIFT_SPAN_EXP
        gamma = float(shift) if shift is not None else gamma
        fac = factors.get(gamma) if factors is not None else None
        if fac is None:
            fac = factorize(B + gamma * L, spd=True)
            if factors is not None:
                factors[gamma] = fac
        for start in range(0, s_total, block):
            cols = slice(start, min(start + block, s_total))
            contiguous = group == list(range(group[0], group[-1] + 1))
            target = out[group[0] : group[-1] + 1, :, cols] if contiguous else None
            res, _ = krylov_block(
                fac, B, X[:, cols], times[group], gamma, tol, max_iter, store, one_thread, target
            )
            if not contiguous:
                out[group, :, cols] = res
    return out
