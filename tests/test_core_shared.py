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
    torchfmap.match(blob, y, k=12, k_descriptors=20, w_orient=0.0, w_dcomm=0.0)  # the row-wise solve
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


def test_defaults_agree_between_the_layer_the_classical_solver_and_match(blob):
    """One source of defaults: with no extra arguments the layer and ``solve_fmap`` give the
    same map in eigenbases (same core, same default ``w_lap``); ``fmap_to_p2p`` converts it
    by the eigenbasis rule that ``match`` uses; ``solve_fmap`` uses landmarks when given."""
    from torchfmap.fmap import fmap_to_p2p, solve_fmap
    from torchfmap.fmap.defaults import W_LAP, default_p2p_mode, default_w_lap

    y = blob.copy(blob.vertices * np.array([1.0, 1.1, 0.9]))
    bx, by = laplacian_eigenbasis(blob, 10), laplacian_eigenbasis(y, 10)
    rng = np.random.default_rng(0)
    dx = rng.standard_normal((blob.n_vertices, 6))
    dy = dx + 0.01 * rng.standard_normal(dx.shape)  # same vertex order: near-identical descriptors
    C = solve_fmap(bx, by, dx, dy)
    layer = RegularizedFMSolver()
    C_t, _ = layer(
        torch.from_numpy(dx)[None],
        torch.from_numpy(dy)[None],
        BasisModule(bx).batch(),
        BasisModule(by).batch(),
    )
    # both solve the same K x K systems in float64; round-off of the frames (eigh of K x K)
    tol = 1e3 * np.finfo(float).eps * np.abs(C).max()
    np.testing.assert_allclose(C_t[0].numpy(), C, atol=tol)
    assert default_w_lap(bx, by) == W_LAP["laplacian"] == layer.w_lap
    assert default_p2p_mode(bx, by) == "orthogonal"
    np.testing.assert_array_equal(fmap_to_p2p(C, bx, by), fmap_to_p2p(C, bx, by, mode="orthogonal"))
    from torchfmap.fmap import values_to_p2p  # the same rules on plain arrays (the learned path)

    for mode in ("orthogonal", "pullback"):
        np.testing.assert_array_equal(
            values_to_p2p(C, bx.values, by.values, mode=mode), fmap_to_p2p(C, bx, by, mode=mode)
        )
    lm = np.array([[0, 0], [50, 50], [100, 100]])
    with_lm = solve_fmap(bx, by, dx, dy, landmarks=lm)
    assert not np.allclose(with_lm, C)  # given landmarks are used (w_lmk defaults to W_LMK)
    np.testing.assert_allclose(solve_fmap(bx, by, dx, dy, landmarks=lm, w_lmk=0.0), C, atol=tol)
