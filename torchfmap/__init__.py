"""torchfmap: functional maps with feature-aware bases. Data flow: mesh -> operators -> seeds -> bases ->
descriptors -> functional map -> point map -> evaluation, in numpy (float64); ``torchfmap.nn``: torch."""

from .bases import (
    Basis,
    Column,
    basis_stack,
    diffusion_basis,
    harmonic_basis,
    laplacian_eigenbasis,
    orthonormalize,
    orthonormalize_pair,
    support_fraction,
)
from .bases.prepared import PreparedShape, prepare_shape
from .errors import (
    ConvergenceError,
    CorruptFileError,
    CostWarning,
    EvaluationInterrupted,
    FileReadError,
    FileWriteError,
    MapWarning,
    MemoryEstimateError,
    MeshError,
    MeshWarning,
    ParameterError,
    SeedError,
    TorchFmapError,
    WorkerLost,
)
from .evaluate.scores import evaluate_map
from .fmap import fmap_to_p2p, p2p_to_fmap, solve_fmap
from .io import load_mesh, load_points, save_mesh
from .kinds import KINDS
from .matching.pipeline import match
from .matching.quality import geodesic_distortion, orientation_agreement
from .matching.results import MatchResult
from .mesh import Mesh, MeshReport, validate_mesh, weld_vertices
from .operators import (
    Factorization,
    GeodesicSolver,
    Operators,
    available_backends,
    eigenpairs,
    factorize,
    geodesic_distances,
    heat_kernels,
    laplacian,
    mass_matrix,
    point_cloud_laplacian,
    total_area,
)
from .seeds import (
    coverage_seeds,
    curvature,
    curvature_features,
    farthest_point_sampling,
    gaussian_curvature,
    mean_curvature,
)

__version__ = "0.1.0"

__all__ = [
    "KINDS", "Basis", "Column", "basis_stack", "coverage_seeds", "curvature", "curvature_features",
    "diffusion_basis", "farthest_point_sampling", "gaussian_curvature", "harmonic_basis", "heat_kernels",
    "laplacian_eigenbasis", "mean_curvature", "orthonormalize", "orthonormalize_pair", "support_fraction",
    "Factorization", "GeodesicSolver", "Mesh", "MeshError", "MeshReport", "MeshWarning", "CostWarning",
    "EvaluationInterrupted", "WorkerLost", "MapWarning", "MemoryEstimateError", "FileReadError",
    "FileWriteError", "CorruptFileError", "Operators", "ParameterError", "ConvergenceError", "SeedError",
    "TorchFmapError", "__version__", "available_backends", "factorize", "geodesic_distances", "laplacian",
    "load_mesh", "load_points", "mass_matrix", "eigenpairs", "point_cloud_laplacian", "prepare_shape",
    "PreparedShape", "geodesic_distortion", "orientation_agreement", "save_mesh", "total_area",
    "validate_mesh", "weld_vertices", "evaluate_map", "fmap_to_p2p", "p2p_to_fmap", "solve_fmap",
    "MatchResult", "match",
]  # fmt: skip
