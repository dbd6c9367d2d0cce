"""Gradient operator, spatial gradient features, the reference DiffusionNet, the feature-network
plug-in protocol, and the ``train`` / ``match --checkpoint`` commands on tiny meshes."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from torchfmap import Mesh, save_mesh
from torchfmap.cli import main
from torchfmap.nn import functional as F
from torchfmap.nn.data import (
    PairDataset,
    ShapeBatch,
    ShapeDataset,
    class_pairs,
    collate_shapes,
    precompute_shape,
    shape_item,
)
from torchfmap.nn.geometry import gradient_operator
from torchfmap.nn.modules import SpectralDiffusion, UnsupervisedFMLoss
from torchfmap.nn.networks import DiffusionNet, FeatureNetwork, SpatialGradientFeatures
from torchfmap.nn.train import features, read_checkpoint, train
from torchfmap.operators.laplacian import normalize_area

from .conftest import bend, bumpy_blob, random_rotation


def _grid(n: int = 5) -> Mesh:
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1.3, n), indexing="ij")
    vertices = np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return Mesh(vertices, faces)


def _batch(mesh: Mesh, k: int = 8, k_net: int = 12):
    arrays = precompute_shape(mesh, k, 6, 20, k_net=k_net)
    return collate_shapes([shape_item(arrays, dtype=torch.float64)])


def test_gradient_is_exact_for_linear_functions_on_a_plane():
    """On a flat mesh with normal +z the frames are (x, y) and every face gradient of a linear
    function is exact, so the vertex gradient is exact to round-off."""
    mesh = _grid()
    ops = gradient_operator(mesh)
    grad = F.GradientBatch(
        *(torch.as_tensor(ops[k])[None] for k in ("grad_rows", "grad_cols", "grad_x", "grad_y"))
    )
    f = torch.as_tensor(mesh.vertices @ np.array([0.7, -2.0, 5.0]))[None, :, None]
    gx, gy = F.spatial_gradient(f, grad)
    torch.testing.assert_close(gx, torch.full_like(gx, 0.7), rtol=0, atol=1e-12)
    torch.testing.assert_close(gy, torch.full_like(gy, -2.0), rtol=0, atol=1e-12)


def test_spatial_gradient_in_any_edge_order_and_padded_batches_equals_the_sparse_matrix():
    """The compressed-row product equals the scipy operator for (a) the precomputed sorted
    edges with their transpose order, (b) the same edges shuffled without it (sorted on the
    call), (c) a padded batch of two meshes of different sizes; so do the gradients
    (``Gᵀ ∂``, checked against scipy's transpose)."""
    meshes = [bumpy_blob(1), _grid(6)]
    items = [shape_item(precompute_shape(m, 6, 4, 20), dtype=torch.float64) for m in meshes]
    batch = collate_shapes(items)
    V = batch.inputs.shape[1]
    g = torch.Generator().manual_seed(4)
    f = torch.randn(2, V, 3, dtype=torch.float64, generator=g, requires_grad=True)
    seed = torch.randn(2, V, 3, dtype=torch.float64, generator=g)
    gx, gy = F.spatial_gradient(f, batch.grad)
    ((gx + 2 * gy) * seed).sum().backward()
    for b, m in enumerate(meshes):
        ops = gradient_operator(normalize_area(m))  # precompute_shape works at unit area
        n = len(m.vertices)
        edges = (ops["grad_rows"], ops["grad_cols"])
        Gx, Gy = (sp.csr_matrix((ops[w], edges), shape=(n, n)) for w in ("grad_x", "grad_y"))
        fb = f[b, :n].detach().numpy()
        np.testing.assert_allclose(gx[b, :n].detach().numpy(), Gx @ fb, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(gy[b, :n].detach().numpy(), Gy @ fb, rtol=1e-12, atol=1e-12)
        if n < V:  # padded vertices get no gradient
            assert gx[b, n:].abs().max() == 0 and gy[b, n:].abs().max() == 0
        expect = Gx.T @ seed[b, :n].numpy() + 2 * (Gy.T @ seed[b, :n].numpy())
        np.testing.assert_allclose(f.grad[b, :n].numpy(), expect, rtol=1e-12, atol=1e-12)
        # shuffled edges, no transpose order: sorted on the call, same result
        perm = torch.randperm(len(ops["grad_rows"]), generator=g)
        keys = ("grad_rows", "grad_cols", "grad_x", "grad_y")
        shuffled = F.GradientBatch(*(torch.as_tensor(ops[k])[perm][None] for k in keys))
        fb_t = f[b : b + 1, :n].detach()
        sx, sy = F.spatial_gradient(fb_t, shuffled)
        torch.testing.assert_close(sx[0], gx[b, :n].detach(), rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(sy[0], gy[b, :n].detach(), rtol=1e-12, atol=1e-12)


def test_gradient_features_gradcheck():
    shape = _batch(bumpy_blob(1))
    layer = SpatialGradientFeatures(3).double()
    x = torch.randn(1, shape.inputs.shape[1], 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda x, a, b: F.gradient_features(*F.spatial_gradient(x, shape.grad), a, b),
        (x, layer.A_re, layer.A_im),
    )
    assert torch.autograd.gradcheck(lambda x: layer(x, shape.grad), (x,))


def test_gradient_features_do_not_depend_on_the_tangent_frame():
    """Rotating every frame by its own angle multiplies g by a unit complex number."""
    shape = _batch(bumpy_blob(1))
    layer = SpatialGradientFeatures(4).double()
    x = torch.randn(1, shape.inputs.shape[1], 4, dtype=torch.float64)
    gx, gy = F.spatial_gradient(x, shape.grad)
    theta = torch.rand(1, x.shape[1], 1, dtype=torch.float64) * 6.28
    rx, ry = torch.cos(theta) * gx - torch.sin(theta) * gy, torch.sin(theta) * gx + torch.cos(theta) * gy
    torch.testing.assert_close(
        F.gradient_features(gx, gy, layer.A_re, layer.A_im),
        F.gradient_features(rx, ry, layer.A_re, layer.A_im),
    )


def test_diffusion_net_with_wks_is_invariant_to_rigid_motions():
    """WKS, the eigenbasis and the gradient-feature magnitudes are intrinsic or frame-free; the
    eigensolver converges to ~1e-10, so outputs agree to 1e-6 of their scale. A reflection
    (mirror and re-wind faces) changes the output: gradient features see orientation."""
    mesh = bumpy_blob(2)
    rng = np.random.default_rng(3)
    moved = mesh.copy(mesh.vertices @ random_rotation(rng).T * 1.0 + rng.normal(size=3))
    torch.manual_seed(0)
    net = DiffusionNet(6, 8, width=16, n_blocks=2).double().eval()
    with torch.no_grad():
        a, b = (features(net, _batch(m)) for m in (mesh, moved))
    scale = float(a.abs().max())
    torch.testing.assert_close(a, b, rtol=0, atol=1e-6 * scale)
    mirrored = Mesh(mesh.vertices * np.array([-1.0, 1, 1]), mesh.faces[:, ::-1])
    with torch.no_grad():
        c = features(net, _batch(mirrored))
    assert float((a - c).abs().max()) > 1e-3 * scale


class TinyNet(torch.nn.Module):
    """A user-written network: a linear lift and one learned diffusion (ignores gradients)."""

    def __init__(self, c_in: int, c_out: int = 8) -> None:
        super().__init__()
        self.lift, self.diffuse = torch.nn.Linear(c_in, c_out), SpectralDiffusion(c_out)

    def forward(self, inputs, basis, grad):
        return self.diffuse(self.lift(inputs), basis)


def test_user_network_plugs_in(tmp_path):
    folder = tmp_path / "meshes"
    folder.mkdir()
    base = bumpy_blob(2)
    for i, s in enumerate((0.1, 0.3, 0.5)):
        save_mesh(base.copy(bend(base.vertices, s)), folder / f"blob{i}.off")
    shapes = ShapeDataset(folder, False, k=8, n_wks=6, k_net=12, dtype=torch.float64, progress=False)
    net = TinyNet(6).double()
    assert isinstance(net, FeatureNetwork)
    before = [p.detach().clone() for p in net.parameters()]
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    state = train(net, PairDataset(shapes), UnsupervisedFMLoss(), opt, max_steps=3, progress=False)
    assert state.step == 3 and all(np.isfinite(t["total"]) for t in state.losses)
    assert any(not torch.equal(a, b) for a, b in zip(before, net.parameters(), strict=True))


@pytest.fixture
def tiny_folder(tmp_path):
    folder = tmp_path / "tiny"
    folder.mkdir()
    base = bumpy_blob(2)
    for i, s in enumerate((0.1, 0.3, 0.5)):
        save_mesh(
            base.copy(bend(base.vertices, s)),
            folder / f"blob{i}.off.gz" if i == 2 else folder / f"blob{i}.ply",
        )
    return folder


def test_train_command_writes_and_resumes_a_checkpoint(tiny_folder, tmp_path, capsys):
    ckpt = tmp_path / "model.ckpt"
    args = ["train", str(tiny_folder), "--out", str(ckpt), "--k", "8", "--no-cache", "--quiet"]
    assert main([*args, "--max-steps", "3"]) == 0
    first = read_checkpoint(ckpt)
    assert first["train_state"]["step"] == 3 and "6 ordered pairs" in capsys.readouterr().out
    assert main([*args, "--max-steps", "5", "--resume"]) == 0
    second = read_checkpoint(ckpt)
    losses = [t["total"] for t in second["train_state"]["losses"]]
    assert second["train_state"]["step"] == 5 and len(losses) == 5 and np.isfinite(losses).all()
    assert losses[:3] == [t["total"] for t in first["train_state"]["losses"]]


def test_match_command_with_checkpoint(tiny_folder, tmp_path, capsys):
    ckpt = tmp_path / "model.ckpt"
    main(
        [
            "train",
            str(tiny_folder),
            "--out",
            str(ckpt),
            "--k",
            "8",
            "--no-cache",
            "--quiet",
            "--max-steps",
            "2",
        ]
    )
    out = tmp_path / "map.txt"
    src, tgt = tiny_folder / "blob0.ply", tiny_folder / "blob1.ply"
    assert (
        main(
            [
                "match",
                str(src),
                str(tgt),
                "--checkpoint",
                str(ckpt),
                "--out",
                str(out),
                "--adapt",
                "1",
                "--refine",
                "zoomout",
            ]
        )
        == 0
    )
    p2p = np.loadtxt(out, dtype=np.int64)
    assert p2p.shape == (162,) and p2p.min() >= 0 and p2p.max() < 162
    assert all(line.strip().isdigit() for line in out.read_text().splitlines())


def test_class_pairs_and_shape_batch_to():
    names = ["cat0", "cat1", "wolf_0", "wolf_1", "dog"]
    assert class_pairs(names) == [(0, 1), (1, 0), (2, 3), (3, 2)]
    assert class_pairs(["a", "b"]) == [(0, 1), (1, 0)]  # no class with two shapes: all pairs
    shape = _batch(bumpy_blob(1))
    assert isinstance(shape, ShapeBatch)
    moved = shape.to(torch.float32)
    assert moved.basis.values.dtype == moved.inputs.dtype == moved.grad.weight_x.dtype == torch.float32
    assert moved.grad.rows.dtype == moved.lengths.dtype == torch.int64
