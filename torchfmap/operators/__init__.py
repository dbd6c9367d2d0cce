"""Operators on meshes: Laplace-Beltrami stiffness and mass, geodesics, sparse solvers."""

from .._checks import check_vertex_indices, lumped_diagonal
from .convert import scipy_to_torch, torch_to_scipy
from .geodesic import DistanceRows, GeodesicSolver, geodesic_distances
from .laplacian import (
    Operators,
    laplacian,
    mass_matrix,
    normalize_area,
    point_cloud_laplacian,
    total_area,
)
from .solvers import Factorization, available_backends, factorize

__all__ = [
    "DistanceRows",
    "Factorization",
    "GeodesicSolver",
    "Operators",
    "available_backends",
    "check_vertex_indices",
    "factorize",
    "geodesic_distances",
    "laplacian",
    "lumped_diagonal",
    "mass_matrix",
    "normalize_area",
    "point_cloud_laplacian",
    "scipy_to_torch",
    "torch_to_scipy",
    "total_area",
]
