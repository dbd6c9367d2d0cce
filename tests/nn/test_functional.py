"""Functions of the learned path (``torchfmap.nn.functional``): the batched solve against gradcheck
and per-pair solves, padding, losses, soft maps to functional maps, vertex masks, bad input,
renamed names."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfmap import ParameterError, laplacian_eigenbasis
from torchfmap.nn import BasisModule, collate_shapes
from torchfmap.nn import functional as F
from torchfmap.nn.functional import BasisBatch

from ..conftest import as_batch, bumpy_blob


@pytest.mark.parametrize("which", ["eig", "stack"])
def test_gradcheck_solver(nn_setting, which):
    x, y, dx, dy, eig, stack = nn_setting
    tx, ty = as_batch(*(eig if which == "eig" else stack))
    fx = torch.tensor(dx[:, :3], requires_grad=True)
    fy = torch.tensor(dy[:, :3], requires_grad=True)

    def fn(a, b):
        C_xy, C_yx = F.solve_fmap_batch(a[None], b[None], tx, ty, w_lap=1e-2)
        return C_xy, C_yx

    assert torch.autograd.gradcheck(fn, (fx, fy), eps=1e-6, atol=1e-6)


def test_gradcheck_losses(nn_setting):
    x, y, dx, dy, eig, stack = nn_setting
    tx, ty = as_batch(*eig)
    C_xy = torch.randn(1, 6, 7, dtype=torch.float64, requires_grad=True)
    C_yx = torch.randn(1, 7, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: F.bijectivity_loss(a, b), (C_xy, C_yx))
    assert torch.autograd.gradcheck(lambda a: F.orthogonality_loss(a), (C_xy,))
    assert torch.autograd.gradcheck(lambda a: F.laplacian_commutativity_loss(a, tx, ty), (C_xy,))
    # soft-map losses on a 20-vertex slice (gradcheck perturbs every input entry)
    n = 20
    sx = BasisBatch(tx.values[:, :n], tx.mass[:, :n], tx.lam, tx.U, tx.valid)
    sy = BasisBatch(ty.values[:, :n], ty.mass[:, :n], ty.lam, ty.U, ty.valid)
    fx = torch.tensor(dx[None, :n, :3], requires_grad=True)
    fy = torch.tensor(dy[None, :n, :3], requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda c, a, b: F.coupling_loss(c, F.soft_map(a, b, tau=0.5), sx, sy), (C_xy, fx, fy), atol=1e-6
    )
    dist = torch.rand(1, 4, n, dtype=torch.float64)
    idx = torch.tensor([[0, 5, 9, 11]])
    assert torch.autograd.gradcheck(
        lambda a, b: F.geodesic_loss(F.soft_map(a, b, tau=0.5), idx, dist), (fx, fy)
    )


def test_losses_vanish_on_perfect_maps():
    Q = torch.linalg.qr(torch.randn(5, 5, dtype=torch.float64))[0][None]
    assert F.orthogonality_loss(Q) < 1e-24 and F.bijectivity_loss(Q, Q.transpose(-1, -2)) < 1e-24


def test_batched_equals_per_pair(nn_setting):
    x, y, dx, dy, eig, stack = nn_setting
    items = []
    for bx, by in (eig, eig):
        items.append(as_batch(bx, by))
    feats_x = torch.stack([torch.tensor(dx), torch.tensor(dx[:, ::-1].copy())])
    feats_y = torch.stack([torch.tensor(dy), torch.tensor(dy[:, ::-1].copy())])
    # unpadded batches of one (lengths None): stack their five tensor fields
    bx = BasisBatch(*(torch.cat(t) for t in zip(items[0][0][:5], items[1][0][:5], strict=True)))
    by = BasisBatch(*(torch.cat(t) for t in zip(items[0][1][:5], items[1][1][:5], strict=True)))
    assert bx.lengths is None and bx.vertex_mask is None
    C_batch, _ = F.solve_fmap_batch(feats_x, feats_y, bx, by)
    for b in range(2):
        C_one, _ = F.solve_fmap_batch(feats_x[b : b + 1], feats_y[b : b + 1], items[b][0], items[b][1])
        assert torch.allclose(C_batch[b], C_one[0], atol=1e-12)


def test_padded_variable_size_batch_equals_unpadded(nn_setting):
    x, y, dx, dy, eig, stack = nn_setting
    small = bumpy_blob(1)  # 42 vertices vs 162
    bs = laplacian_eigenbasis(small, 5)
    ds = np.random.default_rng(1).normal(size=(small.n_vertices, 5))

    def item(basis, feats):
        arrays = {k: v.clone() for k, v in BasisModule(basis).state_dict().items()}
        return {**arrays, "wks": torch.tensor(feats)}

    sx, sy = (
        collate_shapes([item(eig[0], dx), item(bs, ds)]),
        collate_shapes([item(eig[1], dy), item(bs, ds)]),
    )
    (bx, fx), (by, fy) = (sx.basis, sx.inputs), (sy.basis, sy.inputs)
    assert sx.lengths.tolist() == bx.lengths.tolist() == [162, 42] and bx.values.shape == (2, 162, 7)
    assert bx.vertex_mask.sum(dim=1).tolist() == [162, 42] and not bx.vertex_mask[1, 42:].any()
    C_pad, C_pad_yx = F.solve_fmap_batch(fx, fy, bx, by)
    ref, _ = F.solve_fmap_batch(torch.tensor(ds)[None], torch.tensor(ds)[None], *as_batch(bs, bs))
    assert torch.allclose(C_pad[1, :5, :5], ref[0], atol=1e-10)
    assert C_pad[1, 5:].abs().max() == 0 and C_pad[1, :, 5:].abs().max() == 0
    ref0, _ = F.solve_fmap_batch(torch.tensor(dx)[None], torch.tensor(dy)[None], *as_batch(*eig))
    assert torch.allclose(C_pad[0, :6, :7], ref0[0], atol=1e-10)


def test_no_nan_gradients_for_rank_deficient_descriptors(nn_setting):
    x, y, dx, dy, eig, stack = nn_setting
    tx, ty = as_batch(*eig)
    const = torch.ones(1, x.n_vertices, 4, dtype=torch.float64, requires_grad=True)  # rank 1
    C_xy, C_yx = F.solve_fmap_batch(const, const.detach().clone().requires_grad_(True), tx, ty)
    loss = F.bijectivity_loss(C_xy, C_yx) + F.orthogonality_loss(C_xy)
    loss.backward()
    assert torch.isfinite(C_xy).all() and torch.isfinite(const.grad).all()


def test_bad_inputs(nn_setting):
    x, y, dx, dy, eig, stack = nn_setting
    tx, ty = as_batch(*eig)
    fx, fy = torch.tensor(dx)[None], torch.tensor(dy)[None]
    with pytest.raises(ParameterError, match="batch sizes differ"):
        F.solve_fmap_batch(fx, fy, tx, BasisBatch(*(torch.cat([t, t]) for t in ty[:5])))
    with pytest.raises(ParameterError, match=r"features must be \(B, V, D\)"):
        F.solve_fmap_batch(fx[:, :10], fy, tx, ty)
    bad = fx.clone()
    bad[0, 3, 1] = float("nan")
    with pytest.raises(ParameterError, match="NaN"):
        F.solve_fmap_batch(bad, fy, tx, ty)
    with pytest.raises(ParameterError, match="feature dimensions differ"):
        F.solve_fmap_batch(fx, fy[..., :3], tx, ty)
    with pytest.raises(ParameterError, match=r"k=9 is outside \[1, 7\]"):
        BasisModule(eig[0]).truncated(9)
    from torchfmap import harmonic_basis

    with pytest.raises(ParameterError, match="B-orthonormal"):
        BasisModule(harmonic_basis(x, [0, 5]))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(nn_setting):
    x, y, dx, dy, eig, stack = nn_setting
    tx, ty = as_batch(*eig)
    fx, fy = torch.tensor(dx)[None], torch.tensor(dy)[None]
    cpu, _ = F.solve_fmap_batch(fx, fy, tx, ty)
    gpu, _ = F.solve_fmap_batch(fx.cuda(), fy.cuda(), tx.to("cuda"), ty.to("cuda"))
    assert torch.allclose(cpu, gpu.cpu(), atol=1e-10)


def test_soft_map_to_fmap_of_identity_is_identity(sphere2):
    """A permutation soft map between a shape and its relabelled copy gives C = I (the bases
    are relabelled too): Φ_yᵀ M_y Π Φ_x = Φ_xᵀ M_x Φ_x = I to eigensolver round-off."""
    basis = BasisModule(laplacian_eigenbasis(sphere2, 8)).batch()
    pi = torch.eye(sphere2.n_vertices, dtype=torch.float64)[None]
    C = F.soft_map_to_fmap(pi, basis, basis)
    torch.testing.assert_close(C[0], torch.eye(8, dtype=torch.float64), rtol=0, atol=1e-10)


def test_vertex_mask_marks_the_real_vertices():
    from torchfmap.nn.functional import vertex_mask

    mask = vertex_mask(torch.tensor([2, 4]), 4)
    assert mask.tolist() == [[True, True, False, False], [True, True, True, True]]
    assert vertex_mask(None, 4) is None
