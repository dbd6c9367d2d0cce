"""``torch.nn.Module`` layers: thin wrappers that hold settings / buffers and call
:mod:`torchfmap.nn.functional` (which calls the same solver code as the classical path)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
from torch import nn

from .._checks import check_lumped_mass
from ..bases import basis_stack, laplacian_eigenbasis
from ..bases.basis import Basis
from ..errors import ParameterError
from ..fmap import core
from ..fmap.defaults import W_LAP
from ..mesh import Mesh
from . import functional as F
from .functional import BasisBatch


def basis_arrays(basis: Basis) -> dict[str, np.ndarray]:
    """Numpy arrays of a B-orthonormal basis for the torch side: values, lumped mass, frame."""
    if not basis.orthonormal:
        raise ParameterError("the basis must be B-orthonormal. Fix: orthonormalize(basis) first.")
    mass = sp.csr_matrix(basis.mass)
    check_lumped_mass(mass, "torch layers")
    if basis.stiffness is None:
        raise ParameterError("the basis needs its stiffness matrix (for W = Φᵀ L Φ).")
    lam, U = core.spectral_frame(core.as_tensor(basis.projected_laplacian()))
    return {"values": basis.values, "mass": mass.diagonal().copy(), "lam": lam.numpy(), "U": U.numpy()}


class BasisModule(nn.Module):
    """A precomputed basis as buffers (moves with ``.to()``, saved in ``state_dict``):
    ``values (V, K)``, ``mass (V,)``, ``lam (K,)``, ``U (K, K)`` with
    ``W = U diag(lam) Uᵀ = Φᵀ L Φ``. Kept in float64 (``dtype``); layers cast it to their
    input's dtype on use. ``forward()`` returns :meth:`batch`.
    """

    BUFFERS = ("values", "mass", "lam", "U")

    def __init__(self, basis: Basis, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        for name, array in basis_arrays(basis).items():
            self.register_buffer(name, torch.as_tensor(array, dtype=dtype))

    @classmethod
    def from_state_dict(cls, state: dict) -> BasisModule:
        """Rebuild from :meth:`state_dict` alone (no mesh, no :class:`Basis`).

        Raises:
            ParameterError: a buffer is missing or the shapes do not fit together.
        """
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
    def from_mesh(cls, mesh: Mesh, k: int = 50, kind: str = "laplacian", seeds=None, **kwargs) -> BasisModule:
        """Build with the classical bases: ``'laplacian'`` (k eigenfunctions) or ``'stack'``
        (``seeds`` required; ``kwargs`` go to :func:`~torchfmap.basis_stack`)."""
        if kind == "laplacian":
            return cls(laplacian_eigenbasis(mesh, k))
        if kind == "stack":
            if seeds is None:
                raise ParameterError("a stack basis needs seeds.")
            return cls(basis_stack(mesh, seeds, n_eigen=k, **kwargs))
        raise ParameterError(f"unknown basis kind {kind!r}. Fix: 'laplacian' or 'stack'.")

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
    """Differentiable batched functional-map solver for any B-orthonormal bases.

    ``forward(feat_x (B, V_x, D), feat_y (B, V_y, D), basis_x, basis_y) ->
    (C_xy (B, K_y, K_x), C_yx (B, K_x, K_y))`` (``C_yx`` is None with ``both=False``).
    The defaults are those of :func:`torchfmap.fmap.solve_fmap` for eigenbases (the same
    core solve gives the same map); for bases with diffusion columns pass
    ``w_lap=torchfmap.fmap.defaults.W_LAP['diffusion']``.
    """

    def __init__(
        self,
        w_desc: float = 1.0,
        w_lap: float = W_LAP["laplacian"],
        mask: str = "laplacian",
        both: bool = True,
    ):
        super().__init__()
        if w_desc <= 0 or w_lap < 0:
            raise ParameterError(f"weights must be w_desc > 0, w_lap >= 0; got {w_desc}, {w_lap}.")
        self.w_desc, self.w_lap, self.mask, self.both = w_desc, w_lap, mask, both

    def forward(self, feat_x, feat_y, basis_x: BasisBatch, basis_y: BasisBatch):
        """``(feat_x (B, V_x, D), feat_y (B, V_y, D), bases) -> (C_xy (B, K_y, K_x), C_yx)``;
        bases may be :class:`BasisModule` s (cast to the features' dtype)."""
        return F.fmap_solve(
            feat_x,
            feat_y,
            basis_x,
            basis_y,
            w_desc=self.w_desc,
            w_lap=self.w_lap,
            mask=self.mask,
            both=self.both,
        )


class SoftPointMap(nn.Module):
    """Soft map ``Π_yx (B, V_y, V_x)`` from features (softmax or Sinkhorn)."""

    def __init__(self, tau: float = 0.07, sinkhorn_iters: int = 0) -> None:
        super().__init__()
        self.tau, self.sinkhorn_iters = tau, sinkhorn_iters

    def forward(self, feat_x, feat_y, mass_x=None):
        """``(feat_x (B, V_x, D), feat_y (B, V_y, D)) -> Π_yx (B, V_y, V_x)``, rows summing to 1
        (``mass_x (B, V_x)`` weights the columns)."""
        return F.soft_map(feat_x, feat_y, tau=self.tau, mass_x=mass_x, sinkhorn_iters=self.sinkhorn_iters)

    def both(self, feat_x, feat_y, mass_x=None, mass_y=None):
        """``(Π_yx (B, V_y, V_x), Π_xy (B, V_x, V_y))`` from one similarity matrix
        (:func:`~torchfmap.nn.functional.soft_maps`)."""
        return F.soft_maps(
            feat_x, feat_y, tau=self.tau, mass_x=mass_x, mass_y=mass_y, sinkhorn_iters=self.sinkhorn_iters
        )


class UnsupervisedFMLoss(nn.Module):
    """``w_bij·bijectivity + w_orth·orthogonality + w_lap·Laplacian commutativity + w_couple·coupling``."""

    def __init__(
        self, w_bij=1.0, w_orth=1.0, w_lap=0.0, w_couple=1.0, tau: float = 0.07, n_samples: int = 0
    ) -> None:
        super().__init__()
        self.w = dict(bij=w_bij, orth=w_orth, lap=w_lap, couple=w_couple)
        self.soft = SoftPointMap(tau)
        self.n_samples = n_samples  # > 0: coupling between random vertex subsets (n x n soft maps)

    def _samples(self, basis: BasisBatch, feats: torch.Tensor) -> tuple[BasisBatch, torch.Tensor]:
        """A random subset of vertices, its mass rescaled to the total (an unbiased integral)."""
        V = feats.shape[1]
        if not self.n_samples or V <= self.n_samples:
            return basis, feats
        idx = torch.randperm(V, device=feats.device)[: self.n_samples]
        mass = basis.mass[:, idx]
        mass = mass * (basis.mass.sum(dim=1, keepdim=True) / mass.sum(dim=1, keepdim=True).clip(min=1e-30))
        return BasisBatch(basis.values[:, idx], mass, basis.lam, basis.U, basis.valid), feats[:, idx]

    def forward(
        self, C_xy, C_yx, feat_x, feat_y, basis_x: BasisBatch, basis_y: BasisBatch
    ) -> dict[str, torch.Tensor]:
        """The weighted terms and their sum ``'total'``; the coupling term's soft maps are
        ``(B, n, n)`` between ``n_samples`` random vertices of each shape (all when 0)."""
        terms = {
            "bij": F.bijectivity_loss(C_xy, C_yx, basis_x.valid, basis_y.valid),
            "orth": F.orthogonality_loss(C_xy, basis_x.valid) + F.orthogonality_loss(C_yx, basis_y.valid),
        }
        if self.w["lap"]:
            terms["lap"] = F.laplacian_commutativity_loss(C_xy, basis_x, basis_y)
        if self.w["couple"]:
            sub_x, rows_x = self._samples(basis_x, feat_x)
            sub_y, rows_y = self._samples(basis_y, feat_y)
            pi_yx, pi_xy = self.soft.both(rows_x, rows_y, sub_x.mass, sub_y.mass)
            terms["couple"] = F.coupling_loss(C_xy, pi_yx, sub_x, sub_y) + F.coupling_loss(
                C_yx, pi_xy, sub_y, sub_x
            )
        terms["total"] = sum(self.w[name] * value for name, value in terms.items())
        return terms


class SpectralDiffusion(nn.Module):
    """Learned per-channel diffusion in a basis frame: ``x -> Φ U exp(-t λ) Uᵀ Φᵀ M x``.

    Works in any B-orthonormal basis (for an eigenbasis ``U = I``); ``t`` is learned per channel.
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.log_t = nn.Parameter(torch.full((channels,), -4.0))

    def forward(self, x: torch.Tensor, basis: BasisBatch) -> torch.Tensor:
        """``x (B, V, C) -> (B, V, C)`` diffused, in ``x``'s dtype."""
        basis = F.basis_like(basis, x)
        coef = basis.U.transpose(-1, -2) @ F.project(basis, x)  # (B, K, C)
        decay = torch.exp(-basis.lam.clip(min=0)[..., None] * self.log_t.exp())  # (B, K, C)
        return F.reconstruct(basis, basis.U @ (decay * coef))


class FeatureNet(nn.Module):
    """Reference per-vertex feature network (DiffusionNet-like, in any basis).

    ``input (B, V, C_in) -> features (B, V, C_out)``: a linear lift, ``n_blocks`` residual
    blocks of [learned spectral diffusion, MLP on (x, diffused x)], a linear head.
    """

    def __init__(self, c_in: int, c_out: int = 64, width: int = 64, n_blocks: int = 3) -> None:
        super().__init__()
        self.lift = nn.Linear(c_in, width)
        self.diffusions = nn.ModuleList(SpectralDiffusion(width) for _ in range(n_blocks))
        self.mlps = nn.ModuleList(
            nn.Sequential(nn.Linear(2 * width, width), nn.ReLU(), nn.Linear(width, width))
            for _ in range(n_blocks)
        )
        self.head = nn.Linear(width, c_out)

    def forward(self, x: torch.Tensor, basis: BasisBatch) -> torch.Tensor:
        """``x (B, V, C_in)`` -> features ``(B, V, C_out)`` in ``x``'s dtype."""
        basis = F.basis_like(basis, x)
        if not torch.isfinite(x).all():
            raise ParameterError("FeatureNet input contains NaN or inf. Fix: check the precomputed inputs.")
        h = self.lift(x)
        for diffuse, mlp in zip(self.diffusions, self.mlps, strict=True):
            h = h + mlp(torch.cat([h, diffuse(h, basis)], dim=-1))
        return self.head(h)
