"""Bases of functions on a mesh: harmonic, diffusion, Laplacian eigenbasis, orthonormal stacks."""

from .basis import Basis, Column, support_fraction
from .diffusion import DEFAULT_TIMES, diffusion_basis
from .harmonic import harmonic_basis, harmonic_functions
from .laplacian import laplacian_eigenbasis
from .orthonormalize import cholqr, mgs, orthonormalize, orthonormalize_pair
from .prepared import PreparedShape, prepare_shape
from .stack import basis_stack, concatenate

__all__ = [
    "DEFAULT_TIMES", "Basis", "PreparedShape", "Column", "basis_stack", "cholqr", "concatenate",
    "diffusion_basis", "harmonic_basis", "harmonic_functions", "laplacian_eigenbasis", "mgs",
    "orthonormalize", "orthonormalize_pair", "prepare_shape", "support_fraction",
]  # fmt: skip
