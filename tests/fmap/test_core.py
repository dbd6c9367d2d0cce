"""The functional-map core (``torchfmap.fmap.core``) that the classical path and the torch layers
share: one implementation, masks (the resolvent mask of Ren et al. 2019), spectral frames, the
row-wise solve and its gradients, priors, overflow and dtype checks."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchfmap
from torchfmap import ParameterError, laplacian_eigenbasis
from torchfmap.fmap import core, laplacian_mask, solve_rowwise
from torchfmap.nn import BasisModule, RegularizedFMSolver

from ..conftest import np_mask


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


def test_masks():
    lam = torch.tensor([0.0, 1.0, 4.0], dtype=torch.float64)
    m = laplacian_mask(lam, lam)
    assert torch.allclose(torch.diag(m), torch.zeros(3, dtype=torch.float64)) and float(
        m.mean()
    ) == pytest.approx(1.0)
    r = laplacian_mask(lam, lam, "resolvent")
    assert torch.allclose(torch.diag(r), torch.zeros(3, dtype=torch.float64)) and bool((r >= 0).all())
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(
        solve_rowwise(eye, 2 * eye, torch.zeros(3, 3, dtype=torch.float64), 1.0, 0.0), 2 * eye
    )


def test_spectral_frame_is_a_named_tuple():
    """``core.spectral_frame`` returns ``SpectralFrame(lam, U)``: ascending eigenvalues and an
    orthogonal frame with ``W = U diag(lam) Uᵀ`` (round-off), also when unpacked."""
    from torchfmap.fmap import core

    g = torch.Generator().manual_seed(0)
    A = torch.randn(2, 5, 5, generator=g, dtype=torch.float64)
    W = A @ A.mT
    frame = core.spectral_frame(W)
    assert isinstance(frame, core.SpectralFrame) and frame.lam is frame[0]
    lam, U = frame
    assert (lam[:, 1:] >= lam[:, :-1]).all()
    torch.testing.assert_close(U @ torch.diag_embed(lam) @ U.mT, W, rtol=1e-12, atol=1e-12)


def test_the_frame_of_an_eigenbasis_is_read_off_and_of_other_bases_solved():
    """``core.spectral_frame``: ``W = diag(lambda)`` (an eigenbasis) gives ``U = I`` exactly and
    its diagonal; a full symmetric ``W`` gives ``U diag(lam) Uᵀ = W`` with ``U`` orthogonal."""
    from torchfmap.fmap import core

    lam = torch.linspace(0.0, 5.0, 7, dtype=torch.float64)
    frame = core.spectral_frame(torch.diag(lam))
    assert torch.equal(frame.U, torch.eye(7, dtype=torch.float64)) and torch.equal(frame.lam, lam)
    A = torch.randn(7, 7, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    W = A @ A.T
    lam_w, U = core.spectral_frame(W)
    scale = torch.linalg.matrix_norm(W)
    tol = 100 * 7 * torch.finfo(W.dtype).eps * scale  # eigh's backward error, a few ulps per entry
    assert torch.linalg.matrix_norm(U @ torch.diag(lam_w) @ U.T - W) <= tol
    assert (
        torch.linalg.matrix_norm(U.T @ U - torch.eye(7, dtype=torch.float64))
        <= 100 * 7 * torch.finfo(W.dtype).eps
    )
    unsorted = core.spectral_frame(torch.diag(lam.flip(0)))  # not ascending: decomposed, sorted
    assert torch.allclose(unsorted.lam, lam)


def resolvent_reference(lam_x, lam_y, gamma=0.5):
    """Ren et al. 2019 written out with complex numbers: R(λ) = 1 / (λ^γ - i) on eigenvalues
    scaled by their common maximum, M_ij = |R(λ_y,i) - R(λ_x,j)|², then divided by its mean."""
    top = max(lam_x.max(), lam_y.max())
    M = np.empty((len(lam_y), len(lam_x)))
    for i, ly in enumerate(lam_y):
        for j, lx in enumerate(lam_x):
            ry = 1.0 / ((ly / top) ** gamma - 1j)
            rx = 1.0 / ((lx / top) ** gamma - 1j)
            M[i, j] = abs(ry - rx) ** 2
    return M / M.mean()


@pytest.fixture()
def spectra():
    rng = np.random.default_rng(5)
    lam_x = np.concatenate([[0.0], np.sort(rng.uniform(0.1, 40, 11))])
    lam_y = np.concatenate([[0.0], np.sort(rng.uniform(0.1, 55, 8))])
    return lam_x, lam_y


@pytest.mark.parametrize("gamma", [0.5, 1.0])
def test_resolvent_mask_matches_formula_numpy_and_torch(spectra, gamma):
    """The core (torch) gives Ren et al.'s mask (round-off: rtol 1e-12); torch keeps batch
    dimensions and dtype."""
    lam_x, lam_y = spectra
    ref = resolvent_reference(lam_x, lam_y, gamma)
    M = np_mask(lam_x, lam_y, "resolvent", gamma=gamma)
    np.testing.assert_allclose(M, ref, rtol=1e-12, atol=1e-15)
    tx = torch.tensor(np.stack([lam_x, 2 * lam_x]))
    ty = torch.tensor(np.stack([lam_y, 2 * lam_y]))
    Mt = laplacian_mask(tx, ty, "resolvent", gamma=gamma)
    assert Mt.shape == (2, len(lam_y), len(lam_x)) and Mt.dtype == torch.float64
    np.testing.assert_allclose(Mt[0].numpy(), ref, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(Mt[1].numpy(), ref, rtol=1e-12, atol=1e-15)  # common scaling: same mask


def test_resolvent_mask_properties(spectra):
    """Zero where λ_x = λ_y (diagonal of equal spectra), symmetric under swapping x and y,
    mean 1, invariant to a common scaling of both spectra (round-off only)."""
    lam_x, lam_y = spectra
    same = np_mask(lam_x, lam_x, "resolvent")
    np.testing.assert_allclose(np.diag(same), 0.0, atol=1e-15)
    assert np.all(same[~np.eye(len(lam_x), dtype=bool)] > 0)
    M = np_mask(lam_x, lam_y, "resolvent")
    np.testing.assert_allclose(np_mask(lam_y, lam_x, "resolvent"), M.T, rtol=1e-12)
    assert M.mean() == pytest.approx(1.0, rel=1e-12)
    np.testing.assert_allclose(np_mask(7.3 * lam_x, 7.3 * lam_y, "resolvent"), M, rtol=1e-12)
    # negative round-off eigenvalues are clipped to 0
    neg = lam_x.copy()
    neg[0] = -1e-12
    np.testing.assert_allclose(np_mask(neg, lam_y, "resolvent"), M, rtol=1e-12)


def test_resolvent_mask_valid_entries_and_gradients(spectra):
    """With a `valid` pattern the mean over valid entries is 1 and padded entries are 0; the
    torch mask is differentiable (gradcheck, float64, eigenvalues away from 0 and from ties)."""
    lam_x, lam_y = spectra
    valid = np.zeros((len(lam_y), len(lam_x)))
    valid[:5, :7] = 1
    M = np_mask(lam_x, lam_y, "resolvent", valid=valid)
    assert M[valid == 0].max() == 0
    assert M[valid == 1].mean() == pytest.approx(1.0, rel=1e-12)
    tx = torch.tensor(lam_x[1:], requires_grad=True)
    ty = torch.tensor(lam_y[1:], requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: laplacian_mask(a, b, "resolvent"), (tx, ty))
    with pytest.raises(ParameterError, match="unknown mask 'bogus'"):
        np_mask(lam_x, lam_y, "bogus")


def test_prior_pulls_the_core_solution_and_matches_the_classical_path():
    """w_prior -> inf gives the prior; w_prior = 0 ignores it; the classical problem with a
    prior equals the core's rotate_and_solve with the same prior."""
    g = torch.Generator().manual_seed(1)
    A_x, A_y = (
        torch.randn(6, 9, generator=g, dtype=torch.float64),
        torch.randn(5, 9, generator=g, dtype=torch.float64),
    )
    lam_x, U_x = core.spectral_frame(torch.diag(torch.rand(6, generator=g, dtype=torch.float64)))
    lam_y, U_y = core.spectral_frame(torch.diag(torch.rand(5, generator=g, dtype=torch.float64)))
    P = torch.randn(5, 6, generator=g, dtype=torch.float64)
    args = (A_x, A_y, lam_x, U_x, lam_y, U_y)
    free = core.rotate_and_solve(*args, w_desc=1.0, w_lap=0.1)
    torch.testing.assert_close(
        core.rotate_and_solve(*args, w_desc=1.0, w_lap=0.1, prior=P, w_prior=0.0), free
    )
    strong = core.rotate_and_solve(*args, w_desc=1.0, w_lap=0.1, prior=P, w_prior=1e12)
    torch.testing.assert_close(strong, P, atol=1e-9, rtol=0)


def test_rowwise_solve_gradients_match_dense_autograd():
    """The custom backward of the row-wise solve (LU reuse, no (..., Ky, Kx, Kx) gradient)
    equals autograd through torch.linalg.solve on explicit systems, with two leading batch
    dimensions and K_y != K_x; second derivatives are right too (gradgradcheck)."""
    g = torch.Generator().manual_seed(3)
    A_x = torch.randn(2, 3, 7, 5, dtype=torch.float64, generator=g, requires_grad=True)
    A_y = torch.randn(2, 3, 6, 5, dtype=torch.float64, generator=g, requires_grad=True)
    mask = torch.rand(2, 3, 6, 7, dtype=torch.float64, generator=g, requires_grad=True)
    R = torch.randn(2, 3, 6, 7, dtype=torch.float64, generator=g)

    def dense(a_x, a_y, m):
        G = a_x @ a_x.transpose(-1, -2)
        systems = G.unsqueeze(-3) + torch.diag_embed(0.5 * m)
        return torch.linalg.solve(systems, (a_y @ a_x.transpose(-1, -2))[..., None])[..., 0]

    C = solve_rowwise(A_x, A_y, mask, 1.0, 0.5)
    grads = torch.autograd.grad((C * R).sum(), (A_x, A_y, mask))
    C_ref = dense(A_x, A_y, mask)
    grads_ref = torch.autograd.grad((C_ref * R).sum(), (A_x, A_y, mask))
    torch.testing.assert_close(C, C_ref, rtol=1e-10, atol=1e-12)
    for a, b in zip(grads, grads_ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)
    # padding as collate_shapes makes it (zero coefficient rows for padded columns, valid = 0):
    # padded entries come out exactly 0 and the valid block equals the unpadded solve,
    # gradients included (same systems, round-off only)
    valid = torch.zeros(2, 3, 6, 7, dtype=torch.float64)
    valid[..., :4, :5] = 1
    pad_x = torch.cat([A_x[..., :5, :], torch.zeros_like(A_x[..., 5:, :])], dim=-2)
    pad_y = torch.cat([A_y[..., :4, :], torch.zeros_like(A_y[..., 4:, :])], dim=-2)
    Cp = solve_rowwise(pad_x, pad_y, mask, 1.0, 0.5, valid)
    Cu = solve_rowwise(A_x[..., :5, :], A_y[..., :4, :], mask[..., :4, :5], 1.0, 0.5)
    assert Cp[..., 4:, :].abs().max() == 0 and Cp[..., :, 5:].abs().max() == 0
    torch.testing.assert_close(Cp[..., :4, :5], Cu, rtol=1e-10, atol=1e-12)
    gp = torch.autograd.grad((Cp[..., :4, :5] * R[..., :4, :5]).sum(), (A_x, A_y))
    gu = torch.autograd.grad((Cu * R[..., :4, :5]).sum(), (A_x, A_y))
    torch.testing.assert_close(gp[0][..., :5, :], gu[0][..., :5, :], rtol=1e-9, atol=1e-11)
    torch.testing.assert_close(gp[1][..., :4, :], gu[1][..., :4, :], rtol=1e-9, atol=1e-11)
    small = [t.detach()[:1, :1].clone().requires_grad_() for t in (A_x, A_y, mask)]
    assert torch.autograd.gradgradcheck(lambda a, b, m: solve_rowwise(a, b, m, 1.0, 0.5), small)


def test_core_refuses_overflow_and_half_precision():
    """float32 features ~1e20 overflowed the Gram matrix unnoticed (NaN maps); half and bfloat16
    failed inside LAPACK with 'not implemented'."""
    import torch

    from torchfmap.fmap import core

    A = torch.full((4, 3), 1e20, dtype=torch.float32)
    mask = torch.ones(4, 4, dtype=torch.float32)
    with pytest.raises(ParameterError, match="overflows torch.float32"):
        core.solve_rowwise(A, A, mask, 1.0, 0.1)
    for dtype in (torch.float16, torch.bfloat16):
        A = torch.randn(4, 3).to(dtype)
        with pytest.raises(ParameterError, match="needs float32 or float64"):
            core.solve_rowwise(A, A, mask.to(dtype), 1.0, 0.1)
