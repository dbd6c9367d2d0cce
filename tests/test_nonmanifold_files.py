"""Benchmark files with a non-manifold edge or duplicated faces are read as they are, with a
warning, and get operators that are right on them (the intrinsic tufted Laplacian)."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import MeshError, MeshWarning, load_mesh, save_mesh
from torchfmap.bases.prepared import prepare_shape
from torchfmap.cli import main
from torchfmap.mesh import Mesh
from torchfmap.operators import laplacian

from .conftest import bumpy_blob, smallest_eigenvalues


def with_fin(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """``mesh`` plus one extra triangle (a fin) on an existing edge: that edge then has three faces."""
    a, b = mesh.faces[0, 0], mesh.faces[0, 1]
    tip = mesh.vertices[[a, b]].mean(axis=0) + 0.05 * mesh.vertex_normals[a]
    v = np.vstack([mesh.vertices, tip])
    f = np.vstack([mesh.faces, [[a, b, len(mesh.vertices)]]])
    return v, f


def test_nonmanifold_file_loads_with_a_warning_and_robust_operators(tmp_path):
    base = bumpy_blob(2)
    v, f = with_fin(base)
    path = tmp_path / "fin.off"
    with pytest.warns(MeshWarning, match="non-manifold"):
        mesh = Mesh(v, f, allow_nonmanifold="warn")
    save_mesh(mesh, path)
    with pytest.warns(MeshWarning, match="1 non-manifold edges"):
        loaded = load_mesh(path)
    assert loaded.n_nonmanifold_edges == 1 and loaded.report.n_nonmanifold_edges == 1
    with pytest.raises(MeshError, match="non-manifold"):
        load_mesh(path, allow_nonmanifold=False)
    shape = prepare_shape(loaded, 6)
    L_robust, _ = laplacian(loaded.scaled(shape.scale), kind="robust")
    assert abs(shape.operators[0] - L_robust).max() == 0
    # the tufted Laplacian stays positive semidefinite with one zero eigenvalue per component
    lam = smallest_eigenvalues(*shape.operators, 3)
    assert abs(lam[0]) < 1e-8 and lam[1] > 1e-6
    # a manifold mesh keeps the cotangent Laplacian
    assert prepare_shape(base, 0).operators[0].nnz == laplacian(base.scaled(1 / np.sqrt(base.area)))[0].nnz


def test_cli_matches_nonmanifold_files(tmp_path, capsys):
    base = bumpy_blob(2)
    v, f = with_fin(base)
    with pytest.warns(MeshWarning):
        save_mesh(Mesh(v, f, allow_nonmanifold="warn"), tmp_path / "a.off")
    save_mesh(base, tmp_path / "b.off")
    out = tmp_path / "m.txt"
    capsys.readouterr()
    args = ["match", str(tmp_path / "a.off"), str(tmp_path / "b.off"), "--k", "10", "--out", str(out)]
    assert main(args) == 0
    assert len(np.loadtxt(out)) == base.n_vertices
    # the command line prints a warning as one line, without Python's source line
    err = capsys.readouterr().err
    assert "torchfmap: warning: a: 1 non-manifold edges" in err and ".py:" not in err
