"""Operators on meshes: Laplace-Beltrami stiffness and mass, geodesics, sparse solvers, the
heat-kernel action and the generalised eigensolvers."""

from .._util.checks import check_vertex_indices, lumped_diagonal
from .convert import scipy_to_torch, torch_to_scipy
from .eigen import eigenpairs
from .geodesic import DistanceRows, GeodesicSolver, geodesic_distances
from .gradient import gradient_operator, tangent_frames
from .heat import heat_apply, heat_kernels
from .laplacian import Operators, laplacian, mass_matrix, normalize_area, point_cloud_laplacian, total_area
from .solvers import Factorization, available_backends, factorize

__all__ = [
    "DistanceRows", "Factorization", "GeodesicSolver", "Operators", "available_backends",
    "check_vertex_indices", "eigenpairs", "factorize", "geodesic_distances", "gradient_operator",
    "heat_apply", "heat_kernels", "laplacian", "lumped_diagonal", "mass_matrix", "normalize_area",
    "point_cloud_laplacian", "scipy_to_torch", "torch_to_scipy", "tangent_frames", "total_area",
]  # fmt: skip
