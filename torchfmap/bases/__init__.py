"""Bases of functions on a mesh: harmonic, diffusion, Laplacian eigenbasis, orthonormal stacks."""

from ..errors import CorruptFileError
from .basis import Basis, Column, support_fraction
from .diffusion import DEFAULT_TIMES, cf_poles, diffusion_basis, heat_apply, heat_kernels
from .harmonic import harmonic_basis, harmonic_functions
from .laplacian import eigenpairs, fix_signs, laplacian_eigenbasis
from .orthonormalize import cholqr, mgs, orthonormalize, orthonormalize_pair
from .stack import basis_stack, concatenate

__all__ = [
    "DEFAULT_TIMES",
    "Basis",
    "Column",
    "CorruptFileError",
    "basis_stack",
    "cf_poles",
    "cholqr",
    "concatenate",
    "diffusion_basis",
    "eigenpairs",
    "fix_signs",
    "harmonic_basis",
    "harmonic_functions",
    "heat_apply",
    "heat_kernels",
    "laplacian_eigenbasis",
    "mgs",
    "orthonormalize",
    "orthonormalize_pair",
    "support_fraction",
]
