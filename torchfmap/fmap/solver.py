"""Regularised functional-map solver in any B-orthonormal basis: ``C_xy (K_y, K_x)`` minimises
``w_desc ‖C A_x - A_y‖² + w_lap Σ M_ij C'_ij² + w_dcomm Σ_f ‖C D_x^f - D_y^f C‖² + w_orient Σ_f
‖C O_x^f ∓ O_y^f C‖² + w_lmk ‖P_y C - P_x‖²`` (``C'`` in the eigenvectors of ``W = Φᵀ L Φ``);
exact row by row without coupling terms, else by preconditioned CG."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse.linalg as ssla

from .._util import checks as _checks
from .._util.checks import check_landmark_pairs
from .._util.threads import torch_threads
from ..bases.basis import Basis
from ..descriptors import check_descriptors
from ..errors import ConvergenceError, MemoryEstimateError, ParameterError
from ..mesh import Mesh
from . import core
from .defaults import W_LAP_SMOOTH, W_LMK, W_ORIENT

#: Descriptors used for the commutativity / orientation operators (evenly spaced columns), which
#: cost K^3 per descriptor and CG step.
MAX_OPERATOR_DESCRIPTORS = 16


def basis_frame(basis: Basis) -> core.SpectralFrame:
    """:class:`~torchfmap.fmap.core.SpectralFrame` ``(lam (K,), U (K, K))`` (numpy) of ``basis``'s
    projected Laplacian ``W = Φᵀ L Φ`` (:func:`~torchfmap.fmap.core.spectral_frame`)."""
    with torch_threads(1):
        lam, U = core.spectral_frame(core.as_tensor(basis.projected_laplacian()))
    return core.SpectralFrame(lam.numpy(), U.numpy())


def multiplication_operator(basis: Basis, f: np.ndarray, weighted: np.ndarray | None = None) -> np.ndarray:
    """``(K, K)`` ``Φᵀ B diag(f) Φ``: multiplication by ``f (V,)`` in the basis. ``weighted``:
    ``B Φ`` ``(V, K)`` when already at hand (shared by several operators of one basis)."""
    weighted = basis.mass @ basis.values if weighted is None else weighted
    return (f[:, None] * weighted).T @ basis.values


def solve_bytes(k_x: int, k_y: int) -> int:
    """Estimated peak bytes (a lower bound) of one :func:`solve_fmap` in bases of ``k_x`` and ``k_y``
    columns."""
    return 8 * (2 * k_y * k_x * k_x + 2 * MAX_OPERATOR_DESCRIPTORS * (k_x * k_x + k_y * k_y))


def check_solve_memory(k_x: int, k_y: int) -> None:
    """Raise MemoryEstimateError (estimate, memory available, fix) before any work if
    :func:`solve_bytes` exceed the memory available now."""
    needed, available = solve_bytes(k_x, k_y), _checks.available_memory()
    if available is not None and needed > available:
        raise MemoryEstimateError(
            f"the functional-map solve at k = {max(k_x, k_y)} needs an estimated {needed / 2**30:.1f} GiB "
            f"of memory (its row systems grow as k^3), and {available / 2**30:.1f} GiB is available. Fix: "
            "a smaller k (--k; the field uses 30-200)."
        )


#: Faces per chunk in :func:`orientation_operators` (bounds its work buffer to ~chunk·J·K floats).
ORIENT_FACE_CHUNK = 1024


def orientation_operators(
    mesh: Mesh, basis: Basis, F: np.ndarray, dtype: type = np.float64
) -> list[np.ndarray]:
    """``(K, K)`` operators ``g -> (n × ∇f)·∇g``, area-lumped, one per column ``f`` of ``F (V, J)``
    (Ren et al. 2018); ``dtype=np.float32``: single-precision products, float64 sums."""
    phi = np.asarray(basis.values, dtype=dtype)
    F = np.asarray(F, dtype=dtype).reshape(mesh.n_vertices, -1)
    faces = mesh.faces
    K, J = phi.shape[1], F.shape[1]
    acc = np.zeros((K, J * K))
    buf = np.empty((min(ORIENT_FACE_CHUNK, len(faces)), J, K), dtype=dtype)
    for f0 in range(0, len(faces), ORIENT_FACE_CHUNK):
        fc = faces[f0 : f0 + ORIENT_FACE_CHUNK]
        corners = [phi[fc[:, c]] for c in range(3)]
        S = corners[0] + corners[1] + corners[2]
        diff = np.stack([corners[(c + 1) % 3] - corners[(c + 2) % 3] for c in range(3)], axis=1)
        per_face = buf[: len(fc)]
        np.matmul(F[fc].transpose(0, 2, 1), diff, out=per_face)  # (f, J, K): Σ_c f(v_c) diff_c
        acc += S.T @ per_face.reshape(len(fc), J * K)
    ops = acc.reshape(K, J, K) / 6.0
    return [np.ascontiguousarray(ops[:, j, :]) for j in range(J)]


@dataclass
class FmapProblem:
    """Everything the solver needs, already rotated into the spectral frames of ``W_x, W_y``."""

    A_x: np.ndarray
    A_y: np.ndarray
    mask: np.ndarray
    frame_x: core.SpectralFrame
    frame_y: core.SpectralFrame
    commute: list[tuple[np.ndarray, np.ndarray, float, float]]  # (Dx', Dy', weight, sign)
    landmarks: tuple[np.ndarray, np.ndarray, float] | None  # (P_y', P_x', weight)
    w_desc: float
    w_lap: float
    prior: np.ndarray | None = None  # rotated prior map P' = U_yᵀ P U_x
    w_prior: float = 0.0  # absolute weight of ‖C' - P'‖²

    @property
    def shape(self) -> tuple[int, int]:
        return self.A_y.shape[0], self.A_x.shape[0]

    def energy(self, Cr: np.ndarray) -> float:
        """Energy of a rotated map ``C'``."""
        e = self.w_desc * np.sum((Cr @ self.A_x - self.A_y) ** 2) + self.w_lap * np.sum(self.mask * Cr**2)
        for Dx, Dy, w, sign in self.commute:
            e += w * np.sum((Cr @ Dx - sign * Dy @ Cr) ** 2)
        if self.landmarks is not None:
            Py, Px, w = self.landmarks
            e += w * np.sum((Py @ Cr - Px) ** 2)
        if self.prior is not None:
            e += self.w_prior * np.sum((Cr - self.prior) ** 2)
        return float(e)

    def normal_matvec(self, Cr: np.ndarray) -> np.ndarray:
        """Half the gradient's linear part: ``H C'`` of the quadratic energy."""
        out = self.w_desc * (Cr @ self.A_x) @ self.A_x.T + self.w_lap * self.mask * Cr
        for Dx, Dy, w, sign in self.commute:
            R = Cr @ Dx - sign * Dy @ Cr
            out += w * (R @ Dx.T - sign * Dy.T @ R)
        if self.landmarks is not None:
            Py, _, w = self.landmarks
            out += w * Py.T @ (Py @ Cr)
        if self.prior is not None:
            out += self.w_prior * Cr
        return out

    def normal_rhs(self) -> np.ndarray:
        rhs = self.w_desc * self.A_y @ self.A_x.T
        if self.landmarks is not None:
            Py, Px, w = self.landmarks
            rhs = rhs + w * Py.T @ Px
        if self.prior is not None:
            rhs = rhs + self.w_prior * self.prior
        return rhs

    def row_blocks(self) -> np.ndarray:
        """``(K_y, K_x, K_x)`` diagonal blocks of the Hessian, one per row of ``C'`` (coupling
        terms' within-row parts included)."""
        ky, kx = self.shape
        eye = np.eye(kx)
        G = self.w_desc * (self.A_x @ self.A_x.T)
        blocks = G[None] + self.w_lap * self.mask[:, :, None] * eye  # (ky, kx, kx)
        if self.commute:
            shared = sum(w * (Dx @ Dx.T) for Dx, _, w, _ in self.commute)
            blocks += shared[None]
            yy = sum(w * np.einsum("ji,ji->i", Dy, Dy) for _, Dy, w, _ in self.commute)
            blocks += yy[:, None, None] * eye
            diag_y = np.stack([w * s * np.diagonal(Dy) for _, Dy, w, s in self.commute])  # (f, ky)
            sym_x = np.stack([Dx + Dx.T for Dx, _, _, _ in self.commute])  # (f, kx, kx)
            blocks -= np.einsum("fi,fjk->ijk", diag_y, sym_x, optimize=True)
        if self.landmarks is not None:
            Py, _, w = self.landmarks
            blocks += w * np.einsum("li,li->i", Py, Py)[:, None, None] * eye
        if self.prior is not None:
            blocks += self.w_prior * eye
        return blocks

    def solve(self, tol: float = 1e-8, maxiter: int = 2000) -> np.ndarray:
        """The minimiser ``C'``. Raises :class:`ConvergenceError` if CG has not converged to
        ``tol`` after ``maxiter`` iterations."""
        if not self.commute and self.landmarks is None:
            t = core.as_tensor
            prior = None if self.prior is None else t(self.prior)
            with torch_threads(1):
                return core.solve_rowwise(
                    t(self.A_x), t(self.A_y), t(self.mask), self.w_desc, self.w_lap, None, prior, self.w_prior
                ).numpy()
        ky, kx = self.shape
        inv_blocks = np.linalg.inv(self.row_blocks())
        rhs = self.normal_rhs()
        op = ssla.LinearOperator(
            (ky * kx, ky * kx),
            matvec=lambda c: self.normal_matvec(c.reshape(ky, kx)).ravel(),
            dtype=np.float64,
        )
        precond = ssla.LinearOperator(
            (ky * kx, ky * kx),
            matvec=lambda r: np.einsum("ijk,ik->ij", inv_blocks, r.reshape(ky, kx)).ravel(),
            dtype=np.float64,
        )
        x0 = np.einsum("ijk,ik->ij", inv_blocks, rhs).ravel()
        sol, info = ssla.cg(op, rhs.ravel(), x0=x0, rtol=tol, maxiter=maxiter, M=precond)
        if info > 0:
            res = np.linalg.norm(op @ sol - rhs.ravel()) / max(np.linalg.norm(rhs), 1e-300)
            raise ConvergenceError(
                f"the functional-map solve did not converge: relative residual {res:.1e} after "
                f"{maxiter} CG iterations (tolerance {tol:.0e}). Fix: raise w_lap, or lower the "
                "weights of the coupling terms (w_dcomm, w_orient)."
            )
        return sol.reshape(ky, kx)

    def unrotate(self, Cr: np.ndarray) -> np.ndarray:
        return self.frame_y.U @ Cr @ self.frame_x.U.T


def build_problem(
    basis_x: Basis,
    basis_y: Basis,
    desc_x: np.ndarray,
    desc_y: np.ndarray,
    *,
    w_desc: float = 1.0,
    w_lap: float = W_LAP_SMOOTH,
    mask: core.Mask = "laplacian",
    w_dcomm: float = 0.0,
    w_orient: float = 0.0,
    orient_reversing: bool = False,
    meshes: tuple[Mesh, Mesh] | None = None,
    landmarks=None,
    w_lmk: float = 0.0,
    prior=None,
    w_prior: float = 0.0,
) -> FmapProblem:
    """Assemble a :class:`FmapProblem`; see :func:`solve_fmap` for the arguments."""
    for name, basis in (("basis_x", basis_x), ("basis_y", basis_y)):
        if not basis.orthonormal:
            raise ParameterError(
                f"{name} is not B-orthonormal. Fix: orthonormalize(basis) (or basis_stack) first."
            )
        if basis.stiffness is None:
            raise ParameterError(f"{name} has no stiffness matrix: build it from a mesh with (L, B).")
    desc_x = check_descriptors(desc_x, basis_x.n_vertices, "desc_x")
    desc_y = check_descriptors(desc_y, basis_y.n_vertices, "desc_y")
    if desc_x.shape[1] != desc_y.shape[1]:
        raise ParameterError(
            f"descriptor counts differ: desc_x has {desc_x.shape[1]}, desc_y has {desc_y.shape[1]}. Fix: "
            "compute the same descriptors (same parameters) on both shapes."
        )
    weights = {"w_desc": w_desc, "w_lap": w_lap, "w_dcomm": w_dcomm, "w_orient": w_orient, "w_lmk": w_lmk}
    weights["w_prior"] = w_prior
    bad = {k: v for k, v in weights.items() if not (np.isfinite(v) and v >= 0)}
    if bad:
        raise ParameterError(f"energy weights must be finite and >= 0, got {bad}.")
    fx, fy = basis_frame(basis_x), basis_frame(basis_y)
    with np.errstate(over="ignore", invalid="ignore"):
        A_x = fx.U.T @ basis_x.project(desc_x)
        A_y = fy.U.T @ basis_y.project(desc_y)
        gram_ok = np.isfinite(A_x @ A_x.T).all() and np.isfinite(A_y @ A_x.T).all()
    if not gram_ok:
        raise ParameterError(
            "the descriptors' coefficients overflow float64 in the solve (values too large). Fix: "
            "normalise them first, e.g. torchfmap.descriptors.normalize_descriptors(F, mass)."
        )
    commute = []
    op_cols = np.unique(
        np.linspace(0, desc_x.shape[1] - 1, min(MAX_OPERATOR_DESCRIPTORS, desc_x.shape[1])).astype(int)
    )
    if w_dcomm > 0:
        bx, by = basis_x.mass @ basis_x.values, basis_y.mass @ basis_y.values
        for j in op_cols:
            Dx = fx.U.T @ multiplication_operator(basis_x, desc_x[:, j], bx) @ fx.U
            Dy = fy.U.T @ multiplication_operator(basis_y, desc_y[:, j], by) @ fy.U
            commute.append((*_unit_pair(Dx, Dy), w_dcomm, 1.0))
    if w_orient > 0:
        if meshes is None:
            raise ParameterError("the orientation term needs meshes=(mesh_x, mesh_y).")
        sign = -1.0 if orient_reversing else 1.0
        ops_x = orientation_operators(meshes[0], basis_x, desc_x[:, op_cols], np.float32)
        ops_y = orientation_operators(meshes[1], basis_y, desc_y[:, op_cols], np.float32)
        for Ox, Oy in zip(ops_x, ops_y, strict=True):
            commute.append((*_unit_pair(fx.U.T @ Ox @ fx.U, fy.U.T @ Oy @ fy.U), w_orient, sign))
    lmk = None
    if landmarks is not None and w_lmk > 0:
        pairs = check_landmark_pairs(landmarks, basis_x.n_vertices, basis_y.n_vertices)
        P_y, P_x = basis_y.values[pairs[:, 1]] @ fy.U, basis_x.values[pairs[:, 0]] @ fx.U
        # each landmark pair counts like one unit-norm descriptor, whatever the meshes' scale
        row = 0.5 * (np.linalg.norm(P_x, axis=1) + np.linalg.norm(P_y, axis=1))
        row = np.where(row > 0, row, 1.0)[:, None]
        lmk = (P_y / row, P_x / row, w_lmk)
    prior_r, w_prior_abs = None, 0.0
    if prior is not None and w_prior > 0:
        prior = np.asarray(prior, dtype=np.float64)
        if prior.shape != (basis_y.k, basis_x.k):
            raise ParameterError(
                f"prior must be (K_y, K_x) = {(basis_y.k, basis_x.k)}, got {prior.shape}. Fix: e.g. "
                "np.eye(K_y, K_x) for bases built at corresponding seeds."
            )
        prior_r = fy.U.T @ prior @ fx.U
        # relative to the descriptor term: w_prior = 1 weighs like an average row of it
        w_prior_abs = w_prior * w_desc * max(float(np.sum(A_x**2)) / basis_x.k, 1e-300)
    with torch_threads(1):
        mask_w = core.laplacian_mask(core.as_tensor(fx.lam), core.as_tensor(fy.lam), mask).numpy()
    return FmapProblem(A_x, A_y, mask_w, fx, fy, commute, lmk, w_desc, w_lap, prior_r, w_prior_abs)


def _unit_pair(Ox: np.ndarray, Oy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scale an operator pair to mean unit Frobenius norm, so term weights are scale-free."""
    scale = 0.5 * (np.linalg.norm(Ox) + np.linalg.norm(Oy))
    return (Ox / scale, Oy / scale) if scale > 0 else (Ox, Oy)


def solve_fmap(
    basis_x: Basis,
    basis_y: Basis,
    desc_x: np.ndarray,
    desc_y: np.ndarray,
    *,
    w_desc: float = 1.0,
    w_lap: float = W_LAP_SMOOTH,
    mask: core.Mask = "laplacian",
    w_dcomm: float = 0.0,
    w_orient: float | None = None,
    orient_reversing: bool = False,
    meshes: tuple[Mesh, Mesh] | None = None,
    landmarks=None,
    w_lmk: float | None = None,
    prior=None,
    w_prior: float = 0.0,
) -> np.ndarray:
    """Regularised functional map ``C_xy`` (``(K_y, K_x)``) in B-orthonormal bases with stiffness,
    from ``(V_x, D)``, ``(V_y, D)`` descriptors. Defaults: :mod:`torchfmap.fmap.defaults`.

    ``w_desc``, ``w_lap`` (``mask``: ``'laplacian'`` or ``'resolvent'``), ``w_dcomm``: descriptor,
    Laplacian- and descriptor-commutativity weights. ``w_orient``: needs ``meshes=(mesh_x,
    mesh_y)`` (default ``W_ORIENT`` with meshes, else 0; ``orient_reversing``: mirror maps).
    ``landmarks``: ``(L, 2)`` pairs ``(x vertex, y vertex)``, weight ``w_lmk`` (default
    ``W_LMK``). ``prior``: a ``(K_y, K_x)`` map pulled towards by ``w_prior ‖C - P‖²``,
    ``w_prior`` relative to the descriptor term. Raises MemoryEstimateError for bases too large
    for the memory available (:func:`solve_bytes`).
    """
    check_solve_memory(basis_x.k, basis_y.k)
    has_landmarks = landmarks is not None and len(np.atleast_1d(landmarks)) > 0
    problem = build_problem(
        basis_x,
        basis_y,
        desc_x,
        desc_y,
        w_desc=w_desc,
        w_lap=w_lap,
        mask=mask,
        w_dcomm=w_dcomm,
        w_orient=(W_ORIENT if meshes is not None else 0.0) if w_orient is None else w_orient,
        orient_reversing=orient_reversing,
        meshes=meshes,
        landmarks=landmarks if has_landmarks else None,
        w_lmk=(W_LMK if has_landmarks else 0.0) if w_lmk is None else w_lmk,
        prior=prior,
        w_prior=w_prior,
    )
    return problem.unrotate(problem.solve())
