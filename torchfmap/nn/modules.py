"""``torch.nn.Module`` layers: settings and buffers over :mod:`torchfmap.nn.functional`."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from .._util.checks import check_lumped_mass
from ..bases import prepare_shape
from ..bases.basis import Basis
from ..errors import ParameterError
from ..fmap import core
from ..fmap.defaults import DEFAULT_K, W_LAP_SMOOTH
from ..kinds import learned_kind
from ..mesh import Mesh
from . import functional as F
from .functional import BasisBatch


def basis_arrays(basis: Basis) -> dict[str, np.ndarray]:
    """Numpy arrays of a B-orthonormal basis for the torch side, in its mesh's unit-area frame (a mesh of area
    ``A`` as ``mesh.scaled(1 / sqrt(A))``): ``values (V, K)``, lumped ``mass (V,)`` summing to 1, spectral
    frame ``lam (K,)``, ``U (K, K)`` of ``W = Φᵀ L Φ``.

    Raises:
        ParameterError: a basis that is not B-orthonormal, has no stiffness, or a mass not lumped or empty."""
    if not basis.orthonormal:
        raise ParameterError("the basis must be B-orthonormal. Fix: orthonormalize(basis) first.")
    mass = np.asarray(check_lumped_mass(basis.mass, "torch layers"), dtype=np.float64)
    if basis.stiffness is None:
        raise ParameterError("the basis needs its stiffness matrix (for W = Φᵀ L Φ).")
    area = float(mass.sum())
    if not np.isfinite(area) or area <= 0:
        raise ParameterError(f"the basis' mass sums to {area}, not an area. Fix: check its mass matrix.")
    lam, U = core.spectral_frame(core.as_tensor(basis.projected_laplacian()))
    return dict(values=basis.values * np.sqrt(area), mass=mass / area, lam=lam.numpy() * area, U=U.numpy())


class BasisModule(nn.Module):
    """A basis as buffers ``values (V, K)``, ``mass (V,)``, ``lam (K,)``, ``U (K, K)``
    (``W = U diag(lam) Uᵀ``) in ``dtype``, cast by layers on use; ``forward()`` is :meth:`batch`."""

    BUFFERS = ("values", "mass", "lam", "U")

    def __init__(self, basis: Basis, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        for name, array in basis_arrays(basis).items():
            self.register_buffer(name, torch.as_tensor(array, dtype=dtype))

    @classmethod
    def from_state_dict(cls, state: dict) -> BasisModule:
        """Rebuild from :meth:`state_dict`; :class:`ParameterError` if buffers are missing or misfit."""
        missing = [name for name in cls.BUFFERS if name not in state]
        if missing:
            raise ParameterError(f"state_dict lacks {missing}. Fix: pass a BasisModule's state_dict().")
        V, K = state["values"].shape
        if state["mass"].shape != (V,) or state["lam"].shape != (K,) or state["U"].shape != (K, K):
            raise ParameterError(
                "state_dict buffers do not fit: values (V, K), mass (V,), lam (K,), U (K, K) expected."
            )
        out = cls.__new__(cls)
        nn.Module.__init__(out)
        for name in cls.BUFFERS:
            out.register_buffer(name, state[name].clone())
        return out

    def extra_repr(self) -> str:
        return f"V={self.values.shape[0]}, K={self.k}, dtype={self.values.dtype}, device={self.values.device}"

    def forward(self) -> BasisBatch:
        """This basis as a batch of one (:meth:`batch`)."""
        return self.batch()

    @classmethod
    def from_mesh(
        cls,
        mesh: Mesh,
        k: int = DEFAULT_K,
        basis: str = "laplacian",
        seeds=None,
        times=None,
        dtype=torch.float64,
    ) -> BasisModule:
        """A registered kind's basis (``basis``, :data:`torchfmap.bases.KINDS`) of ``k`` columns on
        ``mesh``, seeded at ``seeds`` then farthest points, diffused at relative ``times``. Raises
        :class:`ParameterError`: an unknown kind, or fewer than ``k`` independent columns."""
        kind = learned_kind(basis)
        return cls(kind.shape_basis(prepare_shape(mesh, 0), k, seeds=seeds, times=times), dtype)

    @property
    def k(self) -> int:
        return self.values.shape[1]

    def truncated(self, k: int) -> BasisModule:
        """The first ``k`` functions (frame recomputed)."""
        if not 1 <= k <= self.k:
            raise ParameterError(f"k={k} is outside [1, {self.k}] for this basis. Fix: build a larger basis.")
        out = BasisModule.__new__(BasisModule)
        nn.Module.__init__(out)
        W = self.U @ torch.diag(self.lam) @ self.U.T
        lam, U = core.spectral_frame(W[:k, :k])
        for name, t in (("values", self.values[:, :k]), ("mass", self.mass), ("lam", lam), ("U", U)):
            out.register_buffer(name, t.clone())
        return out

    def batch(self) -> BasisBatch:
        """This basis as a batch of one."""
        valid = torch.ones(self.k, dtype=self.values.dtype, device=self.values.device)
        return BasisBatch(self.values[None], self.mass[None], self.lam[None], self.U[None], valid[None])

    def project(self, f: torch.Tensor) -> torch.Tensor:
        """``(V, D) -> (K, D)`` or ``(1, V, D) -> (1, K, D)``."""
        single = f.dim() == 2
        out = F.project(self.batch(), f[None] if single else f)
        return out[0] if single else out

    def reconstruct(self, c: torch.Tensor) -> torch.Tensor:
        single = c.dim() == 2
        out = F.reconstruct(self.batch(), c[None] if single else c)
        return out[0] if single else out


class RegularizedFMSolver(nn.Module):
    """Differentiable batched functional-map solver for B-orthonormal bases, ``forward(feat_x (B, V_x, D),
    feat_y (B, V_y, D), basis_x, basis_y)`` -> ``(C_xy (B, K_y, K_x), C_yx (B, K_x, K_y))`` (``C_yx`` None
    unless ``both``). Defaults as :func:`torchfmap.fmap.solve_fmap` for eigenbases (diffusion bases:
    ``w_lap=W_LAP_KERNELS``); ``check`` as :func:`~torchfmap.nn.functional.solve_fmap_batch`."""

    def __init__(
        self,
        w_desc: float = 1.0,
        w_lap: float = W_LAP_SMOOTH,
        mask: str = "laplacian",
        both: bool = True,
        check: bool | None = None,
    ):
        super().__init__()
        F.check_solver_weights(w_desc, w_lap)  # the function's own check, early
        self.w_desc, self.w_lap, self.mask, self.both, self.check = w_desc, w_lap, mask, both, check

    def forward(self, feat_x, feat_y, basis_x: BasisBatch, basis_y: BasisBatch) -> F.FmapPair:
        """``(feat_x (B, V_x, D), feat_y (B, V_y, D), bases) -> FmapPair(C_xy (B, K_y, K_x), C_yx)``;
        bases may be :class:`BasisModule` s (cast to the features' dtype)."""
        opts = dict(w_desc=self.w_desc, w_lap=self.w_lap, mask=self.mask, both=self.both, check=self.check)
        return F.solve_fmap_batch(feat_x, feat_y, basis_x, basis_y, **opts)


class SoftPointMap(nn.Module):
    """Soft map ``Π_yx (B, V_y, V_x)`` from features (:func:`~torchfmap.nn.functional.soft_map`)."""

    def __init__(self, tau: float = 0.07, sinkhorn_iters: int = 0, check: bool | None = None) -> None:
        super().__init__()
        self.tau, self.sinkhorn_iters, self.check = tau, sinkhorn_iters, check

    def forward(self, feat_x, feat_y, lengths_x=None):
        """``(feat_x (B, V_x, D), feat_y (B, V_y, D)) -> Π_yx (B, V_y, V_x)``, 0 beyond ``lengths_x``."""
        opts = dict(tau=self.tau, sinkhorn_iters=self.sinkhorn_iters, check=self.check)
        return F.soft_map(feat_x, feat_y, lengths_x=lengths_x, **opts)

    def both(self, feat_x, feat_y, lengths_x=None, lengths_y=None) -> F.SoftMaps:
        """``SoftMaps(Π_yx, Π_xy)`` from one similarity (:func:`~torchfmap.nn.functional.soft_maps`)."""
        opts = dict(tau=self.tau, sinkhorn_iters=self.sinkhorn_iters, check=self.check)
        return F.soft_maps(feat_x, feat_y, lengths_x=lengths_x, lengths_y=lengths_y, **opts)


class UnsupervisedFMLoss(nn.Module):
    """``w_bij·bijectivity + w_orth·orthogonality + w_lap·Laplacian commutativity + w_couple·coupling``;
    with ``n_samples > 0`` the coupling compares maps on that many random vertices per shape, drawn from
    :meth:`forward`'s ``generator``."""

    def __init__(
        self,
        w_bij=1.0,
        w_orth=1.0,
        w_lap=0.0,
        w_couple=1.0,
        tau: float = 0.07,
        n_samples: int = 0,
        check: bool | None = None,
    ) -> None:
        super().__init__()
        if n_samples < 0:
            raise ParameterError(f"n_samples must be >= 0, got {n_samples}.")
        self.w = dict(bij=w_bij, orth=w_orth, lap=w_lap, couple=w_couple)
        self.soft, self.n_samples = SoftPointMap(tau, check=check), n_samples

    def _samples(
        self, basis: BasisBatch, feats: torch.Tensor, generator: torch.Generator | None
    ) -> tuple[BasisBatch, torch.Tensor]:
        """A sorted random subset of vertices (real ones stay first), its mass rescaled to the total."""
        V = feats.shape[1]
        if not self.n_samples or V <= self.n_samples:
            return basis, feats
        if generator is None:
            raise ParameterError(
                f"the coupling term samples {self.n_samples} random vertices and needs a generator. Fix: "
                "loss(..., generator=torch.Generator().manual_seed(0)) (the Trainer passes its own), or "
                "n_samples=0."
            )
        idx = torch.randperm(V, generator=generator, device=generator.device)[: self.n_samples]
        idx = idx.to(feats.device).sort().values
        mass = basis.mass[:, idx]
        mass = mass * (basis.mass.sum(dim=1, keepdim=True) / mass.sum(dim=1, keepdim=True).clip(min=1e-30))
        lengths = None if basis.lengths is None else (idx < basis.lengths[:, None]).sum(dim=1)
        return BasisBatch(basis.values[:, idx], mass, basis.lam, basis.U, basis.valid, lengths), feats[:, idx]

    def forward(
        self,
        C_xy,
        C_yx,
        feat_x,
        feat_y,
        basis_x: BasisBatch,
        basis_y: BasisBatch,
        *,
        generator: torch.Generator | None = None,
    ) -> dict[str, torch.Tensor]:
        """The weighted terms and their ``'total'``; :class:`ParameterError` if sampling without generator."""
        terms = {
            "bij": F.bijectivity_loss(C_xy, C_yx, basis_x.valid, basis_y.valid),
            "orth": F.orthogonality_loss(C_xy, basis_x.valid) + F.orthogonality_loss(C_yx, basis_y.valid),
        }
        if self.w["lap"]:
            terms["lap"] = F.laplacian_commutativity_loss(C_xy, basis_x, basis_y)
        if self.w["couple"]:
            sub_x, rows_x = self._samples(basis_x, feat_x, generator)
            sub_y, rows_y = self._samples(basis_y, feat_y, generator)
            pi_yx, pi_xy = self.soft.both(rows_x, rows_y, sub_x.lengths, sub_y.lengths)
            terms["couple"] = F.coupling_loss(C_xy, pi_yx, sub_x, sub_y) + F.coupling_loss(
                C_yx, pi_xy, sub_y, sub_x
            )
        terms["total"] = sum(self.w[name] * value for name, value in terms.items())
        return terms


class SpectralDiffusion(nn.Module):
    """Learned per-channel diffusion ``x -> Φ U exp(-t λ) Uᵀ Φᵀ M x`` in any B-orthonormal basis."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.log_t = nn.Parameter(torch.full((channels,), -4.0))

    def forward(self, x: torch.Tensor, basis: BasisBatch) -> torch.Tensor:
        """``x (B, V, C) -> (B, V, C)`` diffused, in ``x``'s dtype."""
        basis = F.basis_like(basis, x)
        coef = basis.U.transpose(-1, -2) @ F.project(basis, x)  # (B, K, C)
        decay = torch.exp(-basis.lam.clip(min=0)[..., None] * self.log_t.exp())  # (B, K, C)
        return F.reconstruct(basis, basis.U @ (decay * coef))
