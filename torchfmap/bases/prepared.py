"""Per-shape precomputation and caches (operators, eigenpairs, distances, seed heat kernels), in the
shape's unit-area frame (coordinates times ``scale = 1 / sqrt(area)``)."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from .._util.checks import check_count, check_memory, check_seeds_cover_components, check_vertex_indices
from ..errors import ParameterError
from ..mesh import Mesh
from ..operators.geodesic import DistanceRows
from ..operators.gradient import gradient_operator
from ..operators.heat import heat_kernels
from ..operators.laplacian import Operators
from ..operators.laplacian import laplacian as laplacian_operators
from .basis import Basis, Column
from .laplacian import laplacian_eigenbasis

#: Relative accuracy of the heat kernels of seed bases (far below the seeds' placement error).
SEED_HEAT_TOL = 1e-4


@dataclass
class PreparedShape:
    """One shape's precomputation: ``operators`` ``(L, B)``; ``eigenbasis`` (B-orthonormal, None
    when ``n_eigen = 0``); ``distances`` (units of ``sqrt(area)``); ``kernels`` ``(seed, relative
    time) -> (V,)``; ``scale`` (frame / mesh coordinates; 1 for given operators); ``derived``
    (:meth:`derive`). ``dataclasses.replace`` shares the caches: replace only the eigenbasis."""

    mesh: Mesh
    operators: Operators
    eigenbasis: Basis | None
    distances: DistanceRows
    kernels: dict[tuple[int, float], np.ndarray] = field(default_factory=dict)
    scale: float = 1.0
    derived: dict = field(default_factory=dict, compare=False, repr=False)

    def derive(self, key, compute):
        """``compute()`` on first use of ``key`` (hashable), the same stored object after."""
        if key not in self.derived:
            self.derived[key] = compute()
        return self.derived[key]

    @property
    def frame(self) -> Mesh:
        """The mesh in the frame of the operators (``mesh.scaled(scale)``), built once."""
        return self.derive("frame", lambda: self.mesh if self.scale == 1.0 else self.mesh.scaled(self.scale))

    def gradient(self) -> dict[str, np.ndarray]:
        """The intrinsic gradient operator (:func:`~torchfmap.operators.gradient_operator`) in the
        operators' frame, built once."""
        return self.derive("gradient", lambda: gradient_operator(self.frame))

    @property
    def area(self) -> float:
        """Surface area in the frame of the operators (the mass's total; 1 in the unit-area frame)."""
        return float(self.operators[1].sum())

    @property
    def n_eigen(self) -> int:
        """Eigenpairs held (0 without an eigenbasis)."""
        return 0 if self.eigenbasis is None else self.eigenbasis.k


def prepare_shape(
    mesh: Mesh, n_eigen: int, *, operators: Operators | None = None, laplacian: str = "auto"
) -> PreparedShape:
    """Operators (:func:`~torchfmap.laplacian` ``scheme=laplacian``; ``'auto'``: ``'robust'`` with
    non-manifold edges, else ``'cotan'``) and ``n_eigen`` eigenpairs of ``mesh`` in its unit-area
    frame; given ``operators`` are used as they are (``scale = 1``).

    Raises:
        ParameterError: ``n_eigen`` negative or not below the vertex count, an unknown
            Laplacian scheme, or more memory than is available.
    """
    n_eigen = check_count(n_eigen, 0, max(mesh.n_vertices - 1, 0), "n_eigen")
    check_memory(mesh.n_vertices, n_eigen, f"preparing {mesh.name or 'the mesh'}")
    scale = 1.0 / np.sqrt(mesh.area) if operators is None else 1.0
    frame = mesh.scaled(scale) if operators is None else mesh
    if laplacian == "auto":
        laplacian = "robust" if mesh.n_nonmanifold_edges else "cotan"
    ops = operators if operators is not None else laplacian_operators(frame, scheme=laplacian)
    eig = laplacian_eigenbasis(frame, n_eigen, operators=ops) if n_eigen else None
    return PreparedShape(mesh, ops, eig, DistanceRows(mesh, normalized=True), scale=scale)


def with_eigenpairs(shape: PreparedShape, n_eigen: int) -> PreparedShape:
    """``shape`` with at least ``n_eigen`` eigenpairs (extended in place from its operators)."""
    if n_eigen and shape.n_eigen < n_eigen:  # the operators carry the frame
        shape.eigenbasis = laplacian_eigenbasis(shape.mesh, n_eigen, operators=shape.operators)
    return shape


def check_prepared(shapes, meshes: tuple[Mesh, Mesh]) -> tuple[PreparedShape, PreparedShape]:
    """``shapes`` checked to be prepared shapes of ``meshes``, in order (else ParameterError)."""
    try:
        sx, sy = shapes
    except (TypeError, ValueError) as err:
        raise ParameterError(
            "shapes must be a pair (prepare_shape(mesh_x, n), prepare_shape(mesh_y, n))."
        ) from err
    for shape, mesh in ((sx, meshes[0]), (sy, meshes[1])):
        if not isinstance(shape, PreparedShape) or shape.mesh is not mesh:
            raise ParameterError(
                "shapes must be (prepare_shape(mesh_x, n), prepare_shape(mesh_y, n)) of these meshes, "
                "in order."
            )
    return sx, sy


def seed_kernels(shape: PreparedShape, seeds, rel_times) -> Basis:
    """Heat kernels at ``seeds (S,)`` for each relative time (absolute ``t·|M|``), not
    orthonormalised: ``(V, T·S)`` values, time-major, provenance ``('diffusion', seed, t)``;
    missing pairs are solved and cached in ``shape.kernels``. Raises ParameterError: invalid
    seeds, seeds missing a connected component, or times not > 0."""
    mesh = shape.mesh
    seeds = check_vertex_indices(seeds, mesh.n_vertices, "seeds")
    check_seeds_cover_components(mesh, seeds)
    times = tuple(sorted(float(t) for t in rel_times))
    if not times:
        raise ParameterError("no diffusion times. Fix: give at least one relative time > 0.")
    missing = np.unique([int(s) for s in seeds for t in times if (int(s), t) not in shape.kernels])
    if len(missing):  # heat_kernels checks the times
        K = heat_kernels(
            shape.operators, missing, [t * shape.area for t in times], tol=SEED_HEAT_TOL, local=False,
            factors=shape.derive("heat factorisations", dict),
        )  # fmt: skip
        for (i, t), (j, s) in itertools.product(enumerate(times), enumerate(missing)):
            shape.kernels.setdefault((int(s), t), K[i, :, j])
    values = np.stack([shape.kernels[int(s), t] for t in times for s in seeds], axis=1)
    prov = [Column("diffusion", int(s), t) for t in times for s in seeds]
    L, B = shape.operators
    return Basis(values, B, prov, stiffness=L)
