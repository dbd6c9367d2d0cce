"""Datasets and batches (``torchfmap.nn.data``): the cache (corrupt entries,
a full disk), ``ShapeDataset`` for every learned kind, ``PairDataset``, padded collation, class
pairs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfmap import ParameterError, save_mesh
from torchfmap._util.files import load_arrays
from torchfmap.kinds import KINDS
from torchfmap.nn import PairDataset, ShapeDataset, collate_pairs
from torchfmap.nn import functional as F
from torchfmap.nn.data import PrecomputeCache, ShapeBatch, class_pairs, mesh_key

from ..conftest import LEARNED, _batch, bend, bumpy_blob


@pytest.fixture(scope="module")
def two_size_datasets(tmp_path_factory):
    """Shapes of 642 and 162 vertices, with K = 8 and K = 5 (two datasets), float64.
    (shape_arrays needs more than k_wks = 100 vertices.)"""
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
    C_xy, C_yx = F.solve_fmap_batch(batch["x"].inputs, batch["y"].inputs, batch["x"].basis, batch["y"].basis)
    for b, (ix, iy) in enumerate(items):
        bx = F.BasisBatch(
            *(ix[n][None] for n in ("values", "mass", "lam", "U")),
            torch.ones(1, ix["lam"].shape[0], dtype=torch.float64),
        )
        by = F.BasisBatch(
            *(iy[n][None] for n in ("values", "mass", "lam", "U")),
            torch.ones(1, iy["lam"].shape[0], dtype=torch.float64),
        )
        ref_xy, ref_yx = F.solve_fmap_batch(ix["inputs"][None], iy["inputs"][None], bx, by)
        kx, ky = ix["lam"].shape[0], iy["lam"].shape[0]
        scale = ref_xy.abs().max()
        torch.testing.assert_close(C_xy[b, :ky, :kx], ref_xy[0], rtol=0, atol=1e-10 * float(scale))
        torch.testing.assert_close(C_yx[b, :kx, :ky], ref_yx[0], rtol=0, atol=1e-10 * float(scale))
        assert not C_xy[b, ky:].any() and not C_xy[b, :, kx:].any()


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


def test_class_pairs_and_shape_batch_to():
    names = ["cat0", "cat1", "wolf_0", "wolf_1", "dog"]
    assert class_pairs(names) == [(0, 1), (1, 0), (2, 3), (3, 2)]
    assert class_pairs(["a", "b"]) == [(0, 1), (1, 0)]  # no class with two shapes: all pairs
    shape = _batch(bumpy_blob(1))
    assert isinstance(shape, ShapeBatch)
    moved = shape.to(torch.float32)
    assert moved.basis.values.dtype == moved.inputs.dtype == moved.grad.weight_x.dtype == torch.float32
    assert moved.grad.rows.dtype == moved.lengths.dtype == torch.int64


@pytest.mark.parametrize("name", LEARNED)
def test_shape_dataset_accepts_every_kind(tmp_path, small_blob, name):
    from torchfmap import save_mesh
    from torchfmap.nn.data import ShapeDataset

    paths = [save_mesh(small_blob, tmp_path / "a.off"), save_mesh(small_blob.scaled(2.0), tmp_path / "b.off")]
    data = ShapeDataset(paths, cache_dir=False, k=16, basis=name, progress=False)
    item = data[0]
    values, mass = np.asarray(item["values"], dtype=float), np.asarray(item["mass"], dtype=float)
    assert values.shape == (small_blob.n_vertices, 16)
    # float32 storage: the Gram matrix of the unit-area basis is I to single precision
    np.testing.assert_allclose(values.T @ (mass[:, None] * values), np.eye(16), atol=1e-4)


def test_the_learned_path_refuses_a_classical_only_kind_by_name(tmp_path, small_blob):
    from torchfmap import save_mesh
    from torchfmap.nn import BasisModule
    from torchfmap.nn.data import ShapeDataset

    classical = [name for name, kind in KINDS.items() if not kind.learned]
    assert classical == ["hybrid"]
    path = save_mesh(small_blob, tmp_path / "a.off")
    with pytest.raises(ParameterError, match="hybrid basis is solved block-wise.*Fix: one of laplacian"):
        ShapeDataset([path], cache_dir=False, k=16, basis="hybrid", progress=False)
    with pytest.raises(ParameterError, match="hybrid basis is solved block-wise"):
        BasisModule.from_mesh(small_blob, k=12, basis="hybrid")


def test_cache_uses_the_same_writer_and_rebuilds_corrupt_entries(tmp_path):
    cache = PrecomputeCache(tmp_path)
    calls = []

    def compute():
        calls.append(1)
        return {"values": np.arange(6.0).reshape(3, 2)}

    first = cache.get("k", compute)
    second = cache.get("k", compute)
    assert len(calls) == 1 and np.array_equal(first["values"], second["values"])
    assert load_arrays(cache.path("k"), "__checksum__").keys() == {"values"}  # cache key kept
    cache.path("k").write_bytes(cache.path("k").read_bytes()[:50])
    cache.get("k", compute)
    assert len(calls) == 2
    assert [p.name for p in tmp_path.iterdir()] == ["k.npz"]


def test_a_cache_that_cannot_store_falls_back_to_computing(tmp_path, monkeypatch, caplog):
    import torchfmap.nn.data as data

    cache = data.PrecomputeCache(tmp_path / "cache")

    def refuse(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(data, "save_arrays", refuse)
    with caplog.at_level("WARNING", logger="torchfmap.nn.data"):
        arrays = cache.get("key", lambda: {"a": np.arange(4)})
    assert np.array_equal(arrays["a"], np.arange(4))
    assert "computed without the cache" in caplog.text
