"""Old names (torchfmap._deprecation): each renamed keyword, attribute and module name still
works, warns with the new name, and gives what the new name gives; both names at once are refused."""

from __future__ import annotations

import dataclasses
import importlib
import warnings

import numpy as np
import pytest

import torchfmap as tf
from torchfmap._deprecation import module_aliases, renamed_keywords, warn_renamed
from torchfmap.bases import Column, harmonic_basis, laplacian_eigenbasis
from torchfmap.descriptors import landmark_descriptors
from torchfmap.eval import shape_difference, shape_distance
from torchfmap.fmap.core import laplacian_mask
from torchfmap.operators import laplacian, mass_matrix
from torchfmap.seeds import curvature, curvature_features


def test_renamed_keywords_pass_the_old_name_on_and_refuse_both():
    @renamed_keywords(old="new")
    def f(new=0):
        return new

    assert f(new=3) == 3
    with pytest.warns(DeprecationWarning, match=r"f\(old=\.\.\.\) is now f\(new=\.\.\.\)"):
        assert f(old=4) == 4
    with pytest.raises(TypeError, match="both old="):
        f(old=1, new=2)
    assert f.__name__ == "f" and "new" in f.__wrapped__.__code__.co_varnames


def test_warnings_point_at_the_callers_line():
    @renamed_keywords(old="new")
    def f(new=0):
        return new

    with pytest.warns(DeprecationWarning) as seen:
        f(old=1)
    assert seen[0].filename == __file__
    with pytest.warns(DeprecationWarning) as seen:
        warn_renamed("a", "b", stacklevel=2)
    assert seen[0].filename == __file__


def test_module_aliases_serve_old_names_and_refuse_unknown_ones():
    get = module_aliases("torchfmap.operators", {"old_laplacian": "laplacian", "far": "torchfmap.mesh.Mesh"})
    with pytest.warns(DeprecationWarning, match="torchfmap.operators.old_laplacian is now"):
        assert get("old_laplacian") is laplacian
    with pytest.warns(DeprecationWarning, match="torchfmap.mesh.Mesh"):
        assert get("far") is tf.Mesh
    with pytest.raises(AttributeError, match="no attribute 'missing'"):
        get("missing")


def test_old_keyword_names_give_the_new_results(blob):
    """'kind' named six things; each now has its own word, and the old keyword still works."""
    with pytest.warns(DeprecationWarning, match="scheme"):
        L_old, B_old = laplacian(blob, kind="robust")
    L_new, B_new = laplacian(blob, scheme="robust")
    assert abs(L_old - L_new).max() == 0 and abs(B_old - B_new).max() == 0
    with pytest.warns(DeprecationWarning, match="scheme"):
        assert abs(mass_matrix(blob, kind="fem") - mass_matrix(blob, scheme="fem")).max() == 0
    with pytest.warns(DeprecationWarning, match="scheme"):
        old = harmonic_basis(blob, [0, 5, 9], kind="mean_value").values
    np.testing.assert_array_equal(old, harmonic_basis(blob, [0, 5, 9], scheme="mean_value").values)
    with pytest.warns(DeprecationWarning, match="laplacian="):
        old = tf.prepare_shape(blob, 0, laplacian_kind="robust").operators.stiffness
    assert abs(old - tf.prepare_shape(blob, 0, laplacian="robust").operators.stiffness).max() == 0
    with pytest.warns(DeprecationWarning, match="measure"):
        np.testing.assert_array_equal(curvature(blob, kind="gaussian"), curvature(blob, measure="gaussian"))
    with pytest.warns(DeprecationWarning, match="measure"):
        old = curvature_features(blob, 4, kind="mean")
    np.testing.assert_array_equal(old, curvature_features(blob, 4, measure="mean"))
    ops = laplacian(blob)
    with pytest.warns(DeprecationWarning, match="kernel"):
        old = landmark_descriptors([0, 7], kind="heat", operators=ops)
    np.testing.assert_array_equal(old, landmark_descriptors([0, 7], kernel="heat", operators=ops))


def test_old_names_of_the_solve_and_comparison_choices(rng):
    torch = pytest.importorskip("torch")
    lam = torch.linspace(0, 4, 6, dtype=torch.float64)
    with pytest.warns(DeprecationWarning, match="mask"):
        old = laplacian_mask(lam, lam + 0.5, kind="resolvent")
    torch.testing.assert_close(old, laplacian_mask(lam, lam + 0.5, mask="resolvent"), rtol=0, atol=0)
    C = rng.standard_normal((5, 5))
    W = np.diag(np.arange(5.0))
    with pytest.warns(DeprecationWarning, match="form"):
        old = shape_difference(C, W, W, kind="conformal")
    np.testing.assert_array_equal(old, shape_difference(C, W, W, form="conformal"))
    with pytest.warns(DeprecationWarning, match="form"):
        assert shape_distance(C, kind="area") == shape_distance(C, form="area")


def test_old_attribute_and_method_names_of_columns_and_bases(blob):
    col = Column("harmonic", 3)
    with pytest.warns(DeprecationWarning, match="Column.family"):
        assert col.kind == col.family == "harmonic"
    with pytest.warns(DeprecationWarning, match=r"Column\(family=") as seen:
        assert Column(kind="laplacian", index=2) == Column("laplacian", index=2)
    assert seen[0].filename == __file__
    with pytest.raises(TypeError, match="both kind="):
        Column(family="laplacian", kind="laplacian")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert dataclasses.replace(col, seed=4) == Column("harmonic", 4)
    basis = laplacian_eigenbasis(blob, 6)
    with pytest.warns(DeprecationWarning, match="families"):
        np.testing.assert_array_equal(basis.kinds(), basis.families())
    assert list(basis.families()) == ["laplacian"] * 6


def test_old_keywords_of_the_learned_basis_and_of_collections():
    torch = pytest.importorskip("torch")
    from torchfmap.data import icosphere
    from torchfmap.nn import BasisModule

    mesh = icosphere(2)
    with pytest.warns(DeprecationWarning, match="basis="):
        old = BasisModule.from_mesh(mesh, 6, kind="laplacian", dtype=torch.float64)
    torch.testing.assert_close(old.lam, BasisModule.from_mesh(mesh, 6, basis="laplacian").lam)


def test_moved_and_renamed_module_names():
    cases = [
        ("torchfmap.operators.laplacian", "LaplacianKind", "LaplacianScheme"),
        ("torchfmap.operators.laplacian", "MassKind", "MassScheme"),
        ("torchfmap.operators.laplacian", "LAPLACIAN_KINDS", "LAPLACIAN_SCHEMES"),
        ("torchfmap.operators.laplacian", "MASS_KINDS", "MASS_SCHEMES"),
        ("torchfmap.fmap.core", "MaskKind", "Mask"),
        ("torchfmap.seeds", "CurvatureKind", "CurvatureMeasure"),
        ("torchfmap.results", "RefineKind", "RefineMethod"),
    ]
    for module, old, new in cases:
        mod = importlib.import_module(module)
        with pytest.warns(DeprecationWarning, match=new) as seen:
            assert getattr(mod, old) is getattr(mod, new)
        assert seen[0].filename == __file__
    with pytest.warns(DeprecationWarning, match="torchfmap.operators.normalize_area"):
        assert tf.normalize_area is importlib.import_module("torchfmap.operators").normalize_area


def test_moved_learned_path_names():
    pytest.importorskip("torch")
    import torchfmap.nn.data as data
    import torchfmap.nn.geometry as geometry
    from torchfmap.nn import inputs
    from torchfmap.operators import gradient

    with pytest.warns(DeprecationWarning, match="torchfmap.operators.gradient.gradient_operator"):
        assert geometry.gradient_operator is gradient.gradient_operator
    with pytest.warns(DeprecationWarning, match="torchfmap.nn.inputs.K_WKS"):
        assert data.K_WKS == inputs.K_WKS
    with pytest.warns(DeprecationWarning, match="solve_fmap"):
        import torchfmap.nn.functional as F

        assert F.fmap_solve is F.solve_fmap


def test_precompute_shape_is_shape_arrays(blob):
    pytest.importorskip("torch")
    from torchfmap.nn import precompute_shape, shape_arrays

    with pytest.warns(DeprecationWarning, match="shape_arrays"):
        old = precompute_shape(blob, 6, 8, 20, k_net=8)
    new = shape_arrays(blob, 6, 8, 20, k_net=8)
    assert old.keys() == new.keys()
    for key in new:
        np.testing.assert_array_equal(old[key], new[key], err_msg=key)
    with pytest.warns(DeprecationWarning), pytest.raises(tf.errors.ParameterError, match="of this mesh"):
        precompute_shape(blob, 6, shape=tf.prepare_shape(blob.scaled(2.0), 20))


def test_a_kind_given_its_column_families_under_the_old_name():
    from torchfmap.kinds import get_kind

    base = get_kind("harmonic")
    with pytest.warns(DeprecationWarning, match="column_families") as seen:
        old = type(base)(**{**_fields(base), "column_families": frozenset(), "column_kinds": {"harmonic"}})
    assert seen[0].filename == __file__
    with pytest.warns(DeprecationWarning, match="column_families"):
        assert base.column_kinds == base.column_families == old.column_families == frozenset({"harmonic"})
    with warnings.catch_warnings():  # replace passes the old keyword on: silently, as not given
        warnings.simplefilter("error")
        assert dataclasses.replace(base, name="h2").column_families == base.column_families
        assert dataclasses.replace(base, column_families=frozenset({"x"})).column_families == {"x"}
    with pytest.raises(tf.errors.ParameterError, match="no column families"):
        type(base)(**{**_fields(base), "column_families": frozenset()})


def _fields(kind) -> dict:
    from dataclasses import fields

    return {f.name: getattr(kind, f.name) for f in fields(kind)}
