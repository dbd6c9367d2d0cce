"""SoftPointMap, soft_map_to_fmap, SpectralDiffusion, basis_arrays, precompute_shape and
PairDataset, plus padded collation of shapes with different V and K."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfmap import ParameterError, harmonic_basis, laplacian_eigenbasis, save_mesh
from torchfmap.nn import (
    BasisModule,
    PairDataset,
    ShapeDataset,
    SoftPointMap,
    SpectralDiffusion,
    basis_arrays,
    collate_pairs,
    precompute_shape,
)
from torchfmap.nn import functional as F

from .conftest import bend, bumpy_blob


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


def test_soft_map_to_fmap_of_identity_is_identity(sphere2):
    """A permutation soft map between a shape and its relabelled copy gives C = I (the bases
    are relabelled too): Φ_yᵀ M_y Π Φ_x = Φ_xᵀ M_x Φ_x = I to eigensolver round-off."""
    basis = BasisModule(laplacian_eigenbasis(sphere2, 8)).batch()
    pi = torch.eye(sphere2.n_vertices, dtype=torch.float64)[None]
    C = F.soft_map_to_fmap(pi, basis, basis)
    torch.testing.assert_close(C[0], torch.eye(8, dtype=torch.float64), rtol=0, atol=1e-10)


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
    np.testing.assert_allclose(arrays["mass"], basis.mass.diagonal())
    W = arrays["U"] @ np.diag(arrays["lam"]) @ arrays["U"].T
    np.testing.assert_allclose(W, basis.projected_laplacian(), atol=1e-10 * np.abs(W).max())
    with pytest.raises(ParameterError, match="B-orthonormal"):
        basis_arrays(harmonic_basis(sphere2, [0, 5, 9]))


def test_precompute_shape_unit_area_and_standardised_wks():
    """The mesh is scaled to unit area: eigenvalues scale by the area (λ ∝ 1/area), the
    basis is orthonormal for the unit-area mass; WKS features are standardised per column."""
    mesh = bumpy_blob(2)
    arrays = precompute_shape(mesh, k=6, n_wks=5, k_wks=20)
    assert arrays["values"].shape == (mesh.n_vertices, 6) and arrays["wks"].shape == (mesh.n_vertices, 5)
    assert arrays["mass"].sum() == pytest.approx(1.0, rel=1e-12)
    lam_ref = laplacian_eigenbasis(mesh, 6).eigenvalues * mesh.area
    np.testing.assert_allclose(np.sort(arrays["lam"]), lam_ref, rtol=1e-8, atol=1e-10 * lam_ref[-1])
    np.testing.assert_allclose(arrays["wks"].mean(axis=0), 0, atol=1e-10)
    np.testing.assert_allclose(arrays["wks"].std(axis=0), 1, rtol=1e-10)


@pytest.fixture(scope="module")
def two_size_datasets(tmp_path_factory):
    """Shapes of 642 and 162 vertices, with K = 8 and K = 5 (two datasets), float64.
    (precompute_shape needs more than k_wks = 100 vertices.)"""
    folder = tmp_path_factory.mktemp("sizes")
    big = [
        save_mesh(bumpy_blob(3).copy(bend(bumpy_blob(3).vertices, s)), folder / f"big{i}.off")
        for i, s in enumerate((0.1, 0.3))
    ]
    small = [save_mesh(bumpy_blob(2), folder / "small.off")]
    cache = tmp_path_factory.mktemp("cache")
    opts = dict(n_wks=6, dtype=torch.float64, progress=False)
    return ShapeDataset(big, cache, k=8, **opts), ShapeDataset(small, cache, k=5, **opts)


def test_pair_dataset(two_size_datasets):
    big, _ = two_size_datasets
    pairs = PairDataset(big)
    assert len(pairs) == 2 and pairs.pairs == [(0, 1), (1, 0)]
    x, y = pairs[1]
    assert (x["index"], y["index"]) == (1, 0)
    assert PairDataset(big, [(0, 0)]).pairs == [(0, 0)]


def test_collate_pairs_pads_and_gives_unpadded_maps(two_size_datasets):
    """Pairs of different V (642/162) and K (8/5): padded shapes, zero mass and values on padded
    vertices, valid = 0 / identity U on padded columns, and the solver's maps on the padded batch
    equal the per-item unpadded maps (the padded systems decouple exactly; round-off of
    K x K solves with condition ≤ 1e6 gives atol 1e-10 relative to max |C|)."""
    big, small = two_size_datasets
    items = [(big[0], small[0]), (small[0], big[1])]
    batch = collate_pairs(items)
    assert batch["names"] == [("big0", "small"), ("small", "big1")]
    for side, col in (("x", 0), ("y", 1)):
        basis, feats = batch[side].basis, batch[side].inputs
        assert basis.values.shape == (2, 642, 8) and feats.shape == (2, 642, 6)
        assert batch[side].net_basis is basis  # no network basis in these items: the solver's
        for b in range(2):
            v, k = items[b][col]["values"].shape
            assert basis.lengths[b] == batch[side].lengths[b] == v
            assert not basis.mass[b, v:].any() and not basis.values[b, v:].any()
            assert not basis.values[b, :, k:].any()
            assert basis.valid[b].tolist() == [1.0] * k + [0.0] * (8 - k)
            torch.testing.assert_close(basis.U[b, k:, k:], torch.eye(8 - k, dtype=torch.float64))
            assert not basis.lam[b, k:].any()
    C_xy, C_yx = F.fmap_solve(batch["x"].inputs, batch["y"].inputs, batch["x"].basis, batch["y"].basis)
    for b, (ix, iy) in enumerate(items):
        bx = F.BasisBatch(
            *(ix[n][None] for n in ("values", "mass", "lam", "U")),
            torch.ones(1, ix["lam"].shape[0], dtype=torch.float64),
        )
        by = F.BasisBatch(
            *(iy[n][None] for n in ("values", "mass", "lam", "U")),
            torch.ones(1, iy["lam"].shape[0], dtype=torch.float64),
        )
        ref_xy, ref_yx = F.fmap_solve(ix["inputs"][None], iy["inputs"][None], bx, by)
        kx, ky = ix["lam"].shape[0], iy["lam"].shape[0]
        scale = ref_xy.abs().max()
        torch.testing.assert_close(C_xy[b, :ky, :kx], ref_xy[0], rtol=0, atol=1e-10 * float(scale))
        torch.testing.assert_close(C_yx[b, :kx, :ky], ref_yx[0], rtol=0, atol=1e-10 * float(scale))
        assert not C_xy[b, ky:].any() and not C_xy[b, :, kx:].any()


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
