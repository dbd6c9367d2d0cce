"""The learned path on dense meshes (``torchfmap.nn.coarse``): the simplification the network
runs on, features carried to every vertex, and ``LearnedMatcher``'s automatic route above a
size (taken here by small meshes with the thresholds lowered)."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
import torch

import torchfmap.kinds.refiners as refiners
import torchfmap.nn.coarse as coarse
import torchfmap.nn.inference as inference
from torchfmap import Mesh
from torchfmap.errors import ParameterError
from torchfmap.nn import LearnedMatcher, TrainConfig, build_model
from torchfmap.nn.coarse import check_coarse, coarse_size, simplify

from ..conftest import bumpy_blob

#: A small recipe: k = 8 solver functions, 12 network eigenfunctions.
TINY = TrainConfig(k=8, k_net=12, n_wks=8, width=8, c_out=8, n_blocks=1)


@pytest.fixture(scope="module")
def dense_pair():
    """``x`` (2,562 vertices) and a vertex-permuted copy ``y`` (y vertex i is x vertex ``perm[i]``)."""
    mesh_x = bumpy_blob(4)
    perm = np.random.default_rng(1).permutation(mesh_x.n_vertices)
    mesh_y = Mesh(mesh_x.vertices[perm], np.argsort(perm)[mesh_x.faces], name="y")
    return mesh_x, mesh_y, perm


def _edge_lengths(mesh: Mesh) -> np.ndarray:
    e = mesh.edges
    return np.linalg.norm(mesh.vertices[e[:, 0]] - mesh.vertices[e[:, 1]], axis=1)


def test_a_simplification_is_made_of_dense_vertices_and_carries_values_back(dense_pair):
    """The coarse vertices are dense vertices (positions kept), at most as many as asked; every
    dense vertex is interpolated from three coarse vertices of one face by convex weights, so
    constants are carried exactly and each vertex's carried position lies on the coarse surface
    within one coarse edge of it."""
    mesh, _, _ = dense_pair
    simple = simplify(mesh, 400)
    S = simple.mesh.n_vertices
    assert 4 <= S <= 400 and simple.n_dense == mesh.n_vertices
    np.testing.assert_array_equal(simple.mesh.vertices, mesh.vertices[simple.vertices])
    assert simple.corners.shape == simple.weights.shape == (mesh.n_vertices, 3)
    assert simple.corners.min() >= 0 and simple.corners.max() < S
    assert (simple.weights >= 0).all()
    np.testing.assert_allclose(simple.weights.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(simple.carry(np.full((S, 2), 3.0)), 3.0, rtol=0, atol=1e-12)
    carried = simple.carry(simple.mesh.vertices)
    gap = np.linalg.norm(carried - mesh.vertices, axis=1)
    assert gap.max() <= _edge_lengths(simple.mesh).max()
    # the samples' own vertices are carried from themselves
    np.testing.assert_allclose(carried[simple.vertices], simple.mesh.vertices, rtol=0, atol=1e-9)


def test_carry_follows_the_inputs_type_dtype_and_leading_dimensions(dense_pair):
    """Tensors stay tensors in their dtype (float32, float64) with their leading dimensions;
    numpy stays numpy; values that are not one row per coarse vertex are refused."""
    simple = simplify(dense_pair[0], 300)
    S, V = simple.mesh.n_vertices, simple.n_dense
    for dtype in (torch.float32, torch.float64):
        out = simple.carry(torch.ones(1, S, 5, dtype=dtype))
        assert isinstance(out, torch.Tensor) and out.dtype == dtype and out.shape == (1, V, 5)
    values = np.random.default_rng(0).normal(size=(S, 4))
    np.testing.assert_allclose(
        simple.carry(torch.as_tensor(values)).numpy(), simple.carry(values), rtol=0, atol=1e-12
    )
    with pytest.raises(ParameterError, match="coarse vertices"):
        simple.carry(np.ones((S + 1, 4)))


def test_a_permuted_copy_is_simplified_alike(dense_pair):
    """Samples are chosen by position only: a vertex-permuted copy gets the same coarse points."""
    mesh_x, mesh_y, perm = dense_pair
    sx, sy = simplify(mesh_x, 300), simplify(mesh_y, 300)
    np.testing.assert_array_equal(np.sort(perm[sy.vertices]), np.sort(sx.vertices))


def test_bad_settings_are_refused_with_the_fix(dense_pair):
    mesh = dense_pair[0]
    for bad in ("fine", 3, True, 2.5):
        with pytest.raises(ParameterError, match="coarse must be 'auto', None"):
            check_coarse(bad)
        with pytest.raises(ParameterError, match="coarse must be"):
            LearnedMatcher(build_model(TINY)[0], TINY, device="cpu", coarse=bad)
    with pytest.raises(ParameterError, match="Fix: run the network on the mesh itself"):
        simplify(mesh, mesh.n_vertices)
    assert coarse_size(None, 10**7) is None and coarse_size(500, 400) is None and coarse_size(500, 501) == 500
    assert coarse_size("auto", coarse.DENSE_NETWORK_VERTICES) is None
    assert coarse_size("auto", coarse.DENSE_NETWORK_VERTICES + 1) == coarse.COARSE_VERTICES


def test_a_dense_pair_runs_the_network_on_simplifications_and_maps_every_vertex(dense_pair, monkeypatch):
    """Past the (lowered) threshold the network sees only the simplifications, the dense meshes
    get no network inputs of their own (no eigenpairs beyond the solver's and ZoomOut's), and
    the map of a permuted copy is the permutation: its carried features are the permuted ones
    and its bases the permuted ones up to signs, so the functional map is exact. No step holds
    a ``V x V`` array (numpy allocations traced)."""
    mesh_x, mesh_y, perm = dense_pair
    V = mesh_x.n_vertices
    monkeypatch.setattr(coarse, "DENSE_NETWORK_VERTICES", 1000)
    monkeypatch.setattr(coarse, "COARSE_VERTICES", 400)
    # the point map and ZoomOut searched locally too, around 300 samples (S << V)
    monkeypatch.setattr(refiners, "LOCAL_SEARCH_PAIRS", 1000**2)
    monkeypatch.setattr(refiners, "SURFACE_SAMPLES", 300)
    seen, real = [], inference.features

    def spy(net, batch):
        seen.append(batch.inputs.shape[1])
        return real(net, batch)

    monkeypatch.setattr(inference, "features", spy)
    matcher = LearnedMatcher(build_model(TINY)[0], TINY, device="cpu")
    tracemalloc.start()
    try:
        result = matcher(mesh_x, mesh_y, refine="zoomout")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert seen and max(seen) <= 400
    assert result.p2p_yx.shape == (V,) and result.refined
    assert (result.p2p_yx_initial == perm).mean() > 0.99
    assert (result.p2p_yx == perm).mean() > 0.99
    assert peak < V * V * 8 / 4, f"peak {peak / 2**20:.0f} MiB: a V x V array"


def test_the_features_of_a_dense_mesh_are_carried_from_its_simplification(dense_pair):
    """``features`` of a mesh above ``coarse`` is one row per dense vertex, the carried features
    of the simplification; ``coarse=None`` runs the network on the mesh itself."""
    mesh = dense_pair[0]
    net = build_model(TINY)[0]
    on_simple = LearnedMatcher(net, TINY, device="cpu", coarse=300)
    feats = on_simple.features(mesh)
    simple = simplify(mesh, 300)
    direct = LearnedMatcher(net, TINY, device="cpu", coarse=None)
    assert feats.shape == (mesh.n_vertices, TINY.c_out)
    np.testing.assert_allclose(feats, simple.carry(direct.features(simple.mesh)), rtol=1e-5, atol=1e-6)
    assert direct.features(mesh).shape == feats.shape
