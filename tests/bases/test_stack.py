"""Basis stacks (``torchfmap.bases.stack``): column order and orthonormality, bad times and k."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, basis_stack, farthest_point_sampling


def test_bad_times_and_k(blob):
    with pytest.raises(ParameterError, match="> 0"):
        basis_stack(blob, [0, 10], times=[-1e-3])
    with pytest.raises(ParameterError, match="k must be in"):
        basis_stack(blob, [0, 10], times=[], n_eigen=10**4)
    with pytest.raises(ParameterError, match="empty stack"):
        basis_stack(blob, [0, 10], times=[], harmonic=False)


def test_stack_order_and_orthonormality(blob):
    seeds = farthest_point_sampling(blob, 8, metric="euclidean")
    stack = basis_stack(blob, seeds, times=[1e-2, 1e-3], n_eigen=20)
    kinds = [c.family for c in stack.provenance]
    n_diff = 16
    assert kinds == ["diffusion"] * n_diff + ["harmonic"] * 8 + ["laplacian"] * 20
    assert [c.time for c in stack.provenance[:n_diff]] == [1e-3] * 8 + [1e-2] * 8
    assert np.abs(stack.gram() - np.eye(stack.k)).max() < 1e-10
    # the constant eigenfunction lies in the span of the harmonic functions (they sum to 1)
    assert any(c.family == "laplacian" and c.index == 0 for c in stack.dropped)
    W = stack.projected_laplacian()
    assert W.shape == (stack.k, stack.k) and np.allclose(W, W.T)
