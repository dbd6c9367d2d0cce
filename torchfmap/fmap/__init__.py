"""Functional maps: the regularised solver (any basis), conversions and refinement."""

from .convert import check_p2p, fmap_to_p2p, fmap_to_p2p_bijective, p2p_to_fmap, values_to_p2p
from .core import laplacian_mask, rotate_and_solve, solve_rowwise, spectral_frame
from .nearest import (
    Neighbors,
    SurfaceSampling,
    local_nearest,
    nearest_neighbor,
    nearest_neighbor_distance,
    spread_samples,
    surface_sampling,
)
from .refine import (
    EnergyGuard,
    Refined,
    Samples,
    icp_refine,
    zoomout,
    zoomout_energy,
    zoomout_iterations,
    zoomout_sequence,
)
from .solver import (
    FmapProblem,
    build_problem,
    check_landmark_pairs,
    multiplication_operator,
    orientation_operators,
    solve_fmap,
)

__all__ = [
    "EnergyGuard", "FmapProblem", "build_problem", "check_landmark_pairs", "check_p2p", "fmap_to_p2p",
    "fmap_to_p2p_bijective", "icp_refine", "laplacian_mask", "local_nearest", "multiplication_operator",
    "Neighbors", "nearest_neighbor", "nearest_neighbor_distance", "orientation_operators", "p2p_to_fmap",
    "Refined", "Samples", "rotate_and_solve", "solve_fmap", "solve_rowwise", "spectral_frame",
    "spread_samples", "SurfaceSampling", "surface_sampling", "values_to_p2p", "zoomout", "zoomout_energy",
    "zoomout_iterations", "zoomout_sequence",
]  # fmt: skip
