"""Gradient operator, spatial gradient features, the reference DiffusionNet, the feature-network
plug-in protocol, and the ``train`` / ``match --checkpoint`` commands on tiny meshes."""

from __future__ import annotations

import inspect
import io
from dataclasses import asdict, replace

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from torchfmap import Mesh, save_mesh
from torchfmap._files import save_checked_bytes
from torchfmap.cli import main
from torchfmap.errors import ParameterError
from torchfmap.nn import functional as F
from torchfmap.nn.checkpoints import (
    load_checkpoint,
    load_network,
    network_record,
    read_checkpoint,
    save_checkpoint,
)
from torchfmap.nn.config import TrainConfig, build_model
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
from torchfmap.nn.networks import (
    DiffusionNet,
    FeatureNet,
    FeatureNetwork,
    SpatialGradientFeatures,
    check_network,
    features,
)
from torchfmap.nn.train import train
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
    out = F.spatial_gradient(f, grad)
    assert isinstance(out, F.TangentGradient) and out.x is out[0]
    gx, gy = out
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
        # the same edges shuffled but claimed sorted (order_t given): the data check sorts them
        claimed = shuffled._replace(order_t=torch.as_tensor(ops["grad_order_t"])[None])
        torch.testing.assert_close(F.spatial_gradient(fb_t, claimed).x[0], sx[0], rtol=1e-12, atol=1e-12)
    # operators indexing vertices the features do not have: refused by the function and the layer
    # (a data check, on by default for CPU inputs); shapes that do not fit: refused always
    short = f[:, :30].detach()
    with pytest.raises(ParameterError, match=r"outside \[0, 30\)"):
        F.spatial_gradient(short, batch.grad)
    with pytest.raises(ParameterError, match=r"outside \[0, 30\)"):
        SpatialGradientFeatures(3).double()(short, batch.grad)
    with pytest.raises(ParameterError, match="must all be"):
        F.spatial_gradient(f, batch.grad._replace(cols=batch.grad.cols[:, :-1]), check=False)


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
    """A user-written network: a linear lift and one learned diffusion (ignores gradients). Its
    constructor arguments are in ``init_kwargs``, so checkpoints can rebuild it."""

    def __init__(self, c_in: int, c_out: int = 8) -> None:
        super().__init__()
        self.init_kwargs = {"c_in": c_in, "c_out": c_out}
        self.lift, self.diffuse = torch.nn.Linear(c_in, c_out), SpectralDiffusion(c_out)

    def forward(self, inputs, basis, grad):
        return self.diffuse(self.lift(inputs), basis)


def _padded_batch():
    """Two shapes of 42 and 36 vertices (vertex padding), K = 6, K_net = 8, float64."""
    items = [
        shape_item(precompute_shape(m, 6, 6, 20, k_net=8), dtype=torch.float64)
        for m in (bumpy_blob(1), _grid(6))
    ]
    return collate_shapes(items)


NETWORKS = {
    "DiffusionNet": lambda: DiffusionNet(6, 5, width=8, n_blocks=1),
    "FeatureNet": lambda: FeatureNet(6, 5, width=8, n_blocks=1),
    "TinyNet": lambda: TinyNet(6, 5),
}


@pytest.mark.parametrize("name", sorted(NETWORKS))
def test_networks_follow_the_protocol(name):
    """Called with the protocol's arguments ``(inputs, basis, grad)`` on a padded batch of two
    shapes, every network returns ``(B, V, C)`` in the inputs' dtype; the static protocol type
    names the same call."""
    batch = _padded_batch()
    assert batch.lengths.tolist() == [42, 36]
    assert list(inspect.signature(FeatureNetwork.__call__).parameters) == ["self", "inputs", "basis", "grad"]
    for dtype in (torch.float64, torch.float32):
        torch.manual_seed(0)
        net = NETWORKS[name]().to(dtype).eval()  # eval: no dropout draws
        check_network(net)
        shape = batch.to(dtype)
        out = net(shape.inputs, shape.net_basis, shape.grad)
        assert out.shape == (2, 42, 5) and out.dtype == dtype
        torch.testing.assert_close(features(net, shape), out, rtol=0, atol=0)


class TwoArguments(torch.nn.Module):
    def forward(self, inputs, basis):
        return inputs


class WrongDtype(TinyNet):
    def forward(self, inputs, basis, grad):
        return super().forward(inputs, basis, grad).float()


def test_code_that_takes_networks_refuses_non_conforming_ones():
    """``len`` passed the old ``isinstance(net, FeatureNetwork)`` check; now a non-module, a
    forward without ``grad`` and an output in another dtype are refused, by the functions that
    take networks (train, features)."""
    for bad in (len, lambda inputs, basis, grad: inputs):
        with pytest.raises(ParameterError, match="must be a torch.nn.Module"):
            check_network(bad)
    with pytest.raises(ParameterError, match=r"forward must take \(inputs, basis, grad\)"):
        check_network(TwoArguments())
    opt = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1.0)
    with pytest.raises(ParameterError, match="must be a torch.nn.Module"):
        train(len, None, UnsupervisedFMLoss(), opt, progress=False)
    with pytest.raises(ParameterError, match="returned"):
        features(WrongDtype(6, 5).double(), _padded_batch())


def test_user_network_plugs_in_and_its_checkpoint_rebuilds_it(tmp_path):
    folder = tmp_path / "meshes"
    folder.mkdir()
    base = bumpy_blob(2)
    for i, s in enumerate((0.1, 0.3, 0.5)):
        save_mesh(base.copy(bend(base.vertices, s)), folder / f"blob{i}.off")
    shapes = ShapeDataset(folder, False, k=8, n_wks=6, k_net=12, dtype=torch.float64, progress=False)
    net = TinyNet(6).double()
    before = [p.detach().clone() for p in net.parameters()]
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    loss = UnsupervisedFMLoss(n_samples=100)  # sampled coupling: draws from train's generator
    ckpt = tmp_path / "tiny.ckpt"
    state = train(net, PairDataset(shapes), loss, opt, max_steps=3, checkpoint=ckpt, progress=False)
    assert state.step == 3 and all(np.isfinite(t["total"]) for t in state.losses)
    assert any(not torch.equal(a, b) for a, b in zip(before, net.parameters(), strict=True))
    # the checkpoint records the class and its arguments: load_checkpoint rebuilds a TinyNet
    record = read_checkpoint(ckpt)["network"]
    assert record == {"class": f"{TinyNet.__module__}:TinyNet", "kwargs": {"c_in": 6, "c_out": 8}}
    loaded, config, _ = load_checkpoint(ckpt)
    assert type(loaded) is TinyNet and config == TrainConfig() and not loaded.training
    for a, b in zip(loaded.state_dict().values(), net.state_dict().values(), strict=True):
        assert a.dtype == b.dtype and torch.equal(a, b)
    batch = collate_shapes([shapes[0]])
    with torch.no_grad():
        torch.testing.assert_close(features(loaded, batch), features(net.eval(), batch), rtol=0, atol=0)
    # the same training twice gives the same losses: every draw comes from seeded generators
    again = TinyNet(6).double()
    again.load_state_dict(dict(zip(again.state_dict(), before, strict=True)))
    opt = torch.optim.Adam(again.parameters(), lr=1e-2)
    repeat = train(
        again, PairDataset(shapes), UnsupervisedFMLoss(n_samples=100), opt, max_steps=3, progress=False
    )
    assert [t["total"] for t in repeat.losses] == [t["total"] for t in state.losses]


def test_checkpoints_refuse_networks_they_cannot_rebuild_and_load_old_files(tmp_path):
    class Local(TinyNet):  # defined in a function: not importable
        pass

    path = save_checkpoint(tmp_path / "local.ckpt", Local(6), {})
    with pytest.raises(ParameterError, match="cannot be imported"):
        load_checkpoint(path)
    path = save_checkpoint(tmp_path / "nowhere.ckpt", TinyNet(6), {})
    ckpt = read_checkpoint(path)
    ckpt["network"]["class"] = "torchfmap.nowhere:TinyNet"
    with pytest.raises(ParameterError, match="cannot import"):
        load_network(ckpt)
    ckpt["network"]["class"] = "torchfmap.errors:ParameterError"
    with pytest.raises(ParameterError, match="not a torch.nn.Module"):
        load_network(ckpt)
    plain = torch.nn.Linear(3, 2)  # no init_kwargs: the record has the class only
    assert network_record(plain) == {"class": "torch.nn.modules.linear:Linear", "kwargs": None}
    with pytest.raises(ParameterError, match="not its constructor arguments"):
        load_checkpoint(save_checkpoint(tmp_path / "linear.ckpt", plain, {}))
    back = load_checkpoint(
        save_checkpoint(tmp_path / "args.ckpt", plain, {}, net_kwargs={"in_features": 3, "out_features": 2})
    )[0]
    assert torch.equal(back.weight, plain.weight)
    with pytest.raises(ParameterError, match="plain values"):
        save_checkpoint(tmp_path / "bad.ckpt", plain, {}, net_kwargs={"in_features": torch.ones(1)})
    # a checkpoint written before the record: the recipe's DiffusionNet from its config
    config = TrainConfig(k=8, n_wks=6, k_net=8, width=8, c_out=8, n_blocks=1)
    net = build_model(config)[0]
    buffer = io.BytesIO()
    torch.save({"state_dict": net.state_dict(), "config": asdict(config)}, buffer)
    old = save_checked_bytes(tmp_path / "old.ckpt", buffer.getvalue())
    loaded, cfg, _ = load_checkpoint(old)
    assert type(loaded) is DiffusionNet and cfg == config
    for a, b in zip(loaded.state_dict().values(), net.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    # in such old files 'stack' named the learned mix that is now 'eigen_diffusion'
    buffer = io.BytesIO()
    torch.save({"state_dict": net.state_dict(), "config": asdict(config) | {"basis": "stack"}}, buffer)
    old = save_checked_bytes(tmp_path / "old_stack.ckpt", buffer.getvalue())
    assert load_checkpoint(old)[1].basis == "eigen_diffusion"
    # the recipe's network records itself and comes back the same
    again = load_checkpoint(save_checkpoint(tmp_path / "new.ckpt", net, config))[0]
    stacked = replace(config, basis="stack")  # a new checkpoint's 'stack' is the stack kind
    assert load_checkpoint(save_checkpoint(tmp_path / "stack.ckpt", net, stacked))[1].basis == "stack"
    assert type(again) is DiffusionNet and again.init_kwargs == net.init_kwargs


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
    args = ["train", str(tiny_folder), "--out", str(ckpt), "--k", "8", "--no-cache"]
    assert main([*args, "--max-steps", "3"]) == 0  # without --quiet: the status lines
    first = read_checkpoint(ckpt)
    assert first["train_state"]["step"] == 3 and "6 ordered pairs" in capsys.readouterr().out
    assert main([*args, "--max-steps", "5", "--resume", "--quiet"]) == 0
    assert capsys.readouterr().out == ""
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


def test_eval_command_with_checkpoint_prepares_each_mesh_once_and_pools_agree(
    tiny_folder, tmp_path, capsys, monkeypatch
):
    """``torchfmap eval --checkpoint``: each mesh is precomputed once per process, the maps are
    those of ``match_with_network`` pair by pair, a pool of 2 gives the same table, and settings
    the network path would ignore are refused."""
    import torchfmap.nn.inference as inference
    from torchfmap.collection import evaluate_pairs
    from torchfmap.eval import discover_pairs, evaluate_map
    from torchfmap.io import load_mesh
    from torchfmap.nn.checkpoints import load_checkpoint

    ckpt = tmp_path / "model.ckpt"
    train = ["train", str(tiny_folder), "--out", str(ckpt), "--k", "8", "--no-cache", "--quiet"]
    assert main([*train, "--max-steps", "2"]) == 0
    capsys.readouterr()
    pairs = list(discover_pairs(tiny_folder))
    assert len(pairs) >= 2
    made = []
    real = inference._prepared
    matcher = inference.CheckpointMatcher(ckpt)
    monkeypatch.setattr(
        inference, "_prepared", lambda m, config, refine: made.append(m) or real(m, config, refine)
    )
    results = evaluate_pairs(pairs, threads=1, matcher=matcher)
    monkeypatch.undo()
    assert len(made) == len({p for pair in pairs for p in pair[2:4]})  # once per mesh
    net, config, _ = load_checkpoint(ckpt)
    for (_, _, pa, pb, gt), result in zip(pairs, results, strict=True):
        x, y = load_mesh(pa), load_mesh(pb)
        p2p = inference.match_with_network(net, config, x, y)
        np.testing.assert_array_equal(result.errors, evaluate_map(x, y, p2p, gt)[1])

    def table(*extra):
        assert (
            main(["eval", str(tiny_folder), "--checkpoint", str(ckpt), "--threads", "1", "--quiet", *extra])
            == 0
        )
        lines = capsys.readouterr().out.splitlines()
        return [line.rsplit("|", 2)[0] for line in lines if line.startswith("| ")]  # without the time

    one = table()
    assert len(one) == len(pairs) + 2 and table("--workers", "2") == one
    assert len(table("--refine", "zoomout", "--adapt", "1")) == len(pairs) + 2
    for bad, message in (
        (["--gt-landmarks", "3"], "without landmarks"),
        (["--basis", "laplacian"], "own basis"),
        (["--refine", "icp"], "ZoomOut only"),
    ):
        assert main(["eval", str(tiny_folder), "--checkpoint", str(ckpt), *bad]) == 2
        assert message in capsys.readouterr().err
    assert main(["eval", str(tiny_folder), "--adapt", "2"]) == 2
    assert "--adapt tunes a trained network" in capsys.readouterr().err
    with pytest.raises(ParameterError, match="a matcher matches pairs by itself, so gt_landmarks, k"):
        evaluate_pairs(pairs, matcher=matcher, gt_landmarks=2, k=8)


def test_class_pairs_and_shape_batch_to():
    names = ["cat0", "cat1", "wolf_0", "wolf_1", "dog"]
    assert class_pairs(names) == [(0, 1), (1, 0), (2, 3), (3, 2)]
    assert class_pairs(["a", "b"]) == [(0, 1), (1, 0)]  # no class with two shapes: all pairs
    shape = _batch(bumpy_blob(1))
    assert isinstance(shape, ShapeBatch)
    moved = shape.to(torch.float32)
    assert moved.basis.values.dtype == moved.inputs.dtype == moved.grad.weight_x.dtype == torch.float32
    assert moved.grad.rows.dtype == moved.lengths.dtype == torch.int64


def test_checkpoint_match_with_zoomout_computes_one_laplacian_and_one_eigenbasis_per_shape(
    tiny_folder, tmp_path, monkeypatch
):
    """``match --checkpoint M --refine zoomout``: the network's inputs, its bases and ZoomOut's
    eigenbasis all come from one prepared shape per mesh."""
    import torchfmap.bases.prepared as prepared
    from torchfmap.io import load_mesh
    from torchfmap.nn.checkpoints import load_checkpoint
    from torchfmap.nn.inference import match_with_network

    ckpt = tmp_path / "model.ckpt"
    args = ["train", str(tiny_folder), "--out", str(ckpt), "--k", "8", "--no-cache", "--quiet"]
    assert main([*args, "--max-steps", "1"]) == 0
    net, config, _ = load_checkpoint(ckpt)
    x, y = load_mesh(tiny_folder / "blob0.ply"), load_mesh(tiny_folder / "blob1.ply")
    counts = {"laplacian": 0, "eigen": 0}
    real_lap, real_eig = prepared.laplacian, prepared.laplacian_eigenbasis

    def lap(*a, **kw):
        counts["laplacian"] += 1
        return real_lap(*a, **kw)

    def eig(*a, **kw):
        counts["eigen"] += 1
        return real_eig(*a, **kw)

    monkeypatch.setattr(prepared, "laplacian", lap)
    monkeypatch.setattr(prepared, "laplacian_eigenbasis", eig)
    refined = match_with_network(net, config, x, y, refine=True)
    assert counts == {"laplacian": 2, "eigen": 2}
    monkeypatch.undo()
    assert refined.shape == (y.n_vertices,)
    pair = [str(tiny_folder / "blob0.ply"), str(tiny_folder / "blob1.ply")]
    out = str(tmp_path / "m.txt")
    flags = ["--checkpoint", str(ckpt), "--refine", "zoomout", "--out", out, "--quiet"]
    assert main(["match", *pair, *flags]) == 0
    np.testing.assert_array_equal(np.loadtxt(tmp_path / "m.txt", dtype=np.int64), refined)


def test_match_with_checkpoint_refuses_flags_it_would_ignore(tiny_folder, tmp_path, capsys):
    ckpt = tmp_path / "model.ckpt"
    args = ["train", str(tiny_folder), "--out", str(ckpt), "--k", "8", "--no-cache", "--quiet"]
    assert main([*args, "--max-steps", "1"]) == 0
    pair = [str(tiny_folder / "blob0.ply"), str(tiny_folder / "blob1.ply")]
    base = ["match", *pair, "--checkpoint", str(ckpt), "--out", str(tmp_path / "m.txt")]
    for extra, flag in (
        (["--k", "10"], "--k"),
        (["--basis", "laplacian"], "--basis"),
        (["--k-final", "20"], "--k-final"),
        (["--w-lap", "0.5"], "--w-lap"),
        (["--times", "0.01"], "--times"),
        (["--p2p-mode", "pullback"], "--p2p-mode"),
    ):
        capsys.readouterr()
        assert main([*base, *extra]) == 2
        assert f"{flag} would change nothing" in capsys.readouterr().err
    assert main([*base, "--refine", "icp"]) == 2
    assert "ZoomOut only" in capsys.readouterr().err


def test_resume_refuses_another_recipe_and_save_refuses_a_wrong_config(tiny_folder, tmp_path, capsys):
    from torchfmap.nn import TrainConfig, build_model, save_checkpoint

    ckpt = tmp_path / "model.ckpt"
    args = ["train", str(tiny_folder), "--out", str(ckpt), "--k", "8", "--no-cache", "--quiet"]
    assert main([*args, "--max-steps", "1"]) == 0
    capsys.readouterr()
    bad = ["train", str(tiny_folder), "--out", str(ckpt), "--k", "10", "--no-cache", "--quiet", "--resume"]
    assert main([*bad, "--max-steps", "2"]) == 2
    assert "--k 10 (checkpoint: 8)" in capsys.readouterr().err
    assert main([*args, "--resume", "--max-steps", "2"]) == 0  # the same recipe continues
    net = build_model(TrainConfig(width=48))[0]
    with pytest.raises(ParameterError, match="width: config 32, network 48"):
        save_checkpoint(tmp_path / "x.ckpt", net, TrainConfig(width=32))
    assert not (tmp_path / "x.ckpt").exists()
