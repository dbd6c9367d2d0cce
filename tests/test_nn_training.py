"""Datasets and cache, a short training run on dev data, and 2-process DDP on the CPU."""

from __future__ import annotations

import socket
import time
from dataclasses import asdict

import numpy as np
import pytest
import torch

from torchfmap import save_mesh
from torchfmap.eval import gt_from_vts
from torchfmap.io import read_vts
from torchfmap.nn.checkpoints import load_checkpoint, read_checkpoint
from torchfmap.nn.config import TrainConfig, build_model
from torchfmap.nn.data import PairDataset, PrecomputeCache, ShapeDataset, collate_pairs, mesh_key
from torchfmap.nn.inference import evaluate
from torchfmap.nn.train import ddp_worker, train

from .conftest import bend, bumpy_blob, data_path


@pytest.fixture(scope="module")
def blob_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("blobs")
    base = bumpy_blob(2)
    return [
        save_mesh(base.copy(bend(base.vertices, s)), folder / f"blob{i}.off")
        for i, s in enumerate((0.1, 0.3, 0.5))
    ]


def test_cache_detects_corruption_and_rebuilds(tmp_path, blob_files):
    shapes = ShapeDataset(blob_files, tmp_path, k=8, n_wks=8, progress=False)
    entries = sorted(tmp_path.glob("*.npz"))
    assert len(entries) == 3 and not list(tmp_path.glob("*.tmp"))
    reference = shapes[0]["values"].clone()
    path = tmp_path / f"{mesh_key(__import__('torchfmap').load_mesh(blob_files[0]), shapes.params)}.npz"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])  # truncated
    assert PrecomputeCache(tmp_path).load(path.stem) is None
    reloaded = ShapeDataset(blob_files[:1], tmp_path, k=8, n_wks=8, progress=False)
    assert torch.equal(reloaded[0]["values"], reference)  # rebuilt transparently
    with np.load(path) as z:  # altered content in a valid container
        arrays = {k: z[k] for k in z.files}
    arrays["mass"] = arrays["mass"] * 2
    np.savez(path, **arrays)
    assert PrecomputeCache(tmp_path).load(path.stem) is None
    assert torch.equal(
        shapes[0]["mass"], ShapeDataset(blob_files[:1], tmp_path, k=8, n_wks=8, progress=False)[0]["mass"]
    )
    path.write_bytes(b"not a zip file")
    assert torch.equal(
        ShapeDataset(blob_files[:1], tmp_path, k=8, n_wks=8, progress=False)[0]["values"], reference
    )


def test_collate_pairs(tmp_path, blob_files):
    shapes = ShapeDataset(blob_files, tmp_path, k=8, n_wks=8, progress=False)
    batch = collate_pairs([(shapes[0], shapes[1]), (shapes[2], shapes[0])])
    basis, feats = batch["x"].basis, batch["x"].inputs
    assert basis.values.shape == (2, 162, 8) and feats.shape == (2, 162, 8)
    assert basis.lengths is None and batch["x"].lengths.tolist() == [162, 162]  # equal sizes: no padding
    assert batch["names"] == [("blob0", "blob1"), ("blob2", "blob0")]


def test_short_training_improves_dev_pair(tmp_path):
    folder = data_path("tosca5k_dev")
    files = [folder / "cat0.off", folder / "cat1.off"]
    config = TrainConfig(k=20, n_wks=16, k_net=32, lr=3e-3, width=32, c_out=32, n_blocks=2)
    shapes = ShapeDataset(files, tmp_path, **config.dataset_kwargs(), progress=False)
    gt = gt_from_vts(read_vts(folder / "corres" / "cat0.vts"), read_vts(folder / "corres" / "cat1.vts"))
    net, solver, loss_fn = build_model(config)
    before = evaluate(net, shapes, [(0, 1)], [gt], solver, max_points=200)
    ckpt = tmp_path / "net.ckpt"
    opt = torch.optim.Adam(net.parameters(), lr=config.lr)
    state = train(
        net,
        PairDataset(shapes),
        loss_fn,
        opt,
        solver=solver,
        epochs=8,
        checkpoint=ckpt,
        config=config,
        progress=False,
    )
    after = evaluate(net, shapes, [(0, 1)], [gt], solver, max_points=200)
    first, last = state.losses[0]["total"], np.mean([t["total"] for t in state.losses[-4:]])
    assert last < first
    assert after < before
    loaded, cfg, meta = load_checkpoint(ckpt, best=False)
    assert cfg == config and meta["train_state"]["epoch"] == 8
    for a, b in zip(loaded.state_dict().values(), net.state_dict().values(), strict=True):
        assert torch.equal(a, b)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_ddp_two_processes_identical_weights(tmp_path, blob_files):
    config = TrainConfig(k=8, n_wks=8, k_net=8, epochs=1, width=16, c_out=16, n_blocks=1)
    torch.multiprocessing.spawn(
        ddp_worker,
        args=(2, _free_port(), blob_files, tmp_path / "cache", asdict(config), tmp_path / "ddp.ckpt"),
        nprocs=2,
    )
    w0 = torch.load(tmp_path / "rank0.pt")
    w1 = torch.load(tmp_path / "rank1.pt")
    assert w0.keys() == w1.keys()
    for key in w0:
        assert torch.equal(w0[key], w1[key]), key
    untrained = build_model(config)[0].state_dict()
    assert any(not torch.equal(w0[k], untrained[k]) for k in w0)  # it did train
    assert (tmp_path / "ddp.ckpt").exists()


def test_predict_p2p_point_map_rules(tmp_path, blob_files):
    """Both point-map rules give valid maps; the orthogonal rule is the pull-back rule applied
    to the transpose (for an orthogonal C they coincide up to ties); unknown rules are refused."""
    from torchfmap.errors import ParameterError
    from torchfmap.nn.inference import predict_p2p

    shapes = ShapeDataset(blob_files, tmp_path, k=8, n_wks=8, progress=False)
    config = TrainConfig(k=8, n_wks=8, width=8, c_out=8, n_blocks=1)
    net, solver, _ = build_model(config)
    for rule in ("orthogonal", "pullback"):
        p2p = predict_p2p(net, solver, shapes[0], shapes[1], p2p_mode=rule)
        assert p2p.shape == (162,) and p2p.min() >= 0 and p2p.max() < 162
    with pytest.raises(ParameterError, match="p2p_mode"):
        predict_p2p(net, solver, shapes[0], shapes[1], p2p_mode="nearest")


def test_refine_p2p_reuses_prepared_shapes_and_refuses_wrong_ones():
    """With the meshes prepared once and passed in (reused across pairs), ZoomOut gives exactly
    the map it computes itself; the true map of a vertex-permuted copy is kept; shapes of
    another mesh or with too few eigenpairs are refused."""
    from torchfmap import Mesh, prepare_shape
    from torchfmap.errors import ParameterError
    from torchfmap.nn.inference import refine_p2p

    mesh_x = bumpy_blob(2)
    perm = np.random.default_rng(0).permutation(mesh_x.n_vertices)
    inv = np.argsort(perm)
    mesh_y = Mesh(mesh_x.vertices[perm], inv[mesh_x.faces])  # y vertex i is x vertex perm[i]
    noisy = perm.copy()
    flip = np.random.default_rng(1).choice(len(noisy), len(noisy) // 10, replace=False)
    noisy[flip] = noisy[np.roll(flip, 1)]
    kw = dict(k0=10, k_final=30)
    own = refine_p2p(mesh_x, mesh_y, noisy, **kw)
    same = (prepare_shape(mesh_x, 30), prepare_shape(mesh_y, 30))
    np.testing.assert_array_equal(refine_p2p(mesh_x, mesh_y, noisy, **kw, shapes=same), own)
    more = (prepare_shape(mesh_x, 40), prepare_shape(mesh_y, 40))  # truncated to 30
    np.testing.assert_array_equal(refine_p2p(mesh_x, mesh_y, perm, **kw, shapes=more), perm)
    assert (refine_p2p(mesh_x, mesh_y, noisy, **kw, shapes=more) == perm).mean() > (noisy == perm).mean()
    with pytest.raises(ParameterError, match="eigenpairs"):
        refine_p2p(mesh_x, mesh_y, noisy, **kw, shapes=(more[0], prepare_shape(mesh_y, 20)))
    with pytest.raises(ParameterError, match="prepare_shape"):
        refine_p2p(mesh_x, mesh_y, noisy, **kw, shapes=(prepare_shape(bumpy_blob(1), 30), more[1]))


@pytest.mark.slow
def test_ddp_follows_the_time_budget_and_schedule_of_one_process(tmp_path, blob_files):
    """A DDP run reads its whole budget from the config (train_recipe): a time budget stops it
    (the epochs alone would run far longer) and the cosine schedule reaches its floor there."""
    budget_s = 4.0
    config = TrainConfig(
        k=8,
        n_wks=8,
        k_net=8,
        epochs=None,
        minutes=budget_s / 60,
        width=16,
        c_out=16,
        n_blocks=1,
        clip_grad=1.0,
    )
    t0 = time.perf_counter()
    torch.multiprocessing.spawn(
        ddp_worker,
        args=(2, _free_port(), blob_files, tmp_path / "cache", asdict(config), tmp_path / "ddp.ckpt"),
        nprocs=2,
    )
    assert time.perf_counter() - t0 < 120  # spawn and imports included; the epochs are unbounded
    ckpt = read_checkpoint(tmp_path / "ddp.ckpt")
    state = ckpt["train_state"]
    # training stops at the first step boundary after the budget: within one step of it
    steps = max(state["step"], 1)
    assert budget_s <= state["seconds"] <= budget_s + 3 * state["seconds"] / steps + 1.0
    assert ckpt["config"]["minutes"] == config.minutes and ckpt["config"]["clip_grad"] == 1.0
    lr = ckpt["optimizer"]["param_groups"][0]["lr"]
    assert lr == pytest.approx(config.lr * 0.02, rel=0.05)  # the cosine's floor at the budget's end


def test_train_refuses_an_unknown_augmentation(tmp_path):
    from torchfmap.errors import ParameterError

    mesh = bumpy_blob(2)
    files = [save_mesh(mesh, tmp_path / "a0.off"), save_mesh(mesh.scaled(1.2), tmp_path / "a1.off")]
    shapes = ShapeDataset(files, False, k=8, n_wks=6, k_net=16, progress=False)
    net, solver, loss = build_model(TrainConfig(k=8, n_wks=6, width=8, c_out=8, n_blocks=1))
    opt = torch.optim.Adam(net.parameters())
    with pytest.raises(ParameterError, match="augment must be one of"):
        train(net, PairDataset(shapes), loss, opt, solver=solver, augment="spin", max_steps=1, progress=False)
