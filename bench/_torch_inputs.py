"""Random, seeded inputs of ``solver.py`` and ``train_step.py``.

Built in float64 and cast, so both dtypes see the same numbers: a ``BasisBatch`` per side with
``values = sqrt(V) Q`` (``Q`` from the QR of a Gaussian ``(V, K)``, so ``valuesᵀ diag(mass) values
= I`` with the uniform ``mass = 1/V``), ``lam`` sorted uniform in ``[0, 100]``, ``U`` orthogonal
(QR of a Gaussian ``(K, K)``), ``valid`` all ones.
"""

from __future__ import annotations

from typing import Any

import _common  # noqa: F401  (puts this checkout first on sys.path, before torchfmap)
import torch

from torchfmap.nn.functional import BasisBatch

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def random_basis(b: int, v: int, k: int, dtype: torch.dtype, gen: torch.Generator) -> BasisBatch:
    """B-orthonormal random basis (uniform mass ``1/V``) with a random spectral frame."""
    f64 = torch.float64
    q, _ = torch.linalg.qr(torch.randn(b, v, k, generator=gen, dtype=f64))
    u, _ = torch.linalg.qr(torch.randn(b, k, k, generator=gen, dtype=f64))
    lam = torch.sort(100.0 * torch.rand(b, k, generator=gen, dtype=f64), dim=-1).values
    mass = torch.full((b, v), 1.0 / v, dtype=f64)
    parts = (q * v**0.5, mass, lam, u, torch.ones(b, k, dtype=f64))
    return BasisBatch(*(t.to(dtype).contiguous() for t in parts))


def solver_inputs(b: int, v: int, k: int, d: int, dtype: torch.dtype, seed: int) -> dict[str, Any]:
    gen = torch.Generator().manual_seed(seed)
    bx, by = random_basis(b, v, k, dtype, gen), random_basis(b, v, k, dtype, gen)
    fx = torch.randn(b, v, d, generator=gen, dtype=torch.float64).to(dtype).requires_grad_(True)
    fy = torch.randn(b, v, d, generator=gen, dtype=torch.float64).to(dtype).requires_grad_(True)
    r_xy = torch.randn(b, k, k, generator=gen, dtype=torch.float64).to(dtype)
    r_yx = torch.randn(b, k, k, generator=gen, dtype=torch.float64).to(dtype)
    return {"fx": fx, "fy": fy, "bx": bx, "by": by, "r_xy": r_xy, "r_yx": r_yx}
