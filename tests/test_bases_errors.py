"""Bad inputs to the bases: each raises a clear error naming the problem and the fix."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import (
    Basis,
    ParameterError,
    SeedError,
    basis_stack,
    diffusion_basis,
    harmonic_basis,
)


@pytest.mark.parametrize("build", [harmonic_basis, diffusion_basis, basis_stack])
def test_duplicate_out_of_range_and_empty_seeds(blob, build):
    with pytest.raises(SeedError, match=r"duplicates \[5\].*np.unique"):
        build(blob, [1, 5, 5])
    with pytest.raises(SeedError, match=r"\[642\] are out of range .*0-based"):
        build(blob, [0, 642])
    with pytest.raises(SeedError, match="empty"):
        build(blob, [])
    with pytest.raises(SeedError, match="integer"):
        build(blob, [0.5, 2.0])


def test_bad_times_and_k(blob):
    with pytest.raises(ParameterError, match="> 0"):
        basis_stack(blob, [0, 10], times=[-1e-3])
    with pytest.raises(ParameterError, match="k must be in"):
        basis_stack(blob, [0, 10], times=[], n_eigen=10**4)
    with pytest.raises(ParameterError, match="empty stack"):
        basis_stack(blob, [0, 10], times=[], harmonic=False)


def test_basis_shape_errors(blob):
    with pytest.raises(ParameterError, match="mass is"):
        Basis(np.ones((10, 2)), np.ones(11))
    with pytest.raises(ParameterError, match=r"\(V, K\)"):
        Basis(np.ones(10), np.ones(10))
    basis = harmonic_basis(blob, [0, 10])
    with pytest.raises(ParameterError, match="rows"):
        basis.project(np.ones(5))
