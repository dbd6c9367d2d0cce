"""Inference (``torchfmap.nn.inference``, ``item_inference``): point-map rules of dataset items,
the learned matcher
(a ``MatchResult`` like ``match``'s, float64 point maps searched on the device, ZoomOut sized
from the model's k, one Laplacian and one eigendecomposition per mesh, prepared shapes reused,
pickling, refinement names as in ``match``, device plumbing) and CPU-vs-CUDA maps where CUDA
exists."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

import torchfmap.nn.inference as inference
import torchfmap.nn.item_inference as item_inference
from torchfmap import Mesh, prepare_shape, save_mesh
from torchfmap.errors import ParameterError
from torchfmap.fmap import values_to_p2p
from torchfmap.matching.results import MatchResult
from torchfmap.nn import LearnedMatcher, TrainConfig, build_model, save_checkpoint
from torchfmap.nn.data import ShapeDataset

from ..conftest import _agree, bend, bumpy_blob

#: A small recipe: k = 8 solver functions, 12 network eigenfunctions (meshes of 162 vertices).
TINY = TrainConfig(k=8, k_net=12, n_wks=8, width=8, c_out=8, n_blocks=1)


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    net = build_model(TINY)[0]
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.ckpt", net, TINY)


@pytest.fixture(scope="module")
def permuted():
    """``x`` and a vertex-permuted copy ``y`` (y vertex i is x vertex ``perm[i]``)."""
    mesh_x = bumpy_blob(2)
    perm = np.random.default_rng(0).permutation(mesh_x.n_vertices)
    mesh_y = Mesh(mesh_x.vertices[perm], np.argsort(perm)[mesh_x.faces], name="y")
    return mesh_x, mesh_y, perm


def test_predict_p2p_point_map_rules(tmp_path, blob_files):
    """Both point-map rules give valid maps; the orthogonal rule is the pull-back rule applied
    to the transpose (for an orthogonal C they coincide up to ties); unknown rules are refused."""
    from torchfmap.nn.item_inference import predict_p2p

    shapes = ShapeDataset(blob_files, tmp_path, k=8, n_wks=8, progress=False)
    config = TrainConfig(k=8, n_wks=8, width=8, c_out=8, n_blocks=1)
    net, solver, _ = build_model(config)
    for rule in ("orthogonal", "pullback"):
        p2p = predict_p2p(net, solver, shapes[0], shapes[1], p2p_mode=rule)
        assert p2p.shape == (162,) and p2p.min() >= 0 and p2p.max() < 162
    with pytest.raises(ParameterError, match="p2p_mode"):
        predict_p2p(net, solver, shapes[0], shapes[1], p2p_mode="nearest")


def test_learned_matcher_returns_a_match_result_with_float64_maps(permuted):
    """The result is ``match``'s type: the map, ``C_xy (k, k)`` in the model's bases of ``k``
    columns, the network's map as ``p2p_yx_initial``, the basis kind, the model's name and the
    timings. The point map is the orthogonal rule in float64 on the float64 basis values (the
    float32 rule on the same values may differ only at near ties)."""
    mesh_x, mesh_y, _ = permuted
    net = build_model(TINY)[0]
    result = LearnedMatcher(net, TINY, name="tiny", device="cpu")(mesh_x, mesh_y)
    assert isinstance(result, MatchResult)
    assert result.p2p_yx.shape == (mesh_y.n_vertices,) and result.p2p_yx.dtype == np.int64
    assert result.C_xy.shape == (8, 8) and result.C_xy.dtype == np.float64
    assert result.basis_x.k == result.basis_y.k == 8 and result.basis_x.values.dtype == np.float64
    assert result.kind == "laplacian" and result.model == "tiny" and not result.refined
    assert set(result.timings) == {"prepare", "adapt", "network+fmap", "p2p"}
    np.testing.assert_array_equal(result.p2p_yx_initial, result.p2p_yx)
    rule = values_to_p2p(result.C_xy, result.basis_x.values, result.basis_y.values, mode="orthogonal",
                         precision="double")  # fmt: skip
    np.testing.assert_array_equal(result.p2p_yx, rule)


def test_zoomout_grows_from_the_models_k_to_2k_capped_for_small_meshes(permuted, monkeypatch):
    """ZoomOut starts from the network's map at the model's ``k`` and grows to ``k_final``
    (default ``2k``); on meshes of V vertices both are capped at V - 1. The true map of a
    permuted copy is a fixed point of ZoomOut, so refining it keeps it."""
    mesh_x, mesh_y, perm = permuted
    seen = []
    real = inference._zoomout

    def spy(p2p, shapes, k0, k_final, feats):
        seen.append((k0, k_final))
        return real(p2p, shapes, k0, k_final, feats)

    monkeypatch.setattr(inference, "_zoomout", spy)
    matcher = LearnedMatcher(build_model(TINY)[0], TINY, device="cpu")
    result = matcher(mesh_x, mesh_y, refine="zoomout")
    assert seen == [(8, 16)] and result.C_xy.shape == (16, 16) and result.basis_x.k == 16
    assert result.refined and "refine" in result.timings
    matcher(mesh_x, mesh_y, refine="zoomout", k_final=30)
    assert seen[-1] == (8, 30)
    big = TrainConfig(**{**TINY.__dict__, "k": 100})  # 2k = 200 > 161 = V - 1
    matcher = LearnedMatcher(build_model(big)[0], big, device="cpu")
    assert matcher(mesh_x, mesh_y, refine="zoomout").basis_x.k == 161 and seen[-1] == (100, 161)
    monkeypatch.undo()
    shapes = (prepare_shape(mesh_x, 16), prepare_shape(mesh_y, 16))
    feats = (mesh_x.vertices, mesh_y.vertices)
    assert (inference._zoomout(perm, shapes, 8, 16, feats).p2p_yx == perm).all()


def test_zoomout_matches_the_networks_features_of_both_shapes(permuted, monkeypatch):
    """The learned map's ZoomOut is anchored by the features the network gave the pair (those of
    :meth:`LearnedMatcher.features`, float64), so the refinement keeps what the network learned
    where the spectral embeddings disagree."""
    mesh_x, mesh_y, _ = permuted
    seen = []
    real = inference._zoomout

    def spy(p2p, shapes, k0, k_final, feats):
        seen.append(feats)
        return real(p2p, shapes, k0, k_final, feats)

    monkeypatch.setattr(inference, "_zoomout", spy)
    matcher = LearnedMatcher(build_model(TINY)[0], TINY, device="cpu")
    matcher(mesh_x, mesh_y, refine="zoomout")
    assert len(seen) == 1
    fx, fy = seen[0]
    assert fx.dtype == fy.dtype == np.float64
    for got, mesh in ((fx, mesh_x), (fy, mesh_y)):
        want = matcher.features(mesh)
        # the same float32 network on the same inputs, batched alike: equal to its rounding
        np.testing.assert_allclose(got, want, rtol=0, atol=1e3 * 2**-24 * np.abs(want).max())


def test_the_learned_matcher_names_its_refinement_as_match_does(permuted):
    """``refine='zoomout'`` or None, as in ``torchfmap.match``; True / False and other
    refinements are refused, as are ``k_final`` without ZoomOut or below ``k``, before any
    work; so is a negative ``adapt_steps``."""
    mesh_x, mesh_y, _ = permuted
    matcher = LearnedMatcher(build_model(TINY)[0], TINY, device="cpu")
    for refine in ("icp", "seeded", True, False):
        with pytest.raises(ParameterError, match="the learned path refines by 'zoomout' or None"):
            matcher(mesh_x, mesh_y, refine=refine)
    with pytest.raises(ParameterError, match="without refine='zoomout' it changes nothing"):
        matcher(mesh_x, mesh_y, k_final=20)
    with pytest.raises(ParameterError, match="k_final=5 is below k=8"):
        matcher(mesh_x, mesh_y, refine="zoomout", k_final=5)
    with pytest.raises(ParameterError, match="adapt_steps"):
        LearnedMatcher(build_model(TINY)[0], TINY, adapt_steps=-1)


def test_one_laplacian_and_one_eigendecomposition_per_mesh_and_given_shapes_reused(permuted, monkeypatch):
    """With ZoomOut, the network's inputs, its bases and ZoomOut's eigenbasis all come from one
    prepared shape per mesh; given prepared shapes (eigenpairs 0, as ``evaluate_pairs`` makes
    them) cost no Laplacian and one eigendecomposition each, and give the same map; shapes of
    other meshes are refused."""
    import torchfmap.bases.prepared as prepared

    mesh_x, mesh_y, _ = permuted
    matcher = LearnedMatcher(build_model(TINY)[0], TINY, device="cpu")
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
    own = matcher(mesh_x, mesh_y, refine="zoomout")
    assert counts == {"laplacian": 2, "eigen": 2}
    monkeypatch.undo()
    shapes = (prepare_shape(mesh_x, 0), prepare_shape(mesh_y, 0))
    monkeypatch.setattr(prepared, "laplacian_operators", lap)
    monkeypatch.setattr(prepared, "laplacian_eigenbasis", eig)
    again = matcher(mesh_x, mesh_y, refine="zoomout", shapes=shapes)
    assert counts == {"laplacian": 2, "eigen": 4}
    matcher(mesh_x, mesh_y, refine="zoomout", shapes=shapes)  # reused: nothing computed again
    assert counts == {"laplacian": 2, "eigen": 4}
    monkeypatch.undo()
    np.testing.assert_array_equal(again.p2p_yx, own.p2p_yx)
    with pytest.raises(ParameterError, match="of these meshes"):
        matcher(mesh_x, mesh_y, shapes=(shapes[1], shapes[0]))


def test_the_matcher_pickles_as_its_checkpoint_and_settings(tiny_checkpoint, permuted):
    """Built from a checkpoint, the pickle holds its name and settings, not the weights; the
    copy reloads the network and gives the same map. Built from a network, the network
    travels (on the CPU) and the copy gives the same map too."""
    mesh_x, mesh_y, _ = permuted
    matcher = LearnedMatcher.from_checkpoint(tiny_checkpoint, device="cpu", adapt_steps=1)
    data = pickle.dumps(matcher)
    assert len(data) < 2000 and b"state_dict" not in data
    copy = pickle.loads(data)
    assert (copy.checkpoint, copy.adapt_steps, copy.device) == (tiny_checkpoint, 1, torch.device("cpu"))
    np.testing.assert_array_equal(copy(mesh_x, mesh_y).p2p_yx, matcher(mesh_x, mesh_y).p2p_yx)
    built = LearnedMatcher(build_model(TINY)[0], TINY, name="mine", device="cpu")
    copy = pickle.loads(pickle.dumps(built))
    assert copy.name == "mine" and copy.checkpoint is None
    np.testing.assert_array_equal(copy(mesh_x, mesh_y).p2p_yx, built(mesh_x, mesh_y).p2p_yx)
    with pytest.raises(ParameterError, match="no checkpoint file"):
        LearnedMatcher.from_checkpoint("no_such_model")


class _DeviceSpy(torch.nn.Module):
    """Wraps a network and records the device of every input it is called with."""

    def __init__(self, net) -> None:
        super().__init__()
        self.net, self.devices = net, []

    def forward(self, inputs, basis, grad):
        self.devices.append(inputs.device)
        return self.net(inputs, basis, grad)


def test_network_solver_and_point_map_search_run_on_the_matchers_device(permuted, monkeypatch):
    """The device plumbing on the CPU: ``device`` resolves once, the network's parameters and
    its inputs are on it; operators, eigenbases and the point-map search stay float64 numpy
    (the one search of :func:`~torchfmap.fmap.fmap_to_p2p`). With ``torch.device('meta')`` (no
    data, any machine) the network is moved there."""
    mesh_x, mesh_y, _ = permuted
    spy = _DeviceSpy(build_model(TINY)[0])
    matcher = LearnedMatcher(spy, TINY, device="cpu")
    searched = []
    real = inference.fmap_to_p2p

    def search(C, bx, by, **kw):
        searched.append((type(C), C.dtype, kw["precision"]))
        return real(C, bx, by, **kw)

    monkeypatch.setattr(inference, "fmap_to_p2p", search)
    result = matcher(mesh_x, mesh_y)
    assert spy.devices == [torch.device("cpu")] * 2
    assert searched == [(np.ndarray, np.float64, "double")]
    assert isinstance(result.basis_x.values, np.ndarray)
    meta = LearnedMatcher(build_model(TINY)[0], TINY, device=torch.device("meta"))
    assert meta.device.type == "meta" and all(p.is_meta for p in meta.net.parameters())


def test_zoomout_of_a_scaled_target_is_the_same_map(small_bent_pair):
    """Shapes are prepared in their unit-area frames: a target at 1000x scale gives the same
    learned map and the same ZoomOut (up to near ties)."""
    x, y, _ = small_bent_pair
    config = TrainConfig(**{**TINY.__dict__, "k": 10, "k_net": 10})
    matcher = LearnedMatcher(build_model(config)[0], config, device="cpu")
    ref = matcher(x, y, refine="zoomout", k_final=30)
    scaled = matcher(x, y.scaled(1e3), refine="zoomout", k_final=30)
    assert _agree(scaled.p2p_yx_initial, ref.p2p_yx_initial) >= 0.99
    assert _agree(scaled.p2p_yx, ref.p2p_yx) >= 0.99


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_and_cpu_maps_agree():
    """A shipped model on the demo pair on CUDA and on the CPU: the same eigenbases (CPU float64)
    and float32 networks whose sums run in another order, so features differ by float32
    round-off and only near-tied vertices may match differently (the ZoomOut map, from the
    network's map, likewise)."""
    from torchfmap.data import demo_pair_paths
    from torchfmap.io import load_mesh

    x, y = (load_mesh(p) for p in demo_pair_paths()[:2])
    cpu = LearnedMatcher.from_checkpoint("faust_r", device="cpu")
    cuda = LearnedMatcher.from_checkpoint("faust_r", device="cuda")
    shapes = (prepare_shape(x, 0), prepare_shape(y, 0))
    a, b = (m(x, y, shapes=shapes) for m in (cpu, cuda))
    assert b.timings and np.abs(b.C_xy - a.C_xy).max() < 1e-3 * np.abs(a.C_xy).max()
    assert _agree(b.p2p_yx, a.p2p_yx) >= 0.99
    a, b = (m(x, y, refine="zoomout", shapes=shapes) for m in (cpu, cuda))
    assert _agree(b.p2p_yx, a.p2p_yx) >= 0.99


def test_a_model_trained_facing_anywhere_tries_the_targets_facings(permuted, monkeypatch):
    """An XYZ model trained with augment='up' matches a target turned half a turn about y as it
    matches the unturned one (the quarter turns are tried and the most isometric map kept); other
    models try one facing."""
    from dataclasses import replace

    mesh_x, mesh_y, perm = permuted
    up = replace(TINY, inputs="xyz", augment="up")
    matcher = LearnedMatcher(build_model(up)[0], up, device="cpu")
    assert matcher.facings() == inference.FACINGS and len(inference.FACINGS) == 4
    assert LearnedMatcher(build_model(TINY)[0], TINY, device="cpu").facings() == (0.0,)
    turn = np.diag([-1.0, 1.0, -1.0])  # half a turn about y
    straight = matcher(mesh_x, mesh_y)
    turned = matcher(mesh_x, mesh_y.copy(mesh_y.vertices @ turn.T))
    assert _agree(straight.p2p_yx, turned.p2p_yx) > 0.99
    # the criterion: 0 for the identity between a shape and itself, positive for a swapped map
    seen = []
    real = inference.laplacian_defect
    monkeypatch.setattr(
        inference, "laplacian_defect", lambda C, bx, by: seen.append(real(C, bx, by)) or seen[-1]
    )
    matcher(mesh_x, mesh_x)
    assert len(seen) == 4
    sx = item_inference.pair_batches(*[matcher._items(prepare_shape(mesh_x, 12), 0)[0]] * 2, "cpu")[0]
    eye = torch.eye(TINY.k, dtype=torch.float64)
    assert real(eye, sx.basis, sx.basis) < 1e-9 < real(eye[[1, 0, *range(2, TINY.k)]], sx.basis, sx.basis)


def test_features_follow_the_vertices_and_reuse_a_prepared_shape(permuted):
    """``features`` is ``(V, c_out)`` float64; WKS inputs are intrinsic, so a vertex-permuted copy
    gets the permuted features (to float32 rounding through the network); a prepared shape is
    reused, and one of another mesh is refused."""
    mesh_x, mesh_y, perm = permuted
    matcher = LearnedMatcher(build_model(TINY)[0], TINY, device="cpu")
    fx = matcher.features(mesh_x)
    assert fx.shape == (mesh_x.n_vertices, TINY.c_out) and fx.dtype == np.float64
    fy = matcher.features(mesh_y, shape=prepare_shape(mesh_y, 20))
    # float32 through the network: sums of at most a few hundred terms (a vertex's neighbours,
    # k_net eigenfunctions, width channels), each rounded at 2**-24 of the largest feature
    scale = np.abs(fx).max()
    np.testing.assert_allclose(fy, fx[perm], rtol=0, atol=1e3 * 2**-24 * scale)
    with pytest.raises(ParameterError, match="shape must be prepare_shape"):
        matcher.features(mesh_x, shape=prepare_shape(mesh_y, 20))


def test_a_part_is_matched_by_the_partial_solve_with_the_networks_features(permuted):
    """``partial=True``: the partial functional map of the model's ``k`` with the network's
    features next to SHOT (the same map as ``match_partial`` given them ``with_shot``), an overlap on the
    whole and the model's name; adaptation (a whole-shape loss) is refused with it."""
    from torchfmap.data.cuts import cut_plane
    from torchfmap.matching.partial import match_partial

    mesh_x = permuted[0]
    part = cut_plane(mesh_x, 0.6, seed=0).mesh
    xyz = TrainConfig(**{**TINY.__dict__, "inputs": "wks+xyz"})
    matcher = LearnedMatcher(build_model(xyz)[0], xyz, device="cpu")
    shapes = (prepare_shape(mesh_x, 20), prepare_shape(part, 20))
    result = matcher(mesh_x, part, partial=True, refine="zoomout", shapes=shapes)
    assert result.kind == "partial" and result.model == matcher.name and result.refined
    assert result.overlap.shape == (mesh_x.n_vertices,) and result.p2p_yx.shape == (part.n_vertices,)
    # the part's coordinate inputs are taken in the whole's frame
    feats_y = matcher.features(part, shape=shapes[1], whole=shapes[0])
    feats = matcher.features(mesh_x, shape=shapes[0]), feats_y
    assert not np.allclose(feats[1], matcher.features(part, shape=shapes[1]))
    want = match_partial(*shapes, k=TINY.k, refine="zoomout", descriptors=feats, with_shot=True)
    np.testing.assert_array_equal(result.p2p_yx, want.p2p_yx)
    tuned = LearnedMatcher(build_model(TINY)[0], TINY, device="cpu", adapt_steps=1)
    with pytest.raises(ParameterError, match="adapt"):
        tuned(mesh_x, part, partial=True)


def test_a_shot_models_features_ignore_rigid_motion_and_scale_of_wholes_and_parts(permuted, rng):
    """SHOT inputs (local frames, radius in units of the whole's ``sqrt(area)``) and an intrinsic
    network: a whole turned, moved and scaled 3x gets the same features, and so does a part turned
    with its own motion (its radius is its whole's), and the partial map with it."""
    from torchfmap.data.cuts import cut_plane

    from ..conftest import random_rotation

    mesh_x = permuted[0]
    part = cut_plane(mesh_x, 0.6, seed=0).mesh
    cfg = TrainConfig(**{**TINY.__dict__, "inputs": "shot"})
    matcher = LearnedMatcher(build_model(cfg)[0], cfg, device="cpu")

    def moved(mesh, scale):
        return mesh.copy(scale * mesh.vertices @ random_rotation(rng).T + rng.normal(size=3))

    whole, turned = prepare_shape(mesh_x, 20), moved(mesh_x, 3.0)
    fx = matcher.features(mesh_x, shape=whole)
    # float32 through the network on inputs equal to float64 rounding (as for a permuted copy)
    atol = 1e3 * 2**-24 * np.abs(fx).max()
    np.testing.assert_allclose(matcher.features(turned), fx, rtol=0, atol=atol)
    fy = matcher.features(part, shape=prepare_shape(part, 20), whole=whole)
    np.testing.assert_allclose(matcher.features(moved(part, 1.0), whole=whole), fy, rtol=0, atol=atol)
    assert not np.allclose(matcher.features(part), fy, atol=atol)  # its own radius is another
    turned = moved(part, 1.0)
    maps = [matcher(mesh_x, p, partial=True, refine="zoomout").p2p_yx for p in (part, turned)]
    np.testing.assert_array_equal(maps[1], maps[0])


def test_dataset_item_maps_follow_the_learned_matchers_rule_and_need_the_models_solver(tmp_path):
    """``predict_p2p`` converts in float64 by the orthogonal rule, as ``LearnedMatcher`` does (one
    rule); ``evaluate`` takes the model's own solver and refuses to guess one."""
    from torchfmap.nn import build_solver
    from torchfmap.nn.item_inference import evaluate, pair_batches, predict_p2p, solve_xy
    from torchfmap.nn.networks import features

    mesh = bumpy_blob(2)
    files = [
        save_mesh(mesh, tmp_path / "a.off"),
        save_mesh(mesh.copy(bend(mesh.vertices, 0.3)), tmp_path / "b.off"),
    ]
    shapes = ShapeDataset(files, False, **TINY.dataset_kwargs(), progress=False)
    net, solver, _ = build_model(TINY)
    x, y = shapes[0], shapes[1]
    p2p = predict_p2p(net, solver, x, y)
    with torch.no_grad():
        sx, sy = pair_batches(x, y, "cpu")
        C = solve_xy(solver, features(net, sx), features(net, sy), sx.basis, sy.basis)[0].double().numpy()
    phi_x, phi_y = (item["values"].double().numpy() for item in (x, y))
    np.testing.assert_array_equal(p2p, values_to_p2p(C, phi_x, phi_y, mode="orthogonal", precision="double"))
    with pytest.raises(ParameterError, match="model's solver"):
        evaluate(net, shapes, [(0, 1)], [None], None)
    assert build_solver(TINY)[0] is not None


def test_a_part_too_small_for_the_model_is_refused_in_the_models_terms(permuted):
    """A model of ``k = 40`` on a part of fewer vertices, raw or refined: one error naming the
    model's sizes and the fix, never advice to prepare shapes (which a matcher's user does not
    call); a part the model fits is solved at the model's ``k`` capped at its ``V - 1``."""
    from torchfmap.data.cuts import cut_plane

    mesh_x = permuted[0]
    part = cut_plane(mesh_x, 0.15, seed=0).mesh
    config = TrainConfig(**{**TINY.__dict__, "k": 40})
    assert part.n_vertices <= config.k
    matcher = LearnedMatcher(build_model(config)[0], config, device="cpu")
    for refine in (None, "zoomout"):
        with pytest.raises(ParameterError, match="k=40") as err:
            matcher(mesh_x, part, partial=True, refine=refine)
        assert "prepare_shape" not in str(err.value)
    result = LearnedMatcher(build_model(TINY)[0], TINY, device="cpu")(mesh_x, part, partial=True)
    assert result.C_xy.shape[1] == min(TINY.k, part.n_vertices - 1)
