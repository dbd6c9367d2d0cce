"""torch layers (``torchfmap.nn.modules``): the solver layer against the classical solver,
``SoftPointMap``, ``SpectralDiffusion``, ``BasisModule``, the loss and its generator, layers
refusing what the functions refuse."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfmap import ParameterError, harmonic_basis, laplacian_eigenbasis
from torchfmap.bases import prepare_shape
from torchfmap.fmap import solve_fmap
from torchfmap.kinds import KINDS
from torchfmap.nn import (
    BasisModule,
    RegularizedFMSolver,
    SoftPointMap,
    SpectralDiffusion,
    UnsupervisedFMLoss,
    basis_arrays,
)
from torchfmap.nn import functional as F

from ..conftest import LEARNED, as_batch, bumpy_blob


def test_soft_point_map_rows_padding_and_module_equals_functional():
    g = torch.Generator().manual_seed(0)
    fx = torch.randn(2, 9, 4, dtype=torch.float64, generator=g)
    fy = torch.randn(2, 6, 4, dtype=torch.float64, generator=g)
    lengths = torch.tensor([9, 6])  # the second item has 3 padded vertices
    for iters in (0, 5):
        layer = SoftPointMap(tau=0.2, sinkhorn_iters=iters)
        pi = layer(fx, fy, lengths)
        assert pi.shape == (2, 6, 9)
        torch.testing.assert_close(pi.sum(-1), torch.ones(2, 6, dtype=torch.float64), rtol=1e-12, atol=1e-12)
        assert pi[1, :, 6:].abs().max() == 0
        torch.testing.assert_close(pi, F.soft_map(fx, fy, tau=0.2, lengths_x=lengths, sinkhorn_iters=iters))
        # padding is read from lengths only: the same map as the unpadded second item
        torch.testing.assert_close(pi[1:, :, :6], layer(fx[1:, :6], fy[1:]), rtol=1e-12, atol=1e-14)
    # function and layer refuse the same vertex counts (a data check: on for CPU inputs)
    for bad in (torch.tensor([9, 10]), torch.tensor([0, 6])):
        with pytest.raises(ParameterError, match="vertex counts"):
            SoftPointMap()(fx, fy, bad)
        with pytest.raises(ParameterError, match="vertex counts"):
            F.soft_map(fx, fy, lengths_x=bad)
        SoftPointMap(check=False)(fx, fy, bad)  # unchecked: no error (and no host sync)
    with pytest.raises(ParameterError, match="integer vertex counts"):  # a shape check: always
        SoftPointMap(check=False)(fx, fy, torch.ones(2, 9))


def test_soft_maps_both_directions_equal_two_soft_map_calls():
    """One similarity matrix for both directions: the same maps as two calls, padding on either
    side (the x side of the second item, the y side of the first), with and without Sinkhorn."""
    g = torch.Generator().manual_seed(3)
    fx = torch.randn(2, 9, 4, dtype=torch.float64, generator=g)
    fy = torch.randn(2, 7, 4, dtype=torch.float64, generator=g)
    lengths_x, lengths_y = torch.tensor([9, 6]), torch.tensor([5, 7])
    for iters in (0, 4):
        layer = SoftPointMap(tau=0.2, sinkhorn_iters=iters)
        pi_yx, pi_xy = layer.both(fx, fy, lengths_x, lengths_y)
        torch.testing.assert_close(pi_yx, layer(fx, fy, lengths_x), rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(pi_xy, layer(fy, fx, lengths_y), rtol=1e-12, atol=1e-14)
        assert pi_xy[0, :, 5:].abs().max() == 0 and pi_yx[1, :, 6:].abs().max() == 0
        direct = F.soft_maps(fx, fy, tau=0.2, lengths_x=lengths_x, lengths_y=lengths_y, sinkhorn_iters=iters)
        assert isinstance(direct, F.SoftMaps) and direct.pi_yx is direct[0]
        torch.testing.assert_close(tuple(direct), (pi_yx, pi_xy), rtol=0, atol=0)


def test_soft_point_map_small_tau_is_nearest_neighbour():
    """As tau -> 0 the softmax of cosine similarity becomes the argmax; with similarity gaps
    ≥ δ, off-argmax weights are ≤ V·exp(-δ/τ): τ = δ/50 gives < V·e^-50."""
    g = torch.Generator().manual_seed(1)
    fx = torch.randn(1, 30, 5, dtype=torch.float64, generator=g)
    fy = torch.randn(1, 12, 5, dtype=torch.float64, generator=g)
    cos = torch.nn.functional.normalize(fy, dim=-1) @ torch.nn.functional.normalize(fx, dim=-1).mT
    top2 = cos.topk(2, dim=-1).values
    delta = float((top2[..., 0] - top2[..., 1]).min())
    pi = SoftPointMap(tau=delta / 50)(fx, fy)
    hard = torch.nn.functional.one_hot(cos.argmax(-1), 30).to(pi.dtype)
    assert (pi - hard).abs().max() < 30 * np.exp(-50)


def test_soft_point_map_gradcheck():
    g = torch.Generator().manual_seed(2)
    fx = torch.randn(1, 5, 3, dtype=torch.float64, generator=g, requires_grad=True)
    fy = torch.randn(1, 4, 3, dtype=torch.float64, generator=g, requires_grad=True)
    lengths = torch.tensor([4])
    assert torch.autograd.gradcheck(lambda a, b: SoftPointMap(tau=0.3)(a, b, lengths), (fx, fy))
    sinkhorn = SoftPointMap(tau=0.3, sinkhorn_iters=3)
    assert torch.autograd.gradcheck(lambda a, b: sinkhorn(a, b), (fx, fy))


def test_soft_point_map_sinkhorn_gradients_finite_with_padding():
    """A padded vertex (beyond lengths) gets no weight and changes nothing: the padded Sinkhorn map equals
    the unpadded one on the real vertices (round-off), with finite, correct gradients (its
    all -inf column used to give NaN gradients)."""
    g = torch.Generator().manual_seed(2)
    fx = torch.randn(1, 5, 3, dtype=torch.float64, generator=g, requires_grad=True)
    fy = torch.randn(1, 4, 3, dtype=torch.float64, generator=g, requires_grad=True)
    lengths = torch.tensor([4])
    layer = SoftPointMap(tau=0.3, sinkhorn_iters=3)
    pi = layer(fx, fy, lengths)
    grads = torch.autograd.grad(pi[..., 0].sum(), (fx, fy))
    assert all(torch.isfinite(gr).all() for gr in grads)
    assert pi[..., 4].abs().max() == 0
    torch.testing.assert_close(pi[..., :4], layer(fx[:, :4], fy), rtol=1e-12, atol=1e-14)
    assert torch.autograd.gradcheck(lambda a, b: layer(a, b, lengths), (fx, fy))
    for tau in (0.0, -1.0, float("nan")):
        with pytest.raises(ParameterError, match="tau must be finite"):
            SoftPointMap(tau=tau)(fx, fy)


def test_spectral_diffusion_is_heat_semigroup_in_eigenbasis(sphere2):
    """In an eigenbasis (U = I) the layer is Φ diag(e^{-λt}) Φᵀ M x: on x = φ_k it gives
    e^{-λ_k t} φ_k; diffusing twice with t equals once with 2t (semigroup). Round-off only."""
    bm = BasisModule(laplacian_eigenbasis(sphere2, 9))
    basis = bm.batch()
    layer = SpectralDiffusion(9).double()
    t = layer.log_t.exp().detach()
    x = bm.values[None]  # channel k = φ_k
    out = layer(x, basis)
    expected = bm.values * torch.exp(-bm.lam.clip(min=0) * t)
    torch.testing.assert_close(out[0], expected, rtol=1e-9, atol=1e-12)
    twice = layer(layer(x, basis), basis)
    with torch.no_grad():
        layer.log_t += np.log(2.0)
    torch.testing.assert_close(twice, layer(x, basis), rtol=1e-9, atol=1e-12)


def test_basis_arrays(sphere2):
    """values, lumped mass and a spectral frame with U diag(lam) Uᵀ = Φᵀ L Φ (round-off)."""
    basis = laplacian_eigenbasis(sphere2, 6)
    arrays = basis_arrays(basis)
    area = basis.mass.diagonal().sum()  # 4 pi: the arrays are in the unit-area frame
    np.testing.assert_allclose(arrays["mass"], basis.mass.diagonal() / area)
    np.testing.assert_allclose(arrays["values"], basis.values * np.sqrt(area))
    W = arrays["U"] @ np.diag(arrays["lam"]) @ arrays["U"].T
    np.testing.assert_allclose(W, area * basis.projected_laplacian(), atol=1e-10 * np.abs(W).max())
    # still B-orthonormal, in the new mass
    gram = arrays["values"].T @ (arrays["mass"][:, None] * arrays["values"])
    np.testing.assert_allclose(gram, np.eye(6), atol=1e-10)
    with pytest.raises(ParameterError, match="B-orthonormal"):
        basis_arrays(harmonic_basis(sphere2, [0, 5, 9]))


def test_layers_see_a_mesh_in_file_units_as_at_unit_area(bent_pair):
    """A basis of a mesh in its file's units (area far from 1) reaches the layers as the basis
    of the same mesh scaled to unit area: the layers' settings hold at any scale."""
    x = bent_pair[0]
    unit = basis_arrays(laplacian_eigenbasis(x.normalized(), 8))
    for scale in (140.0, 1e-3):  # e.g. a TOSCA cat in centimetres, a scan in kilometres
        big = basis_arrays(laplacian_eigenbasis(x.scaled(scale), 8))
        np.testing.assert_allclose(big["mass"], unit["mass"], rtol=1e-9)
        np.testing.assert_allclose(big["lam"], unit["lam"], rtol=1e-7, atol=1e-9 * unit["lam"].max())
        signs = np.sign(np.sum(big["values"] * unit["values"], axis=0))
        tol = 1e-6 * np.abs(unit["values"]).max()
        np.testing.assert_allclose(big["values"] * signs, unit["values"], atol=tol)


def test_basis_module_rebuilds_from_its_state_dict_and_layers_follow_the_input_dtype():
    """A BasisModule comes back from state_dict alone, prints its sizes, and the layers cast
    the float64 basis to the features' dtype (float32 in -> float32 maps), accepting the module
    itself where a BasisBatch is expected."""
    import torch

    from torchfmap import laplacian_eigenbasis
    from torchfmap.data import demo_pair
    from torchfmap.errors import ParameterError
    from torchfmap.nn import BasisModule, RegularizedFMSolver

    x, _, _ = demo_pair()
    bm = BasisModule(laplacian_eigenbasis(x, 12))
    back = BasisModule.from_state_dict(bm.state_dict())
    for name in BasisModule.BUFFERS:
        assert torch.equal(getattr(back, name), getattr(bm, name))
    assert "V=2562, K=12" in repr(back)
    with pytest.raises(ParameterError, match="lacks"):
        BasisModule.from_state_dict({"values": bm.values})
    feats = torch.randn(1, x.n_vertices, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    solver = RegularizedFMSolver()
    C64, _ = solver(feats, feats, bm.batch(), bm.batch())
    C32, _ = solver(feats.float(), feats.float(), bm, bm)
    assert C64.dtype == torch.float64 and C32.dtype == torch.float32
    # the same map up to float32 round-off of the K x K solves (cond ~ 1 / w_lap-regularised)
    assert torch.allclose(C32.double(), C64, atol=1e-3 * float(C64.abs().max()))
    with pytest.raises(ParameterError, match="expected a BasisBatch"):
        solver(feats, feats, bm.values, bm.values)
    from torchfmap.nn.functional import basis_like

    assert basis_like(bm, feats.float()).values.dtype == torch.float32
    assert basis_like(bm.batch(), feats) is not None and bm().values.shape == (1, x.n_vertices, 12)


@pytest.mark.parametrize("which", ["eig", "stack"])
def test_module_equals_classical_solver(nn_setting, which):
    x, y, dx, dy, eig, stack = nn_setting
    bx, by = eig if which == "eig" else stack
    C = solve_fmap(bx, by, dx, dy, w_lap=1e-2)
    tx, ty = as_batch(bx, by)
    out = RegularizedFMSolver(w_lap=1e-2)(torch.tensor(dx)[None], torch.tensor(dy)[None], tx, ty)
    assert isinstance(out, F.FmapPair) and out.C_xy is out[0] and out.C_yx is out[1]
    C_xy, C_yx = out
    assert np.abs(C_xy[0].numpy() - C).max() < 1e-10 * np.abs(C).max()
    assert np.abs(C_yx[0].numpy() - solve_fmap(by, bx, dy, dx, w_lap=1e-2)).max() < 1e-10 * np.abs(C).max()


def test_basis_module_buffers_move_and_project(nn_setting):
    x, y, dx, dy, eig, stack = nn_setting
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


def test_random_draws_come_from_the_given_generator(nn_setting):
    """The loss's vertex samples, the augmentation and the recipe's initial weights are drawn from
    given or seeded generators; torch's global RNG state is left untouched."""
    from torchfmap.nn.augment import random_rigid
    from torchfmap.nn.config import TrainConfig, build_model

    x, y, dx, dy, eig, stack = nn_setting
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
    scaled = random_rigid(xyz, torch.Generator().manual_seed(0), rotation="none")
    S = torch.linalg.lstsq(xyz, scaled).solution
    s = torch.diagonal(S, dim1=-2, dim2=-1)
    eye = torch.eye(3, dtype=S.dtype)
    torch.testing.assert_close(S, s[:, :1, None] * eye, atol=1e-12, rtol=0)
    assert ((s >= 0.9) & (s <= 1.1)).all()
    config = TrainConfig(n_wks=6, width=8, c_out=8, n_blocks=1)
    a, b = build_model(config)[0], build_model(config)[0]
    assert all(torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters(), strict=True))
    assert torch.equal(torch.random.get_rng_state(), state)


@pytest.mark.parametrize("name", LEARNED)
def test_basis_module_from_mesh_builds_every_kind(small_blob, name):
    import torch

    from torchfmap.nn import BasisModule

    layer = BasisModule.from_mesh(small_blob, k=12, basis=name, seeds=[4, 90], dtype=torch.float32)
    assert layer.k == 12 and layer.values.dtype == torch.float32
    reference = KINDS[name].shape_basis(prepare_shape(small_blob, 0), 12, seeds=[4, 90])
    np.testing.assert_allclose(layer.values.numpy(), reference.values, atol=1e-6)


def test_layers_refuse_what_the_functions_refuse():
    import torch

    from torchfmap.nn import functional as F
    from torchfmap.nn.modules import RegularizedFMSolver
    from torchfmap.nn.networks import DiffusionNet

    for w in (float("nan"), float("inf"), -1.0):
        with pytest.raises(ParameterError, match="solver weights must be finite"):
            RegularizedFMSolver(w_lap=w)
    feats = torch.randn(1, 5, 3, dtype=torch.float64)
    d = dict(dtype=torch.float64)
    basis = F.BasisBatch(
        torch.randn(1, 5, 2, **d),
        torch.ones(1, 5, **d),
        torch.zeros(1, 2, **d),
        torch.eye(2, **d)[None],
        torch.ones(1, 2, **d),
    )
    with pytest.raises(ParameterError, match="solver weights must be finite"):
        F.solve_fmap_batch(feats, feats, basis, basis, w_lap=float("nan"))
    from ..conftest import _batch

    shape = _batch(bumpy_blob(1))
    net = DiffusionNet(c_in=shape.inputs.shape[-1], c_out=4, width=8, n_blocks=1).double()
    inputs = shape.inputs.double().clone()
    inputs[0, 3, 0] = float("nan")
    with pytest.raises(ParameterError, match="DiffusionNet inputs contain NaN"):
        net(inputs, shape.basis, shape.grad)
