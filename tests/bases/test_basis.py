"""The Basis type (``torchfmap.bases.basis``): shape checks, projection and reconstruction, save
and load (checksums, corruption, old formats, long provenance names, missing files), support
statistics."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import (
    Basis,
    ParameterError,
    TorchFmapError,
    basis_stack,
    farthest_point_sampling,
    harmonic_basis,
    laplacian_eigenbasis,
)
from torchfmap._util.files import checksum
from torchfmap.bases import support_fraction
from torchfmap.cli import main
from torchfmap.errors import CorruptFileError, FileReadError

from ..conftest import DEMO, _basis, _err


def test_basis_shape_errors(blob):
    with pytest.raises(ParameterError, match="mass is"):
        Basis(np.ones((10, 2)), np.ones(11))
    with pytest.raises(ParameterError, match=r"\(V, K\)"):
        Basis(np.ones(10), np.ones(10))
    basis = harmonic_basis(blob, [0, 10])
    with pytest.raises(ParameterError, match="rows"):
        basis.project(np.ones(5))


def test_project_reconstruct_round_trip(blob):
    seeds = farthest_point_sampling(blob, 10, metric="euclidean")
    basis = basis_stack(blob, seeds, times=[1e-2])
    f = basis.values @ np.arange(basis.k, dtype=float)
    assert np.allclose(basis.project(f), np.arange(basis.k))
    assert np.allclose(basis.reconstruct(basis.project(f)), f)
    raw = basis_stack(blob, seeds, times=[1e-2], harmonic=False)
    nonorth = Basis(raw.values * 3.0 + 0.1 * raw.values[:, :1], raw.mass)
    target = nonorth.values[:, 2]
    assert np.allclose(nonorth.reconstruct(nonorth.least_squares(target)), target)
    with pytest.raises(ParameterError, match="rows"):
        basis.reconstruct(np.ones(basis.k + 1))


def test_save_load_round_trip_and_corruption(blob, tmp_path):
    seeds = farthest_point_sampling(blob, 6, metric="euclidean")
    basis = basis_stack(blob, seeds, times=[1e-2], n_eigen=5)
    path = basis.save(tmp_path / "basis.npz")
    back = Basis.load(path)
    assert np.array_equal(back.values, basis.values) and back.orthonormal
    assert back.provenance == basis.provenance
    assert abs(back.mass - basis.mass).max() == 0 and abs(back.stiffness - basis.stiffness).max() == 0
    assert [p.name for p in tmp_path.iterdir()] == ["basis.npz"]  # atomic: no temp file left
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # truncated
    with pytest.raises(CorruptFileError, match="rebuild"):
        Basis.load(path)
    # altered values inside a valid container
    basis.save(path)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["values"] = arrays["values"] + 1e-9
    np.savez(path, **arrays)
    with pytest.raises(CorruptFileError, match="checksum"):
        Basis.load(path)


def test_support_fraction_by_hand():
    f = np.array([[1.0, 0.0], [0.5, 0.0], [1e-4, 2.0], [0.0, -1.0]])
    assert support_fraction(f, eps=1e-3).tolist() == [0.5, 0.5]
    assert support_fraction(f[:, 0], eps=1e-5) == 0.75
    mass = np.diag([1.0, 1.0, 2.0, 4.0])
    assert np.allclose(support_fraction(f, eps=1e-3, mass=mass), [2 / 8, 6 / 8])


def test_eigenvalues_survive_save_load(blob, tmp_path):
    from torchfmap import Basis

    basis = laplacian_eigenbasis(blob, 6)
    back = Basis.load(basis.save(tmp_path / "eig.npz"))
    assert np.array_equal(back.eigenvalues, basis.eigenvalues)


def test_old_basis_format_still_loads(tmp_path):
    """A file as the previous ``Basis.save`` wrote it (plain np.savez, ``checksum`` key)."""
    basis = _basis(n=20, k=3)
    arrays = {
        "values": basis.values,
        "mass_row": np.arange(20, dtype=np.int64),
        "mass_col": np.arange(20, dtype=np.int64),
        "mass_data": np.full(20, 1 / 20),
        "prov_kind": np.array(["custom"] * 3, dtype="U16"),
        "prov_seed": np.full(3, -1, dtype=np.int64),
        "prov_time": np.full(3, np.nan),
        "prov_index": np.full(3, -1, dtype=np.int64),
        "prov_kept": np.ones(3, dtype=bool),
        "orthonormal": np.array(False),
        "version": np.array(1),
    }
    arrays["checksum"] = np.array(checksum(arrays))
    np.savez(tmp_path / "old.npz", **arrays)
    back = Basis.load(tmp_path / "old.npz")
    assert np.array_equal(back.values, basis.values) and back.provenance == basis.provenance


def test_long_provenance_names_survive_save(tmp_path, sphere2):
    """Provenance kinds were cut to 16 characters on save."""
    from torchfmap import Basis, Column, laplacian_eigenbasis

    b = laplacian_eigenbasis(sphere2, 2)
    long = Basis(
        b.values, b.mass, [Column("a-rather-long-custom-kind-name"), Column("x")], stiffness=b.stiffness
    )
    back = Basis.load(long.save(tmp_path / "long.npz"))
    assert back.provenance[0].family == "a-rather-long-custom-kind-name"


def test_missing_input_files_are_torchfmap_errors_with_exit_1(tmp_path, capsys):
    from torchfmap.bases import Basis

    with pytest.raises(FileReadError, match="cannot read the basis file") as info:
        Basis.load(tmp_path / "none.npz")
    assert isinstance(info.value, FileNotFoundError) and isinstance(info.value, TorchFmapError)
    src, tgt = f"{DEMO}/blob_a.off", f"{DEMO}/blob_b.off"
    out = str(tmp_path / "m.txt")
    assert (
        main(["match", src, tgt, "--bases", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--out", out])
        == 1
    )
    err = _err(capsys)
    assert "cannot read the basis file" in err and "Fix:" in err and "[Errno" not in err


@pytest.mark.parametrize(
    "edit, problem",
    [
        (lambda a: a.pop("values"), "no 'values' array"),
        (lambda a: a.update(values=a["values"][:, 0]), "values of shape"),
        (lambda a: a.update(values=np.where(a["values"] > 0, np.nan, a["values"])), "not finite"),
        (lambda a: a.update(mass_row=a["mass_row"] + 1), "outside the"),
        (lambda a: a.update(prov_seed=a["prov_seed"][:-1]), "shorter"),
        (lambda a: a.update(version=np.array(99)), "format version 99"),
    ],
)
def test_a_file_with_a_valid_checksum_but_no_basis_in_it_is_refused(blob, tmp_path, edit, problem):
    """Found by the fuzz suite: arrays written with a valid checksum but missing, reshaped or out
    of range raised KeyError / ValueError from scipy, or loaded NaN values."""
    from torchfmap._util.files import load_arrays, save_arrays

    seeds = farthest_point_sampling(blob, 4, metric="euclidean")
    path = basis_stack(blob, seeds, times=[1e-2], n_eigen=3).save(tmp_path / "basis.npz")
    arrays = load_arrays(path)
    edit(arrays)
    path.unlink()
    save_arrays(path, arrays)
    expected = rf"basis\.npz is not a basis torchfmap can read \(.*{problem}.*Fix"
    with pytest.raises(CorruptFileError, match=expected):
        Basis.load(path)
