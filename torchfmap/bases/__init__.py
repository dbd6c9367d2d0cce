"""Bases of functions on a mesh: harmonic, diffusion, Laplacian eigenbasis, orthonormal stacks."""

from ..errors import CorruptFileError
from ..operators.eigen import eigenpairs, fix_signs
from ..operators.heat import cf_poles, heat_apply, heat_kernels
from .basis import Basis, Column, support_fraction
from .diffusion import DEFAULT_TIMES, diffusion_basis
from .harmonic import harmonic_basis, harmonic_functions
from .laplacian import laplacian_eigenbasis
from .orthonormalize import cholqr, mgs, orthonormalize, orthonormalize_pair
from .prepared import PreparedShape, prepare_shape
from .stack import basis_stack, concatenate

__all__ = [
    "DEFAULT_TIMES",
    "Basis",
    "PreparedShape",
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
    "prepare_shape",
    "support_fraction",
]
