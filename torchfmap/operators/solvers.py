"""Sparse direct solvers: factorise once, solve many right-hand sides. ``backend='auto'`` tries, for
SPD systems, ``cholespy``, ``cholmod`` (``scikit-sparse``), then ``splu`` (SuperLU, always present,
and the only one for other systems); a Cholesky that finds the matrix not positive definite falls
back to ``splu`` under ``auto`` and raises under an explicit backend."""

from __future__ import annotations

import importlib.util
from typing import Literal

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from ..errors import NotPositiveDefiniteError, ParameterError

Backend = Literal["auto", "cholmod", "cholespy", "splu"]
_BACKENDS = ("cholmod", "cholespy", "splu")


def available_backends() -> list[str]:
    """Backends importable on this machine, fastest first (``splu`` is always last)."""
    found = []
    if importlib.util.find_spec("cholespy") is not None:
        found.append("cholespy")
    if importlib.util.find_spec("sksparse") is not None:
        try:
            import sksparse.cholmod  # noqa: F401

            found.append("cholmod")
        except ImportError:  # built against a missing SuiteSparse
            pass
    found.append("splu")
    return found


class Factorization:
    """A factorised sparse matrix ``A (n, n)``; :meth:`solve` takes ``(n,)`` or ``(n, k)``."""

    def __init__(self, backend: str, n: int, solve_fn, dtype, solve_into=None) -> None:
        self.backend = backend
        self.n = n
        self._solve = solve_fn
        self._solve_into = solve_into  # (b, out) -> None, C-ordered float64 arrays
        self.dtype = dtype

    def solve(self, b: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``x = A^{-1} b`` for ``b`` ``(n,)`` or ``(n, k)``, C-ordered, of ``b``'s shape. ``out``: a
        C-ordered float64 array of ``b``'s shape written into and returned (real matrices only).

        Raises :class:`ParameterError` for a right-hand side or ``out`` of the wrong shape or dtype."""
        b = np.asarray(b)
        if b.shape[0] != self.n:
            raise ParameterError(f"right-hand side has {b.shape[0]} rows, the matrix has {self.n}.")
        if out is not None:
            if out.shape != b.shape or out.dtype != np.float64 or not out.flags.c_contiguous:
                raise ParameterError(
                    f"out must be a C-ordered float64 array of shape {b.shape}, got {out.dtype} "
                    f"{out.shape}. Fix: np.empty_like(b, dtype=np.float64)."
                )
            if np.iscomplexobj(b) or np.issubdtype(self.dtype, np.complexfloating):
                raise ParameterError("out= takes a real matrix and right-hand side. Fix: leave out=None.")
            if self._solve_into is not None:
                self._solve_into(np.ascontiguousarray(b, dtype=np.float64), out)
            else:
                out[...] = self._solve(b)
            return out
        if np.iscomplexobj(b) and not np.issubdtype(self.dtype, np.complexfloating):
            return self.solve(b.real) + 1j * self.solve(b.imag)
        return np.ascontiguousarray(self._solve(b))

    __call__ = solve

    def __repr__(self) -> str:
        return f"Factorization(backend={self.backend!r}, n={self.n})"


def _splu(a: sp.csc_matrix, symmetric: bool) -> Factorization:
    if symmetric:
        lu = sla.splu(a, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    else:
        lu = sla.splu(a)
    return Factorization("splu", a.shape[0], lu.solve, a.dtype)


def _cholmod(a: sp.csc_matrix) -> Factorization:
    from sksparse.cholmod import CholmodNotPositiveDefiniteError, cholesky

    try:
        factor = cholesky(a)
    except CholmodNotPositiveDefiniteError as err:
        raise NotPositiveDefiniteError(f"CHOLMOD: matrix is not positive definite ({err}).") from err
    return Factorization("cholmod", a.shape[0], factor, a.dtype)


def _cholespy(a: sp.csc_matrix) -> Factorization:
    import cholespy

    coo = a.tocoo()
    try:
        solver = cholespy.CholeskySolverD(
            a.shape[0],
            coo.row.astype(np.int32),
            coo.col.astype(np.int32),
            coo.data.astype(np.float64),
            cholespy.MatrixType.COO,
        )
    except ValueError as err:
        raise NotPositiveDefiniteError(f"cholespy: {err}") from err

    def solve(b: np.ndarray) -> np.ndarray:
        b = np.ascontiguousarray(b, dtype=np.float64)
        x = np.empty_like(b)
        solver.solve(b, x)
        return x

    return Factorization("cholespy", a.shape[0], solve, np.float64, solve_into=solver.solve)


def factorize(
    matrix: sp.spmatrix | sp.sparray, *, spd: bool = False, backend: Backend = "auto"
) -> Factorization:
    """A :class:`Factorization` of a square ``(n, n)`` sparse matrix (real or complex).

    ``spd``: the caller knows it is symmetric positive definite (enables Cholesky backends).

    Raises:
        ParameterError: an unknown or uninstalled backend, a non-square matrix, or a Cholesky
            backend without ``spd`` (or on a complex matrix).
        NotPositiveDefiniteError: the matrix is singular, or not SPD under an explicit Cholesky.
    """
    if backend != "auto" and backend not in _BACKENDS:
        raise ParameterError(f"unknown solver backend {backend!r}. Fix: use 'auto' or one of {_BACKENDS}.")
    a = sp.csc_matrix(matrix)
    if a.shape[0] != a.shape[1]:
        raise ParameterError(f"factorize needs a square matrix, got shape {a.shape}.")
    complex_matrix = np.iscomplexobj(a.data)
    if not complex_matrix:
        a = a.astype(np.float64)
    if backend in ("cholmod", "cholespy"):
        if complex_matrix or not spd:
            raise ParameterError(
                f"backend {backend!r} needs a real symmetric positive definite matrix. Fix: pass "
                "spd=True if it is, or use backend='splu'."
            )
        if backend not in available_backends():
            raise ParameterError(
                f"backend {backend!r} is not installed. Fix: `pip install "
                f"{'scikit-sparse' if backend == 'cholmod' else 'cholespy'}`, or use backend='auto'."
            )
        return _verified(_cholmod(a) if backend == "cholmod" else _cholespy(a), a)
    if backend == "auto" and spd and not complex_matrix:
        for name in available_backends():
            if name == "splu":
                break
            try:
                return _verified(_cholmod(a) if name == "cholmod" else _cholespy(a), a)
            except NotPositiveDefiniteError:
                break
    return _verified(_splu(a, symmetric=spd), a)


#: Largest relative error of the probe solve in :func:`_verified`.
PROBE_RTOL = 1e-3


def _verified(fac: Factorization, a: sp.csc_matrix) -> Factorization:
    """``fac`` after a probe solve ``A⁻¹ (A r) = r``; singular: :class:`NotPositiveDefiniteError`."""
    r = np.random.default_rng(0).standard_normal(a.shape[0])
    with np.errstate(all="ignore"):
        x = fac.solve(a @ r)
        err = float(np.linalg.norm(x - r) / np.linalg.norm(r))
    if not np.isfinite(err) or err > PROBE_RTOL:
        raise NotPositiveDefiniteError(
            f"the matrix is singular (a probe solve is off by {err:.1e} relative). Fix: make it "
            "definite, e.g. factorize(L + s * B) with a shift s > 0 for a Laplacian L."
        )
    return fac
