"""Differentiable functional-map operations on padded batches of ``B`` pairs, ``V`` vertices, ``K`` basis
functions, ``D`` channels (the classical :func:`torchfmap.fmap.core.rotate_and_solve`;
:mod:`torchfmap.nn.gradients` re-exported). ``check``: :mod:`torchfmap._util.torch_checks`."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from .._util.torch_checks import check_batched, check_finite, check_index_range, check_lengths, resolve_check
from ..errors import ParameterError
from ..fmap import core
from ..fmap.defaults import W_LAP_SMOOTH
from .gradients import GradientBatch, TangentGradient, gradient_features, spatial_gradient

__all__ = [
    "BasisBatch", "FmapPair", "GradientBatch", "SoftMaps", "TangentGradient", "basis_like",
    "bijectivity_loss", "coupling_loss", "solve_fmap_batch", "geodesic_loss", "gradient_features",
    "laplacian_commutativity_loss", "orthogonality_loss", "project", "reconstruct", "soft_map",
    "soft_map_to_fmap", "soft_maps", "spatial_gradient", "vertex_mask",
]  # fmt: skip


def vertex_mask(lengths: torch.Tensor | None, n_vertices: int) -> torch.Tensor | None:
    """``(B, V)`` bool, True on the first ``lengths[b]`` (real) vertices; None for None."""
    if lengths is None:
        return None
    return torch.arange(n_vertices, device=lengths.device) < lengths[:, None]


class BasisBatch(NamedTuple):
    """A padded batch of bases (:func:`~torchfmap.nn.collate_shapes`): ``values (B, V, K)``, lumped
    ``mass (B, V)``, spectral frame ``lam (B, K)``, ``U (B, K, K)`` of ``W = U diag(lam) Uᵀ``,
    ``valid (B, K)``, ``lengths (B,)`` (int64 or None).

    Shape ``b`` has ``lengths[b]`` real vertices, the first ones (None: all), and real columns where
    ``valid[b] == 1``; padded entries (zero values, mass and ``lam``, identity in ``U``) change no map."""

    values: torch.Tensor
    mass: torch.Tensor
    lam: torch.Tensor
    U: torch.Tensor
    valid: torch.Tensor
    lengths: torch.Tensor | None = None

    @property
    def W(self) -> torch.Tensor:
        """``(B, K, K)`` projected Laplacian ``U diag(lam) Uᵀ``."""
        return self.U @ (self.lam[..., None] * self.U.transpose(-1, -2))

    @property
    def vertex_mask(self) -> torch.Tensor | None:
        """``(B, V)`` bool, True on real vertices (from :attr:`lengths`); None when none is padded."""
        return vertex_mask(self.lengths, self.values.shape[1])

    def to(self, *args, **kwargs) -> BasisBatch:
        """Floats follow ``.to(dtype/device)``; ``lengths`` only moves device."""
        floats = [t.to(*args, **kwargs) for t in self[:5]]
        lengths = None if self.lengths is None else self.lengths.to(floats[0].device)
        return BasisBatch(*floats, lengths)


class FmapPair(NamedTuple):
    """Result of :func:`solve_fmap_batch`: ``C_xy (B, K_y, K_x)`` and ``C_yx (B, K_x, K_y)`` (or None)."""

    C_xy: torch.Tensor
    C_yx: torch.Tensor | None


class SoftMaps(NamedTuple):
    """Result of :func:`soft_maps`: ``pi_yx (B, V_y, V_x)`` and ``pi_xy (B, V_x, V_y)``."""

    pi_yx: torch.Tensor
    pi_xy: torch.Tensor


def basis_like(basis, f: torch.Tensor) -> BasisBatch:
    """``basis`` (or a module's ``.batch()``) as a :class:`BasisBatch` in ``f``'s dtype. Raises
    :class:`ParameterError`: not a basis, or a basis on another device than ``f``."""
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
    check_batched(f, basis.values.shape[0], basis.values.shape[1], "features")
    return basis.values.transpose(-1, -2) @ (basis.mass[..., None] * f)


def reconstruct(basis: BasisBatch, coeffs: torch.Tensor) -> torch.Tensor:
    """``Φ c``: ``(B, K, D) -> (B, V, D)``, in ``coeffs``' dtype."""
    basis = basis_like(basis, coeffs)
    if coeffs.shape[-2] != basis.values.shape[-1]:
        raise ParameterError(
            f"coefficients have K={coeffs.shape[-2]}, the basis has K={basis.values.shape[-1]}."
        )
    return basis.values @ coeffs


def check_solver_weights(w_desc: float, w_lap: float) -> None:
    """The solver's weights: finite, ``w_desc > 0``, ``w_lap >= 0`` (else :class:`ParameterError`)."""
    try:
        ok = all(not isinstance(w, bool) and math.isfinite(float(w)) for w in (w_desc, w_lap))
    except (TypeError, ValueError):
        ok = False
    if not ok or float(w_desc) <= 0 or float(w_lap) < 0:
        raise ParameterError(
            f"solver weights must be finite with w_desc > 0 and w_lap >= 0; got w_desc={w_desc!r}, "
            f"w_lap={w_lap!r}. Fix: e.g. w_desc=1, w_lap=1e-3."
        )


def solve_fmap_batch(
    feat_x: torch.Tensor,
    feat_y: torch.Tensor,
    basis_x: BasisBatch,
    basis_y: BasisBatch,
    *,
    w_desc: float = 1.0,
    w_lap: float = W_LAP_SMOOTH,
    mask: str = "laplacian",
    both: bool = True,
    check: bool | None = None,
) -> FmapPair:
    """Regularised functional maps from features, differentiable and batched (as
    :func:`torchfmap.fmap.solve_fmap`): :class:`FmapPair` ``(C_xy (B, K_y, K_x), C_yx or None)`` in the
    features' dtype, 0 on padded columns.

    Raises:
        ParameterError: weights not finite with ``w_desc > 0``, ``w_lap >= 0``; shapes that do not fit;
            with ``check``, non-finite features or projections, or singular systems."""
    check_solver_weights(w_desc, w_lap)
    basis_x, basis_y = basis_like(basis_x, feat_x), basis_like(basis_y, feat_y)
    if basis_x.values.shape[0] != basis_y.values.shape[0]:
        raise ParameterError(
            f"batch sizes differ: {basis_x.values.shape[0]} x-shapes and {basis_y.values.shape[0]} y-shapes. "
            "Fix: collate x and y of the same pairs together."
        )
    if feat_x.shape[-1] != feat_y.shape[-1]:
        raise ParameterError(f"feature dimensions differ: {feat_x.shape[-1]} vs {feat_y.shape[-1]}.")
    check = resolve_check(check, feat_x)
    A_x, A_y = project(basis_x, feat_x), project(basis_y, feat_y)
    if check:
        # a non-finite feature (even padded: NaN * 0 = NaN) makes its projection non-finite: check those
        for A, feat in ((A_x, feat_x), (A_y, feat_y)):
            if not bool(torch.isfinite(A).all()):
                check_finite(feat, "features", "check the network's inputs and outputs.")
                raise ParameterError(
                    "the projected features overflow (finite features, non-finite Φᵀ M f). Fix: scale "
                    "the features down (e.g. normalise them)."
                )
    valid_xy = basis_y.valid[..., :, None] * basis_x.valid[..., None, :]
    frames = (basis_x.lam, basis_x.U, basis_y.lam, basis_y.U)
    options = dict(w_desc=w_desc, w_lap=w_lap, mask=mask, check=check)
    C_xy = core.rotate_and_solve(A_x, A_y, *frames, valid=valid_xy, **options)
    C_yx = None
    if both:
        frames_yx = (basis_y.lam, basis_y.U, basis_x.lam, basis_x.U)
        C_yx = core.rotate_and_solve(A_y, A_x, *frames_yx, valid=valid_xy.transpose(-1, -2), **options)
    return FmapPair(C_xy, C_yx)


def soft_map(
    feat_x: torch.Tensor,
    feat_y: torch.Tensor,
    *,
    tau: float = 0.07,
    lengths_x: torch.Tensor | None = None,
    sinkhorn_iters: int = 0,
    check: bool | None = None,
) -> torch.Tensor:
    """Soft point map ``Π_yx (B, V_y, V_x)``: softmax over ``x`` of cosine similarity / ``tau``, no weight
    beyond ``lengths_x (B,)``; ``sinkhorn_iters > 0`` alternates row and column normalisation. Raises
    :class:`ParameterError` unless ``tau`` is finite and > 0, for features of mismatched shapes, and
    (``check``) for vertex counts outside ``[1, V_x]``."""
    _check_soft(feat_x, feat_y, lengths_x, None, check)
    return _normalise_soft(_similarity(feat_x, feat_y, tau), lengths_x, sinkhorn_iters)


def soft_maps(
    feat_x: torch.Tensor,
    feat_y: torch.Tensor,
    *,
    tau: float = 0.07,
    lengths_x: torch.Tensor | None = None,
    lengths_y: torch.Tensor | None = None,
    sinkhorn_iters: int = 0,
    check: bool | None = None,
) -> SoftMaps:
    """:class:`SoftMaps` ``(Π_yx, Π_xy)`` from one similarity: two :func:`soft_map` calls, raising alike."""
    _check_soft(feat_x, feat_y, lengths_x, lengths_y, check)
    logits = _similarity(feat_x, feat_y, tau)
    return SoftMaps(
        _normalise_soft(logits, lengths_x, sinkhorn_iters),
        _normalise_soft(logits.transpose(-1, -2), lengths_y, sinkhorn_iters),
    )


def _check_soft(feat_x, feat_y, lengths_x, lengths_y, check: bool | None) -> None:
    if feat_x.dim() != 3 or feat_y.dim() != 3 or feat_x.shape[::2] != feat_y.shape[::2]:
        raise ParameterError(
            f"features must be (B, V_x, D) and (B, V_y, D), got {tuple(feat_x.shape)} and "
            f"{tuple(feat_y.shape)}. Fix: the same batch size and channels on both sides."
        )
    check = resolve_check(check, feat_x)
    check_lengths(lengths_x, feat_x.shape[0], feat_x.shape[1], "lengths_x", check)
    check_lengths(lengths_y, feat_y.shape[0], feat_y.shape[1], "lengths_y", check)


def _similarity(feat_x: torch.Tensor, feat_y: torch.Tensor, tau: float) -> torch.Tensor:
    """Cosine similarity over ``tau``: ``(B, V_y, V_x)``."""
    if not (isinstance(tau, (int, float)) and 0 < tau < float("inf")):
        raise ParameterError(f"tau must be finite and > 0, got {tau!r}. Fix: e.g. tau=0.07.")
    fx, fy = (torch.nn.functional.normalize(f, dim=-1) for f in (feat_x, feat_y))
    return fy @ fx.transpose(-1, -2) / tau


def _normalise_soft(
    logits: torch.Tensor, lengths_x: torch.Tensor | None, sinkhorn_iters: int
) -> torch.Tensor:
    """Row softmax (then Sinkhorn) of ``logits (B, V_y, V_x)``, columns beyond ``lengths_x`` excluded."""
    real = vertex_mask(lengths_x, logits.shape[-1])
    padded = None if real is None else ~real[..., None, :]  # (B, 1, V_x)
    if padded is not None:
        logits = logits.masked_fill(padded, float("-inf"))
    log_p = torch.log_softmax(logits, dim=-1)
    for _ in range(sinkhorn_iters):
        # padded columns hold only -inf: a finite stand-in keeps logsumexp's gradient finite
        safe = log_p if padded is None else torch.where(padded, torch.zeros_like(log_p), log_p)
        col = torch.logsumexp(safe, dim=-2, keepdim=True)
        if padded is not None:
            col = torch.where(padded, torch.zeros_like(col), col)
        log_p = torch.log_softmax(log_p - col, dim=-1)
    return log_p.exp()


def soft_map_to_fmap(pi_yx: torch.Tensor, basis_x: BasisBatch, basis_y: BasisBatch) -> torch.Tensor:
    """``C_xy = Φ_yᵀ M_y Π_yx Φ_x``: ``(B, K_y, K_x)``."""
    return basis_y.values.transpose(-1, -2) @ (basis_y.mass[..., None] * (pi_yx @ basis_x.values))


def _valid_eye(valid: torch.Tensor | None, k: int, like: torch.Tensor) -> torch.Tensor:
    """``diag(valid)`` (the identity on a batch's valid columns), or ``I_k`` without padding."""
    return torch.eye(k, dtype=like.dtype, device=like.device) if valid is None else torch.diag_embed(valid)


def orthogonality_loss(C_xy: torch.Tensor, valid_x: torch.Tensor | None = None) -> torch.Tensor:
    """``mean_b ‖C_xyᵀ C_xy - I‖²_F`` (area preservation)."""
    eye = _valid_eye(valid_x, C_xy.shape[-1], C_xy)
    return ((C_xy.transpose(-1, -2) @ C_xy - eye) ** 2).sum(dim=(-2, -1)).mean()


def bijectivity_loss(C_xy: torch.Tensor, C_yx: torch.Tensor, valid_x=None, valid_y=None) -> torch.Tensor:
    """``mean_b ‖C_yx C_xy - I‖² + ‖C_xy C_yx - I‖²``."""
    ex, ey = _valid_eye(valid_x, C_xy.shape[-1], C_xy), _valid_eye(valid_y, C_xy.shape[-2], C_xy)
    a, b = ((C_yx @ C_xy - ex) ** 2).sum(dim=(-2, -1)), ((C_xy @ C_yx - ey) ** 2).sum(dim=(-2, -1))
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


def geodesic_loss(
    pi_yx: torch.Tensor, idx_y: torch.Tensor, dist_rows: torch.Tensor, *, check: bool | None = None
) -> torch.Tensor:
    """Supervised expected geodesic error ``mean Σ_x Π[idx_y, x] d_x(x, gt)`` of ``pi_yx (B, V_y, V_x)`` at
    target vertices ``idx_y (B, P)`` with distances ``dist_rows (B, P, V_x)`` from their true matches;
    :class:`ParameterError` for shapes that do not fit or (``check``) ``idx_y`` outside ``[0, V_y)``."""
    B, V_y, V_x = pi_yx.shape
    if idx_y.dim() != 2 or idx_y.shape[0] != B or dist_rows.shape != (B, idx_y.shape[1], V_x):
        raise ParameterError(
            f"idx_y must be (B, P) and dist_rows (B, P, V_x) for pi_yx {tuple(pi_yx.shape)}, got "
            f"{tuple(idx_y.shape)} and {tuple(dist_rows.shape)}."
        )
    if resolve_check(check, pi_yx):
        check_index_range(idx_y, V_y, "idx_y", "ground-truth vertices are 0-based vertices of y.")
    rows = torch.gather(pi_yx, 1, idx_y[..., None].expand(-1, -1, V_x))
    return (rows * dist_rows).sum(dim=-1).mean()
