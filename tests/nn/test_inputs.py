"""torchfmap.nn.inputs: the learned path's per-shape arrays, read off one PreparedShape."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchfmap.bases.prepared as prepared
from torchfmap import laplacian_eigenbasis, prepare_shape
from torchfmap.data import icosphere
from torchfmap.errors import ParameterError
from torchfmap.nn import coordinates_on, network_inputs, shape_arrays, shape_item

from ..conftest import bumpy_blob, random_rotation


def test_network_inputs_are_computed_once_per_shape_and_setting(blob):
    shape = prepare_shape(blob, 30)
    first = network_inputs(shape, 8, 20)
    assert network_inputs(shape, 8, 20) is first  # cached on the shape
    assert network_inputs(shape, 6, 20) is not first
    wks, xyz = first["wks"], first["xyz"]
    assert wks.shape == (blob.n_vertices, 8) and xyz.shape == (blob.n_vertices, 3)
    assert wks.dtype == xyz.dtype == np.float64
    # standardised channels; coordinates centred at the area-weighted centroid, unit area
    np.testing.assert_allclose(wks.mean(axis=0), 0, atol=1e-10)
    np.testing.assert_allclose(wks.std(axis=0), 1, rtol=1e-10)
    mass = shape.operators.mass.diagonal()
    np.testing.assert_allclose(mass @ xyz, 0, atol=1e-12)
    assert np.isclose(shape.frame.area, 1.0, rtol=1e-12)


def test_inputs_do_not_depend_on_position_or_size(blob, rng):
    """WKS is intrinsic and xyz is centred at unit area: a moved, scaled copy gives the same inputs
    (xyz up to the rotation)."""
    R = random_rotation(rng)
    moved = blob.copy(vertices=3.0 * blob.vertices @ R.T + np.array([1.0, -2.0, 0.5]))
    a, b = network_inputs(prepare_shape(blob, 30), 8, 20), network_inputs(prepare_shape(moved, 30), 8, 20)
    np.testing.assert_allclose(b["wks"], a["wks"], atol=1e-6)
    np.testing.assert_allclose(b["xyz"], a["xyz"] @ R.T, atol=1e-10)


def test_a_parts_coordinates_in_its_wholes_frame_are_the_wholes_inputs(blob, rng):
    """A part cut from the whole, lying where it lies: its coordinates in the whole's frame are the
    whole's inputs at its vertices (the part's own frame scales them by 1 / sqrt(area ratio) and
    shifts them); a rigid motion of both turns them, a translation leaves them."""
    from torchfmap.data.cuts import cut_plane

    whole = prepare_shape(blob, 20)
    cut = cut_plane(blob, 0.5, seed=0)
    on_whole = coordinates_on(cut.mesh, whole)
    np.testing.assert_allclose(on_whole, network_inputs(whole, 8, 20)["xyz"][cut.vertices], atol=1e-12)
    own = network_inputs(prepare_shape(cut.mesh, 20), 8, 20)["xyz"]
    spread = np.linalg.norm(own - own.mean(axis=0), axis=1).max()
    assert np.abs(own - on_whole).max() > 0.1 * spread  # not the part's own frame
    R, t = random_rotation(rng), np.array([1.0, -2.0, 0.5])
    moved = coordinates_on(
        cut.mesh.copy(cut.mesh.vertices @ R.T + t), prepare_shape(blob.copy(blob.vertices @ R.T + t), 20)
    )
    np.testing.assert_allclose(moved, on_whole @ R.T, atol=1e-10)
    with pytest.raises(ParameterError, match="prepare_shape"):
        coordinates_on(cut.mesh, blob)


def test_the_eigenbasis_grows_in_place_and_the_laplacian_is_not_rebuilt(blob, monkeypatch):
    shape = prepare_shape(blob, 10)
    laplacians, decompositions = [], []
    eig = prepared.laplacian_eigenbasis
    monkeypatch.setattr(prepared, "laplacian_operators", lambda *a, **k: laplacians.append(a))
    monkeypatch.setattr(
        prepared, "laplacian_eigenbasis", lambda *a, **k: decompositions.append(a) or eig(*a, **k)
    )
    arrays = shape_arrays(shape, 6, 8, 40, k_net=12)
    shape_arrays(shape, 6, 8, 40, k_net=12)  # a second call reuses all of it
    assert shape.n_eigen == 40 and not laplacians and len(decompositions) == 1
    assert arrays["values"].shape == (blob.n_vertices, 6) and arrays["net_values"].shape[1] == 12
    for key in ("grad_rows", "grad_cols", "grad_x", "grad_y", "grad_order_t"):
        np.testing.assert_array_equal(arrays[key], shape.gradient()[key])


def test_arrays_handed_out_are_the_callers_to_change(blob):
    """The shape's cached inputs and gradient stay as computed whatever a caller does with the
    arrays (and the tensors of its items, which share their memory)."""
    shape = prepare_shape(blob, 20)
    first = shape_arrays(shape, 6, 8, 20)
    reference = {key: first[key].copy() for key in ("wks", "xyz", "grad_x", "values", "vertices")}
    for key in reference:
        first[key][...] = 0
    shape_item(first, dtype=torch.float64)["inputs"].zero_()
    again = shape_arrays(shape, 6, 8, 20)
    for key, value in reference.items():
        np.testing.assert_array_equal(again[key], value, err_msg=key)
    np.testing.assert_array_equal(blob.vertices, reference["vertices"])  # the mesh too


def test_a_mesh_smaller_than_the_wks_spectrum_still_gives_arrays():
    """The WKS takes the eigenpairs a small mesh has (V - 1); the bases must fit (k, k_net < V)."""
    small = icosphere(1)
    assert small.n_vertices < 100
    arrays = shape_arrays(small, 6, 8)  # k_wks = 100 by default
    assert arrays["wks"].shape == (small.n_vertices, 8) and np.isfinite(arrays["wks"]).all()
    with pytest.raises(ParameterError, match="k_net=60 eigenfunctions need a mesh of more than 60"):
        shape_arrays(small, 6, k_net=60)


def test_shape_arrays_of_a_mesh_and_of_its_prepared_shape_agree(blob):
    a = shape_arrays(blob, 6, 8, 20, k_net=8)
    b = shape_arrays(prepare_shape(blob, 20), 6, 8, 20, k_net=8)
    assert a.keys() == b.keys()
    for key in ("wks", "xyz", "mass", "lam", "grad_x", "grad_y", "vertices"):
        np.testing.assert_allclose(a[key], b[key], rtol=1e-8, atol=1e-8, err_msg=key)
    # eigenfunctions up to sign
    np.testing.assert_allclose(np.abs((a["values"] * b["values"] * a["mass"][:, None]).sum(0)), 1, atol=1e-6)


def test_items_cast_once_to_the_networks_dtype(blob):
    item = shape_item(shape_arrays(blob, 6, 8, 20), inputs="xyz", dtype=torch.float64, name="b", index=3)
    assert item["inputs"].dtype == torch.float64 and item["inputs"].shape == (blob.n_vertices, 3)
    assert item["grad_rows"].dtype == torch.int64 and item["name"] == "b" and item["index"] == 3
    assert shape_item(shape_arrays(blob, 6, 8, 20))["values"].dtype == torch.float32
    arrays = shape_arrays(blob, 6, 8, 20)
    both = shape_item(arrays, inputs="wks+xyz", dtype=torch.float64)["inputs"]  # WKS first, then xyz
    assert both.shape == (blob.n_vertices, 8 + 3)
    assert torch.equal(both[:, :8], torch.as_tensor(arrays["wks"]))
    assert torch.equal(both[:, 8:], item["inputs"])


def test_bad_requests_are_refused_before_any_work(blob):
    with pytest.raises(ParameterError, match="PreparedShape or a Mesh"):
        shape_arrays(blob.vertices, 6)
    with pytest.raises(ParameterError, match="unknown|classical"):
        shape_arrays(blob, 6, basis="no_such_kind")
    with pytest.raises(ParameterError, match="n_wks and k_wks"):
        network_inputs(prepare_shape(blob, 0), 0)


def test_shape_arrays_unit_area_and_standardised_wks():
    """The mesh is scaled to unit area: eigenvalues scale by the area (λ ∝ 1/area), the
    basis is orthonormal for the unit-area mass; WKS features are standardised per column."""
    mesh = bumpy_blob(2)
    arrays = shape_arrays(mesh, k=6, n_wks=5, k_wks=20)
    assert arrays["values"].shape == (mesh.n_vertices, 6) and arrays["wks"].shape == (mesh.n_vertices, 5)
    assert arrays["mass"].sum() == pytest.approx(1.0, rel=1e-12)
    lam_ref = laplacian_eigenbasis(mesh, 6).eigenvalues * mesh.area
    np.testing.assert_allclose(np.sort(arrays["lam"]), lam_ref, rtol=1e-8, atol=1e-10 * lam_ref[-1])
    np.testing.assert_allclose(arrays["wks"].mean(axis=0), 0, atol=1e-10)
    np.testing.assert_allclose(arrays["wks"].std(axis=0), 1, rtol=1e-10)
