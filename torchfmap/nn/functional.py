"""Differentiable functional-map operations on batches (torch).

Shapes: ``B`` pairs, ``V`` vertices (padded), ``K`` basis functions (padded), ``D`` feature
channels. A :class:`BasisBatch` holds ``values (B, V, K)``, ``mass (B, V)`` (lumped; 0 on
padded vertices), the spectral frame of the projected Laplacian ``lam (B, K)``, ``U (B, K, K)``
(identity on padded columns) and ``valid (B, K)`` (1 for real columns). The solve itself is
:func:`torchfmap.fmap.core.rotate_and_solve`; the classical path runs the same core
(:func:`~torchfmap.fmap.core.spectral_frame`, :func:`~torchfmap.fmap.core.solve_rowwise`).
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import torch

from ..errors import ParameterError
from ..fmap import core
from ..fmap.defaults import W_LAP


class BasisBatch(NamedTuple):
    """A padded batch of bases; see the module docstring for shapes."""

    values: torch.Tensor
    mass: torch.Tensor
    lam: torch.Tensor
    U: torch.Tensor
    valid: torch.Tensor

    @property
    def W(self) -> torch.Tensor:
        """``(B, K, K)`` projected Laplacian ``U diag(lam) Uᵀ``."""
        return self.U @ (self.lam[..., None] * self.U.transpose(-1, -2))

    def to(self, *args, **kwargs) -> BasisBatch:
        return BasisBatch(*(t.to(*args, **kwargs) for t in self))


class GradientBatch(NamedTuple):
    """Padded batch of vertex gradient operators (:func:`torchfmap.nn.geometry.gradient_operator`).

    ``rows, cols (B, E)`` (int64) and ``weight_x, weight_y (B, E)``: ``(∇f)_v`` in the tangent
    frame of ``v`` is ``Σ_{rows == v} weight · f[cols]``. Padded entries have weight 0.
    ``order_t (B, E)`` (int64, optional): per shape, the permutation that sorts the edges by
    ``(col, row)``. With edges sorted by ``(row, col)`` and ``order_t`` given (as
    :func:`~torchfmap.nn.collate_shapes` builds them), :func:`spatial_gradient` sorts nothing;
    otherwise it sorts on every call.
    """

    rows: torch.Tensor
    cols: torch.Tensor
    weight_x: torch.Tensor
    weight_y: torch.Tensor
    order_t: torch.Tensor | None = None

    def to(self, *args, **kwargs) -> GradientBatch:
        """Weights follow ``.to(dtype/device)``; indices only move device."""
        moved = [t.to(*args, **kwargs) for t in (self.weight_x, self.weight_y)]
        device = moved[0].device
        order_t = None if self.order_t is None else self.order_t.to(device)
        return GradientBatch(self.rows.to(device), self.cols.to(device), *moved, order_t)


def _csr(crow: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, n: int) -> torch.Tensor:
    with warnings.catch_warnings():  # "sparse CSR support is in beta": the product used here is not
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(crow, cols, values, (n, n))


def _row_pointers(index: torch.Tensor, n: int) -> torch.Tensor:
    crow = torch.zeros(n + 1, dtype=torch.int64, device=index.device)
    crow[1:] = torch.cumsum(torch.bincount(index, minlength=n), 0)
    return crow


class _SparsePairProduct(torch.autograd.Function):
    """``(Gx f, Gy f)`` for CSR ``Gx, Gy (N, N)`` and ``f (N, C)``; the backward applies the
    prebuilt transposes, ``Gxᵀ ∂gx + Gyᵀ ∂gy`` (no gradient to the operators)."""

    @staticmethod
    def forward(ctx, f, Gx, Gy, GxT, GyT):
        ctx.transposes = (GxT, GyT)
        return Gx @ f, Gy @ f

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, dgx, dgy):
        GxT, GyT = ctx.transposes
        return GxT @ dgx + GyT @ dgy, None, None, None, None


def spatial_gradient(f: torch.Tensor, grad: GradientBatch) -> tuple[torch.Tensor, torch.Tensor]:
    """Tangent-frame gradient of per-vertex features: ``(B, V, C) -> ((B, V, C), (B, V, C))``.

    One block-diagonal compressed-sparse-row product for the batch (forward ``G f``, backward
    ``Gᵀ ∂``); the weights are cast to ``f``'s dtype and device. First derivatives only.
    """
    if f.dim() != 3 or grad.rows.shape[0] != f.shape[0]:
        raise ParameterError(
            f"features must be (B, V, C) with B={grad.rows.shape[0]} (the operators' batch), got "
            f"{tuple(f.shape)}. Fix: collate features and operators of the same shapes."
        )
    if grad.rows.numel() and int(max(grad.rows.max(), grad.cols.max())) >= f.shape[1]:
        raise ParameterError(
            f"the gradient operator indexes vertex {int(max(grad.rows.max(), grad.cols.max()))} but "
            f"the features have V={f.shape[1]}. Fix: use the operators precomputed for these meshes."
        )
    B, V, C = f.shape
    N, E = B * V, grad.rows.shape[1]
    offset = V * torch.arange(B, device=f.device)[:, None]  # shape b's vertices are rows bV..bV+V-1
    rows = (grad.rows.to(f.device) + offset).reshape(-1)
    cols = (grad.cols.to(f.device) + offset).reshape(-1)
    wx = grad.weight_x.to(dtype=f.dtype, device=f.device).reshape(-1)
    wy = grad.weight_y.to(dtype=f.dtype, device=f.device).reshape(-1)
    order_t = None
    if grad.order_t is not None:  # per-shape (col, row) orders; the blocks follow each other
        order_t = (grad.order_t.to(f.device) + E * torch.arange(B, device=f.device)[:, None]).reshape(-1)
    key = rows * N + cols
    if key.numel() > 1 and not bool((key[1:] >= key[:-1]).all()):
        by_row = torch.argsort(key)
        rows, cols, wx, wy, order_t = rows[by_row], cols[by_row], wx[by_row], wy[by_row], None
    if order_t is None:
        order_t = torch.argsort(cols * N + rows)
    crow, ccol = _row_pointers(rows, N), _row_pointers(cols, N)
    rows_t = rows[order_t]
    gx, gy = _SparsePairProduct.apply(
        f.reshape(N, C),
        _csr(crow, cols, wx, N),
        _csr(crow, cols, wy, N),
        _csr(ccol, rows_t, wx[order_t], N),
        _csr(ccol, rows_t, wy[order_t], N),
    )
    return gx.reshape(B, V, C), gy.reshape(B, V, C)


def gradient_features(
    gx: torch.Tensor, gy: torch.Tensor, A_re: torch.Tensor, A_im: torch.Tensor
) -> torch.Tensor:
    """DiffusionNet's spatial gradient features: ``tanh(Re(conj(g) ⊙ (A g)))``, ``(B, V, C)``.

    ``g = gx + i gy (B, V, C)`` are tangent-frame gradients and ``A = A_re + i A_im (C, C)`` a
    complex channel mixing, so the result does not depend on the choice of tangent frame (a
    frame rotation multiplies ``g`` by a unit complex number). The ``A_im`` part is the normal
    component of cross products of gradients: it changes sign under a reflection of the
    surface, which is what lets a network tell left from right.
    """
    if gx.shape != gy.shape or A_re.shape != A_im.shape or A_re.shape != (gx.shape[-1], gx.shape[-1]):
        raise ParameterError(
            f"gradients must have equal shapes (B, V, C) and A_re, A_im be (C, C); got {tuple(gx.shape)}, "
            f"{tuple(gy.shape)}, {tuple(A_re.shape)}, {tuple(A_im.shape)}."
        )
    b_re = gx @ A_re.T - gy @ A_im.T
    b_im = gy @ A_re.T + gx @ A_im.T
    return torch.tanh(gx * b_re + gy * b_im)


def basis_like(basis, f: torch.Tensor) -> BasisBatch:
    """``basis`` as a :class:`BasisBatch` in ``f``'s dtype (bases are precomputed in float64
    and cast on use, so float32 features get float32 maps). A module with ``.batch()`` (a
    :class:`~torchfmap.nn.BasisModule`) is accepted.

    Raises:
        ParameterError: not a basis, or a basis on another device than ``f``.
    """
    if not isinstance(basis, BasisBatch) and callable(getattr(basis, "batch", None)):
        basis = basis.batch()
    if not isinstance(basis, BasisBatch):
        raise ParameterError(
            f"expected a BasisBatch, got {type(basis).__name__}. Fix: pass BasisModule.batch() or "
            "ShapeBatch.basis."
        )
    if basis.values.device != f.device:
        raise ParameterError(
            f"the basis is on {basis.values.device}, the features on {f.device}. Fix: move both to "
            "one device (module.to(device), batch.to(device))."
        )
    return basis if basis.values.dtype == f.dtype else basis.to(dtype=f.dtype)


def project(basis: BasisBatch, f: torch.Tensor) -> torch.Tensor:
    """``Φᵀ M f``: ``(B, V, D) -> (B, K, D)``, in ``f``'s dtype."""
    basis = basis_like(basis, f)
    _check_batch(basis, f, "features")
    return basis.values.transpose(-1, -2) @ (basis.mass[..., None] * f)


def reconstruct(basis: BasisBatch, coeffs: torch.Tensor) -> torch.Tensor:
    """``Φ c``: ``(B, K, D) -> (B, V, D)``, in ``coeffs``' dtype."""
    basis = basis_like(basis, coeffs)
    if coeffs.shape[-2] != basis.values.shape[-1]:
        raise ParameterError(
            f"coefficients have K={coeffs.shape[-2]}, the basis has K={basis.values.shape[-1]}."
        )
    return basis.values @ coeffs


def _check_batch(basis: BasisBatch, f: torch.Tensor, name: str, finite: bool = False) -> None:
    if f.dim() != 3 or f.shape[0] != basis.values.shape[0] or f.shape[1] != basis.values.shape[1]:
        raise ParameterError(
            f"{name} must be (B, V, D) = ({basis.values.shape[0]}, {basis.values.shape[1]}, D), got "
            f"{tuple(f.shape)}. Fix: one row per (padded) vertex, the same batch size as the basis."
        )
    if finite and not torch.isfinite(f).all():
        raise ParameterError(f"{name} contain NaN or inf. Fix: check the network's inputs and outputs.")


def fmap_solve(
    feat_x: torch.Tensor,
    feat_y: torch.Tensor,
    basis_x: BasisBatch,
    basis_y: BasisBatch,
    *,
    w_desc: float = 1.0,
    w_lap: float = W_LAP["laplacian"],
    mask: str = "laplacian",
    both: bool = True,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Regularised functional maps from features, differentiable and batched.

    Returns ``(C_xy (B, K_y, K_x), C_yx (B, K_x, K_y) or None)`` in the features' dtype.
    Equal to :func:`torchfmap.fmap.solve_fmap` with the same weights (descriptor + Laplacian
    terms).
    """
    basis_x, basis_y = basis_like(basis_x, feat_x), basis_like(basis_y, feat_y)
    if basis_x.values.shape[0] != basis_y.values.shape[0]:
        raise ParameterError(
            f"batch sizes differ: {basis_x.values.shape[0]} x-shapes and {basis_y.values.shape[0]} y-shapes. "
            "Fix: collate x and y of the same pairs together."
        )
    if feat_x.shape[-1] != feat_y.shape[-1]:
        raise ParameterError(f"feature dimensions differ: {feat_x.shape[-1]} vs {feat_y.shape[-1]}.")
    A_x, A_y = project(basis_x, feat_x), project(basis_y, feat_y)
    # a non-finite feature (even at a padded vertex: NaN * 0 = NaN) makes its projection
    # non-finite, so checking the small (B, K, D) projections is enough and ~100x cheaper
    for A, feat, basis in ((A_x, feat_x, basis_x), (A_y, feat_y, basis_y)):
        if not bool(torch.isfinite(A).all()):
            _check_batch(basis, feat, "features", finite=True)
            raise ParameterError(
                "the projected features overflow (finite features, non-finite Φᵀ M f). Fix: scale "
                "the features down (e.g. normalise them)."
            )
    valid_xy = basis_y.valid[..., :, None] * basis_x.valid[..., None, :]
    if bool((valid_xy == 1).all()):
        valid_xy = None  # no padding: skip the masking work
    C_xy = core.rotate_and_solve(
        A_x,
        A_y,
        basis_x.lam,
        basis_x.U,
        basis_y.lam,
        basis_y.U,
        w_desc=w_desc,
        w_lap=w_lap,
        mask=mask,
        valid=valid_xy,
    )
    C_yx = None
    if both:
        C_yx = core.rotate_and_solve(
            A_y,
            A_x,
            basis_y.lam,
            basis_y.U,
            basis_x.lam,
            basis_x.U,
            w_desc=w_desc,
            w_lap=w_lap,
            mask=mask,
            valid=None if valid_xy is None else valid_xy.transpose(-1, -2),
        )
    return C_xy, C_yx


def soft_map(
    feat_x: torch.Tensor,
    feat_y: torch.Tensor,
    *,
    tau: float = 0.07,
    mass_x: torch.Tensor | None = None,
    sinkhorn_iters: int = 0,
) -> torch.Tensor:
    """Soft point map ``Π_yx (B, V_y, V_x)``: row ``v`` is a distribution over vertices of ``x``.

    Softmax of cosine similarity / ``tau``; padded vertices of ``x`` (``mass_x == 0``) get no
    weight. ``sinkhorn_iters > 0`` alternates row and column normalisation (log domain).

    Raises :class:`ParameterError` unless ``tau`` is finite and > 0.
    """
    return _normalise_soft(_similarity(feat_x, feat_y, tau), mass_x, sinkhorn_iters)


def soft_maps(
    feat_x: torch.Tensor,
    feat_y: torch.Tensor,
    *,
    tau: float = 0.07,
    mass_x: torch.Tensor | None = None,
    mass_y: torch.Tensor | None = None,
    sinkhorn_iters: int = 0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Both directions, ``(Π_yx (B, V_y, V_x), Π_xy (B, V_x, V_y))``, from one similarity
    matrix: equal to two :func:`soft_map` calls at about half the cost of the products.

    Raises :class:`ParameterError` unless ``tau`` is finite and > 0.
    """
    logits = _similarity(feat_x, feat_y, tau)
    return (
        _normalise_soft(logits, mass_x, sinkhorn_iters),
        _normalise_soft(logits.transpose(-1, -2), mass_y, sinkhorn_iters),
    )


def _similarity(feat_x: torch.Tensor, feat_y: torch.Tensor, tau: float) -> torch.Tensor:
    """Cosine similarity over ``tau``: ``(B, V_y, V_x)``."""
    if not (isinstance(tau, (int, float)) and 0 < tau < float("inf")):
        raise ParameterError(f"tau must be finite and > 0, got {tau!r}. Fix: e.g. tau=0.07.")
    fx = torch.nn.functional.normalize(feat_x, dim=-1)
    fy = torch.nn.functional.normalize(feat_y, dim=-1)
    return fy @ fx.transpose(-1, -2) / tau


def _normalise_soft(logits: torch.Tensor, mass_x: torch.Tensor | None, sinkhorn_iters: int) -> torch.Tensor:
    """Row softmax (then Sinkhorn) of ``logits (B, V_y, V_x)``, columns with ``mass_x <= 0`` excluded."""
    padded = None if mass_x is None else (mass_x <= 0)[..., None, :]  # (B, 1, V_x)
    if padded is not None and not bool(padded.any()):
        padded = None  # nothing to mask: skip the (B, V_y, V_x) fill
    if padded is not None:
        logits = logits.masked_fill(padded, float("-inf"))
    log_p = torch.log_softmax(logits, dim=-1)
    for _ in range(sinkhorn_iters):
        # padded columns hold only -inf: normalise the others, leave those (a finite stand-in
        # keeps logsumexp's gradient finite; torch.where routes no gradient through it)
        safe = log_p if padded is None else torch.where(padded, torch.zeros_like(log_p), log_p)
        col = torch.logsumexp(safe, dim=-2, keepdim=True)
        if padded is not None:
            col = torch.where(padded, torch.zeros_like(col), col)
        log_p = torch.log_softmax(log_p - col, dim=-1)
    return log_p.exp()


def soft_map_to_fmap(pi_yx: torch.Tensor, basis_x: BasisBatch, basis_y: BasisBatch) -> torch.Tensor:
    """``C_xy = Φ_yᵀ M_y Π_yx Φ_x``: ``(B, K_y, K_x)``."""
    return basis_y.values.transpose(-1, -2) @ (basis_y.mass[..., None] * (pi_yx @ basis_x.values))


# -- losses ------------------------------------------------------------------------------------
def _valid_eye(valid: torch.Tensor) -> torch.Tensor:
    return torch.diag_embed(valid)


def orthogonality_loss(C_xy: torch.Tensor, valid_x: torch.Tensor | None = None) -> torch.Tensor:
    """``mean_b ‖C_xyᵀ C_xy - I‖²_F`` (area preservation)."""
    eye = (
        _valid_eye(valid_x)
        if valid_x is not None
        else torch.eye(C_xy.shape[-1], dtype=C_xy.dtype, device=C_xy.device)
    )
    return ((C_xy.transpose(-1, -2) @ C_xy - eye) ** 2).sum(dim=(-2, -1)).mean()


def bijectivity_loss(C_xy: torch.Tensor, C_yx: torch.Tensor, valid_x=None, valid_y=None) -> torch.Tensor:
    """``mean_b ‖C_yx C_xy - I‖² + ‖C_xy C_yx - I‖²``."""
    kx, ky = C_xy.shape[-1], C_xy.shape[-2]
    ex = _valid_eye(valid_x) if valid_x is not None else torch.eye(kx, dtype=C_xy.dtype, device=C_xy.device)
    ey = _valid_eye(valid_y) if valid_y is not None else torch.eye(ky, dtype=C_xy.dtype, device=C_xy.device)
    a = ((C_yx @ C_xy - ex) ** 2).sum(dim=(-2, -1))
    b = ((C_xy @ C_yx - ey) ** 2).sum(dim=(-2, -1))
    return (a + b).mean()


def laplacian_commutativity_loss(
    C_xy: torch.Tensor, basis_x: BasisBatch, basis_y: BasisBatch
) -> torch.Tensor:
    """``mean_b ‖C W_x - W_y C‖² / ‖W‖²`` (scale-free)."""
    Wx, Wy = basis_x.W, basis_y.W
    scale = 0.5 * ((Wx**2).sum(dim=(-2, -1)) + (Wy**2).sum(dim=(-2, -1))) / C_xy.shape[-1]
    return (((C_xy @ Wx - Wy @ C_xy) ** 2).sum(dim=(-2, -1)) / scale.clip(min=1e-300)).mean()


def coupling_loss(
    C_xy: torch.Tensor, pi_yx: torch.Tensor, basis_x: BasisBatch, basis_y: BasisBatch
) -> torch.Tensor:
    """``mean_b ‖C_xy - Φ_yᵀ M_y Π_yx Φ_x‖²``: the functional map agrees with the soft point map."""
    return ((C_xy - soft_map_to_fmap(pi_yx, basis_x, basis_y)) ** 2).sum(dim=(-2, -1)).mean()


def geodesic_loss(pi_yx: torch.Tensor, idx_y: torch.Tensor, dist_rows: torch.Tensor) -> torch.Tensor:
    """Supervised: expected geodesic error ``mean Σ_x Π[idx_y, x] d_x(x, gt)``.

    Args:
        pi_yx: ``(B, V_y, V_x)`` soft map.
        idx_y: ``(B, P)`` target vertices with known ground truth.
        dist_rows: ``(B, P, V_x)`` geodesic distances on ``x`` from the true match of each.
    """
    rows = torch.gather(pi_yx, 1, idx_y[..., None].expand(-1, -1, pi_yx.shape[-1]))
    return (rows * dist_rows).sum(dim=-1).mean()
