"""Diffusion bases (``torchfmap.bases.diffusion``): scale, rigid-motion and permutation invariance,
column order and provenance, bad times, a real remeshed pair."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, diffusion_basis, load_mesh
from torchfmap.operators.heat import heat_kernels

from ..conftest import REL_TIMES, data_path, random_rotation


def test_scale_invariance_relative_times(heat_setting):
    mesh, ops, seeds, times, ref = heat_setting
    alpha = 3.0
    a = diffusion_basis(mesh, seeds, REL_TIMES[1:], local=False).values
    b = diffusion_basis(mesh.scaled(alpha), seeds, REL_TIMES[1:], local=False).values
    assert np.abs(alpha**2 * b - a).max() < 1e-6 * np.abs(a).max()  # delta kernels scale by 1/alpha^2


def test_rigid_motion_and_permutation_invariance(heat_setting, rng):
    mesh, ops, seeds, times, ref = heat_setting
    base = diffusion_basis(mesh, seeds, REL_TIMES[1:], local=False).values
    moved = mesh.copy(mesh.vertices @ random_rotation(rng).T + 4.0)
    assert (
        np.abs(diffusion_basis(moved, seeds, REL_TIMES[1:], local=False).values - base).max()
        < 1e-6 * base.max()
    )
    perm = rng.permutation(mesh.n_vertices)
    inv = np.argsort(perm)
    permuted = diffusion_basis(mesh.permuted(perm), inv[seeds], REL_TIMES[1:], local=False).values
    assert np.abs(permuted - base[perm]).max() < 1e-6 * base.max()


def test_column_order_and_provenance(heat_setting):
    mesh, ops, seeds, times, ref = heat_setting
    basis = diffusion_basis(mesh, seeds, [1e-2, 1e-3], local=False)  # given unsorted
    assert [c.time for c in basis.columns] == [1e-3] * 3 + [1e-2] * 3  # small to large
    assert [c.seed for c in basis.columns] == seeds.tolist() * 2


@pytest.mark.parametrize("bad", [0.0, -1e-3, np.nan])
def test_bad_times(heat_setting, bad):
    mesh, ops, seeds, times, ref = heat_setting
    with pytest.raises(ParameterError, match="times must be finite and > 0"):
        diffusion_basis(mesh, seeds, [1e-3, bad])
    with pytest.raises(ParameterError, match="> 0"):
        heat_kernels(ops, seeds, [bad])


def test_remeshed_pose_pair_agrees_through_ground_truth():
    """cat0 and cat1 have different connectivity: kernels at corresponding points agree."""
    folder = data_path("tosca5k_dev")
    m0, m1 = load_mesh(folder / "cat0.off"), load_mesh(folder / "cat1.off")
    v0 = np.loadtxt(folder / "corres" / "cat0.vts", dtype=int) - 1
    v1 = np.loadtxt(folder / "corres" / "cat1.vts", dtype=int) - 1
    rows = np.array([100, 2000, 4000])
    k0 = diffusion_basis(m0, v0[rows], [1e-2], tol=1e-6).values[v0]
    k1 = diffusion_basis(m1, v1[rows], [1e-2], tol=1e-6).values[v1]
    # delta kernels divide by the area: compare the scale-free t|M| K
    k0, k1 = k0 * m0.area, k1 * m1.area
    for j in range(len(rows)):
        corr = np.corrcoef(k0[:, j], k1[:, j])[0, 1]
        rel = np.linalg.norm(k0[:, j] - k1[:, j]) / np.linalg.norm(k0[:, j])
        assert corr > 0.95 and rel < 0.3, (corr, rel)
