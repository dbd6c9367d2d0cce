"""The classical path and the torch layers run the same functional-map core (torchfmap.fmap.core)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchfmap
from torchfmap import laplacian_eigenbasis
from torchfmap.fmap import core
from torchfmap.nn import BasisModule, RegularizedFMSolver


@pytest.fixture()
def recorded_core(monkeypatch):
    """Wrap the core's frame and row-wise solve so that every call through them is recorded."""
    calls: list[str] = []
    frame, rowwise = core.spectral_frame, core.solve_rowwise

    def spy_frame(W):
        calls.append("spectral_frame")
        return frame(W)

    def spy_rowwise(*args, **kwargs):
        calls.append("solve_rowwise")
        return rowwise(*args, **kwargs)

    monkeypatch.setattr(core, "spectral_frame", spy_frame)
    monkeypatch.setattr(core, "solve_rowwise", spy_rowwise)
    return calls


def test_match_and_layers_call_the_same_core(blob, recorded_core):
    """Patching the core is seen by match() (classical, numpy) and by the layer (torch)."""
    y = blob.copy(blob.vertices * np.array([1.0, 1.1, 0.9]))
    torchfmap.match(blob, y, k=12, k_descriptors=20, w_orient=0.0)
    # two frames (one per shape) and one row-wise solve per map
    assert recorded_core.count("spectral_frame") == 2 and recorded_core.count("solve_rowwise") == 1
    recorded_core.clear()
    bx, by = BasisModule(laplacian_eigenbasis(blob, 8)), BasisModule(laplacian_eigenbasis(y, 8))
    assert recorded_core.count("spectral_frame") == 2  # the frames stored as buffers
    feats = torch.randn(1, blob.n_vertices, 5, dtype=torch.float64)
    RegularizedFMSolver(w_lap=0.1)(feats, feats, bx.batch(), by.batch())
    assert recorded_core.count("solve_rowwise") == 2  # C_xy and C_yx


def test_core_follows_dtype_and_keeps_no_state():
    """float32 in -> float32 out; the same call twice gives bit-identical maps (no buffers)."""
    g = torch.Generator().manual_seed(0)
    A_x, A_y = torch.randn(2, 6, 4, generator=g), torch.randn(2, 5, 4, generator=g)
    lam_x, U_x = core.spectral_frame(torch.diag_embed(torch.rand(2, 6, generator=g)))
    lam_y, U_y = core.spectral_frame(torch.diag_embed(torch.rand(2, 5, generator=g)))
    C1 = core.rotate_and_solve(A_x, A_y, lam_x, U_x, lam_y, U_y, w_desc=1.0, w_lap=0.1)
    C2 = core.rotate_and_solve(A_x, A_y, lam_x, U_x, lam_y, U_y, w_desc=1.0, w_lap=0.1)
    assert C1.dtype == torch.float32 and C1.shape == (2, 5, 6)
    assert torch.equal(C1, C2)
    assert not [name for name in vars(core) if name.isupper() or name.startswith("_SCRATCH")]
