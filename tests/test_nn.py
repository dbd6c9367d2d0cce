"""torch layers: gradcheck, equality with the classical solver, batching, padding, losses, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfmap import ParameterError, basis_stack, farthest_point_sampling, laplacian_eigenbasis
from torchfmap.fmap import solve_fmap, solve_rowwise
from torchfmap.nn import BasisModule, FeatureNet, RegularizedFMSolver, UnsupervisedFMLoss, collate_shapes
from torchfmap.nn import functional as F
from torchfmap.nn.functional import BasisBatch

from .conftest import bend, bumpy_blob


@pytest.fixture(scope="module")
def setting():
    x = bumpy_blob(2)
    y = x.copy(bend(x.vertices, 0.3))
    rng = np.random.default_rng(0)
    dx = rng.normal(size=(x.n_vertices, 5))
    dy = dx + 0.05 * rng.normal(size=dx.shape)
    seeds = farthest_point_sampling(x, 4, metric="euclidean")
    eig = (laplacian_eigenbasis(x, 7), laplacian_eigenbasis(y, 6))
    stack = (basis_stack(x, seeds, times=[1e-2], n_eigen=2), basis_stack(y, seeds, times=[1e-2], n_eigen=2))
    return x, y, dx, dy, eig, stack


def as_batch(*bases):
    return [BasisModule(b).batch() for b in bases]


@pytest.mark.parametrize("which", ["eig", "stack"])
def test_module_equals_classical_solver(setting, which):
    x, y, dx, dy, eig, stack = setting
    bx, by = eig if which == "eig" else stack
    C = solve_fmap(bx, by, dx, dy, w_lap=1e-2)
    tx, ty = as_batch(bx, by)
    out = RegularizedFMSolver(w_lap=1e-2)(torch.tensor(dx)[None], torch.tensor(dy)[None], tx, ty)
    assert isinstance(out, F.FmapPair) and out.C_xy is out[0] and out.C_yx is out[1]
    C_xy, C_yx = out
    assert np.abs(C_xy[0].numpy() - C).max() < 1e-10 * np.abs(C).max()
    assert np.abs(C_yx[0].numpy() - solve_fmap(by, bx, dy, dx, w_lap=1e-2)).max() < 1e-10 * np.abs(C).max()


@pytest.mark.parametrize("which", ["eig", "stack"])
def test_gradcheck_solver(setting, which):
    x, y, dx, dy, eig, stack = setting
    tx, ty = as_batch(*(eig if which == "eig" else stack))
    fx = torch.tensor(dx[:, :3], requires_grad=True)
    fy = torch.tensor(dy[:, :3], requires_grad=True)

    def fn(a, b):
        C_xy, C_yx = F.solve_fmap(a[None], b[None], tx, ty, w_lap=1e-2)
        return C_xy, C_yx

    assert torch.autograd.gradcheck(fn, (fx, fy), eps=1e-6, atol=1e-6)


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


def test_gradcheck_losses(setting):
    x, y, dx, dy, eig, stack = setting
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


def test_batched_equals_per_pair(setting):
    x, y, dx, dy, eig, stack = setting
    items = []
    for bx, by in (eig, eig):
        items.append(as_batch(bx, by))
    feats_x = torch.stack([torch.tensor(dx), torch.tensor(dx[:, ::-1].copy())])
    feats_y = torch.stack([torch.tensor(dy), torch.tensor(dy[:, ::-1].copy())])
    # unpadded batches of one (lengths None): stack their five tensor fields
    bx = BasisBatch(*(torch.cat(t) for t in zip(items[0][0][:5], items[1][0][:5], strict=True)))
    by = BasisBatch(*(torch.cat(t) for t in zip(items[0][1][:5], items[1][1][:5], strict=True)))
    assert bx.lengths is None and bx.vertex_mask is None
    C_batch, _ = F.solve_fmap(feats_x, feats_y, bx, by)
    for b in range(2):
        C_one, _ = F.solve_fmap(feats_x[b : b + 1], feats_y[b : b + 1], items[b][0], items[b][1])
        assert torch.allclose(C_batch[b], C_one[0], atol=1e-12)


def test_padded_variable_size_batch_equals_unpadded(setting):
    x, y, dx, dy, eig, stack = setting
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
    C_pad, C_pad_yx = F.solve_fmap(fx, fy, bx, by)
    ref, _ = F.solve_fmap(torch.tensor(ds)[None], torch.tensor(ds)[None], *as_batch(bs, bs))
    assert torch.allclose(C_pad[1, :5, :5], ref[0], atol=1e-10)
    assert C_pad[1, 5:].abs().max() == 0 and C_pad[1, :, 5:].abs().max() == 0
    ref0, _ = F.solve_fmap(torch.tensor(dx)[None], torch.tensor(dy)[None], *as_batch(*eig))
    assert torch.allclose(C_pad[0, :6, :7], ref0[0], atol=1e-10)


def test_no_nan_gradients_for_rank_deficient_descriptors(setting):
    x, y, dx, dy, eig, stack = setting
    tx, ty = as_batch(*eig)
    const = torch.ones(1, x.n_vertices, 4, dtype=torch.float64, requires_grad=True)  # rank 1
    C_xy, C_yx = F.solve_fmap(const, const.detach().clone().requires_grad_(True), tx, ty)
    loss = F.bijectivity_loss(C_xy, C_yx) + F.orthogonality_loss(C_xy)
    loss.backward()
    assert torch.isfinite(C_xy).all() and torch.isfinite(const.grad).all()


def test_bad_inputs(setting):
    x, y, dx, dy, eig, stack = setting
    tx, ty = as_batch(*eig)
    fx, fy = torch.tensor(dx)[None], torch.tensor(dy)[None]
    with pytest.raises(ParameterError, match="batch sizes differ"):
        F.solve_fmap(fx, fy, tx, BasisBatch(*(torch.cat([t, t]) for t in ty[:5])))
    with pytest.raises(ParameterError, match=r"features must be \(B, V, D\)"):
        F.solve_fmap(fx[:, :10], fy, tx, ty)
    bad = fx.clone()
    bad[0, 3, 1] = float("nan")
    with pytest.raises(ParameterError, match="NaN"):
        F.solve_fmap(bad, fy, tx, ty)
    with pytest.raises(ParameterError, match="feature dimensions differ"):
        F.solve_fmap(fx, fy[..., :3], tx, ty)
    with pytest.raises(ParameterError, match=r"k=9 is outside \[1, 7\]"):
        BasisModule(eig[0]).truncated(9)
    with pytest.raises(ParameterError, match="NaN or inf"):
        FeatureNet(5, 4).double()(bad, tx)
    from torchfmap import harmonic_basis

    with pytest.raises(ParameterError, match="B-orthonormal"):
        BasisModule(harmonic_basis(x, [0, 5]))


def test_basis_module_buffers_move_and_project(setting):
    x, y, dx, dy, eig, stack = setting
    module = BasisModule(eig[0]).float()
    assert module.values.dtype == torch.float32 and {n for n, _ in module.named_buffers()} == {
        "values",
        "mass",
        "lam",
        "U",
    }
    f = torch.tensor(eig[0].values[:, :3], dtype=torch.float32)
    assert torch.allclose(module.project(f), torch.eye(7)[:, :3], atol=1e-5)
    assert torch.allclose(module.reconstruct(module.project(f)), f, atol=1e-5)
    assert module.truncated(4).k == 4


def test_feature_net_and_unsupervised_loss_backward(setting):
    x, y, dx, dy, eig, stack = setting
    tx, ty = as_batch(*eig)
    net = FeatureNet(5, 8, width=16, n_blocks=2).double()
    fx, fy = net(torch.tensor(dx)[None], tx), net(torch.tensor(dy)[None], ty)
    C_xy, C_yx = RegularizedFMSolver()(fx, fy, tx, ty)
    terms = UnsupervisedFMLoss(w_lap=1.0)(C_xy, C_yx, fx, fy, tx, ty)
    terms["total"].backward()
    grads = [p.grad for p in net.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert set(terms) == {"bij", "orth", "lap", "couple", "total"}


def test_data_checks_follow_the_switch_in_function_and_layer(setting):
    """Data checks run by default on CPU tensors and are skipped with check=False, in the
    function and in its layer alike; shape checks run either way."""
    x, y, dx, dy, eig, stack = setting
    tx, ty = as_batch(*eig)
    fx, fy = torch.tensor(dx)[None], torch.tensor(dy)[None]
    bad = fx.clone()
    bad[0, 3, 1] = float("inf")
    for solve in (
        lambda **kw: F.solve_fmap(bad, fy, tx, ty, **kw),
        lambda **kw: RegularizedFMSolver(**kw)(bad, fy, tx, ty),
    ):
        with pytest.raises(ParameterError, match="NaN or inf"):
            solve()
        with pytest.raises(ParameterError, match="NaN or inf"):
            solve(check=True)
        assert not torch.isfinite(solve(check=False).C_xy).all()  # unchecked: non-finite, no error
        with pytest.raises(ParameterError, match=r"features must be \(B, V, D\)"):
            F.solve_fmap(fx[:, :10], fy, tx, ty, check=False)
    with pytest.raises(ParameterError, match="check must be"):
        F.solve_fmap(fx, fy, tx, ty, check="yes")
    # singular systems (no descriptor information, w_lap = 0): the LU's info is read under check
    zeros, mask = torch.zeros(1, 4, 3, dtype=torch.float64), torch.ones(1, 4, 4, dtype=torch.float64)
    with pytest.raises(ParameterError, match="singular: the descriptor term is zero"):
        solve_rowwise(zeros, zeros, mask, 1.0, 0.0)
    low_rank = torch.zeros(1, 4, 3, dtype=torch.float64)
    low_rank[0, 0, 0] = 1.0  # one descriptor direction for four columns
    with pytest.raises(ParameterError, match=r"Laplacian term is off \(w_lap = 0\)"):
        solve_rowwise(low_rank, low_rank, mask, 1.0, 0.0)
    solve_rowwise(zeros, zeros, mask, 1.0, 0.0, check=False)  # unchecked: no error
    with pytest.raises(ParameterError, match="NaN or inf"):
        FeatureNet(5, 4).double()(bad, tx)
    assert FeatureNet(5, 4, check=False).double()(bad, tx).shape == (1, x.n_vertices, 4)


class _NoHostReads:
    """Tensor methods that copy a value to the host (a sync on an accelerator) raise inside."""

    NAMES = ("__bool__", "__int__", "__float__", "__index__", "item", "tolist", "numpy")

    def __enter__(self):
        self.saved = {name: getattr(torch.Tensor, name) for name in self.NAMES}

        def refuse(*args, **kwargs):
            raise AssertionError("a tensor value was read on the host")

        for name in self.NAMES:
            setattr(torch.Tensor, name, refuse)
        self.bincount, torch.bincount = torch.bincount, refuse
        return self

    def __exit__(self, *exc):
        for name, method in self.saved.items():
            setattr(torch.Tensor, name, method)
        torch.bincount = self.bincount
        return False


def test_unchecked_training_step_reads_no_tensor_value_on_the_host():
    """With check=False a whole step (DiffusionNet with gradient features on a padded batch,
    both maps, the loss with sampled coupling, backward) never reads a tensor value on the host:
    no bool()/int()/.item() on tensors, so no host sync on an accelerator. With the default
    (check=None on CPU) the data checks do read values."""
    from torchfmap.nn import DiffusionNet
    from torchfmap.nn.data import precompute_shape, shape_item
    from torchfmap.nn.networks import features

    items = [
        shape_item(precompute_shape(bumpy_blob(n), 6, 6, 20, k_net=8), dtype=torch.float64) for n in (1, 2)
    ]
    x = collate_shapes(items)
    y = collate_shapes(items[::-1])
    assert x.basis.lengths.tolist() == [42, 162]

    def step(check):
        torch.manual_seed(0)
        net = DiffusionNet(6, 5, width=8, n_blocks=2, dropout=0.0, check=check).double()
        solver = RegularizedFMSolver(check=check)
        loss = UnsupervisedFMLoss(n_samples=30, check=check)
        gen = torch.Generator().manual_seed(0)
        fx, fy = features(net, x), features(net, y)
        C_xy, C_yx = solver(fx, fy, x.basis, y.basis)
        total = loss(C_xy, C_yx, fx, fy, x.basis, y.basis, generator=gen)["total"]
        total.backward()
        return total.detach()

    with _NoHostReads():
        unchecked = step(False)
    with pytest.raises(AssertionError, match="host"), _NoHostReads():
        step(None)
    assert torch.equal(unchecked, step(None))  # the checks change nothing but the errors


def test_random_draws_come_from_the_given_generator(setting):
    """The loss's vertex samples, the augmentation and the recipe's initial weights are drawn from
    given or seeded generators; torch's global RNG state is left untouched."""
    from torchfmap.nn.config import TrainConfig, build_model
    from torchfmap.nn.train import random_rigid

    x, y, dx, dy, eig, stack = setting
    tx, ty = as_batch(*eig)
    fx, fy = torch.tensor(dx)[None], torch.tensor(dy)[None]
    C_xy, C_yx = RegularizedFMSolver()(fx, fy, tx, ty)
    loss = UnsupervisedFMLoss(n_samples=50)
    with pytest.raises(ParameterError, match="needs a generator"):
        loss(C_xy, C_yx, fx, fy, tx, ty)
    state = torch.random.get_rng_state()
    totals = [
        float(loss(C_xy, C_yx, fx, fy, tx, ty, generator=torch.Generator().manual_seed(seed))["total"])
        for seed in (1, 1, 2)
    ]
    assert totals[0] == totals[1] != totals[2]
    xyz = torch.tensor(x.vertices)[None].repeat(2, 1, 1)
    moved = random_rigid(xyz, torch.Generator().manual_seed(0))
    torch.testing.assert_close(moved, random_rigid(xyz, torch.Generator().manual_seed(0)), rtol=0, atol=0)
    T = torch.linalg.lstsq(xyz, moved).solution  # (2, 3, 3): scale * rotation
    assert (torch.linalg.det(T) > 0).all() and not torch.allclose(T[0], T[1])
    # augment='scale' (shapes aligned alike): a pure scaling, T = s I with s in the range
    scaled = random_rigid(xyz, torch.Generator().manual_seed(0), rotate=False)
    S = torch.linalg.lstsq(xyz, scaled).solution
    s = torch.diagonal(S, dim1=-2, dim2=-1)
    eye = torch.eye(3, dtype=S.dtype)
    torch.testing.assert_close(S, s[:, :1, None] * eye, atol=1e-12, rtol=0)
    assert ((s >= 0.9) & (s <= 1.1)).all()
    config = TrainConfig(n_wks=6, width=8, c_out=8, n_blocks=1)
    a, b = build_model(config)[0], build_model(config)[0]
    assert all(torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters(), strict=True))
    assert torch.equal(torch.random.get_rng_state(), state)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(setting):
    x, y, dx, dy, eig, stack = setting
    tx, ty = as_batch(*eig)
    fx, fy = torch.tensor(dx)[None], torch.tensor(dy)[None]
    cpu, _ = F.solve_fmap(fx, fy, tx, ty)
    gpu, _ = F.solve_fmap(fx.cuda(), fy.cuda(), tx.to("cuda"), ty.to("cuda"))
    assert torch.allclose(cpu, gpu.cpu(), atol=1e-10)
