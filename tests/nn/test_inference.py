"""Inference (``torchfmap.nn.inference``): point-map rules, ZoomOut of network maps (prepared
shapes reused, scale invariance), refinement names as in match."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap.cli import main
from torchfmap.nn.config import TrainConfig, build_model
from torchfmap.nn.data import ShapeDataset

from ..conftest import _agree, bumpy_blob


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


def test_the_learned_path_names_its_refinement_as_match_does():
    """``refine='zoomout'`` / None, as in ``torchfmap.match`` (True / False: the older form);
    other refinements are refused before any work."""
    from torchfmap.data import demo_pair_paths
    from torchfmap.errors import ParameterError
    from torchfmap.io import load_mesh
    from torchfmap.nn import CheckpointMatcher, load_checkpoint, match_with_network

    net, config, _ = load_checkpoint("faust_r")
    x, y = (load_mesh(p) for p in demo_pair_paths()[:2])
    with pytest.raises(ParameterError, match="refines by ZoomOut only"):
        match_with_network(net, config, x, y, refine="icp")
    with pytest.raises(ParameterError, match="refines by ZoomOut only"):
        CheckpointMatcher("faust_r", refine="seeded")
    assert CheckpointMatcher("faust_r", refine="zoomout").refine is True
    assert CheckpointMatcher("faust_r").refine is False


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
    real_lap, real_eig = prepared.laplacian_operators, prepared.laplacian_eigenbasis

    def lap(*a, **kw):
        counts["laplacian"] += 1
        return real_lap(*a, **kw)

    def eig(*a, **kw):
        counts["eigen"] += 1
        return real_eig(*a, **kw)

    monkeypatch.setattr(prepared, "laplacian_operators", lap)
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


def test_learned_path_zoomout_of_a_scaled_target_is_the_same_map(small_bent_pair):
    from torchfmap.nn.inference import refine_p2p

    x, y, _ = small_bent_pair
    start = np.random.default_rng(0).integers(0, x.n_vertices, y.n_vertices)
    ref = refine_p2p(x, y, start, k0=10, k_final=30)
    assert _agree(refine_p2p(x, y.scaled(1e3), start, k0=10, k_final=30), ref) >= 0.99
