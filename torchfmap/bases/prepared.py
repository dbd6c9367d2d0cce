"""Per-shape precomputation shared by every pair a shape takes part in, and its caches.

A :class:`PreparedShape` holds what a shape needs once, whatever it is matched to and whichever
path matches it (classical or learned): its operators, its first eigenpairs (grown in place when
ZoomOut needs more), its geodesic distance rows (solved on first use), the heat kernels of seed
bases (solved on first use, per ``(seed, relative time)``), its intrinsic gradient operator and
what layers above derive from it once (the learned path's network inputs,
:func:`torchfmap.nn.inputs.network_inputs`). Its lifetime is the caller's: nothing is kept
between calls unless the caller keeps the object.

Everything is computed in the shape's **unit-area frame** (its coordinates times
``scale = 1 / sqrt(area)``), so two shapes of different sizes get comparable eigenvalues,
descriptors and basis values, and a match does not depend on the units of either mesh. Vertex
indices are the caller's; distances are in units of ``sqrt(area)``.
"""

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

#: Relative accuracy of the heat kernels of seed bases: far below the seeds' placement error
#: (a few percent of sqrt(area)), so a tighter tolerance changes no map, only the time.
SEED_HEAT_TOL = 1e-4


@dataclass
class PreparedShape:
    """One shape's precomputation.

    ``mesh``; ``operators`` ``(L, B)`` (``(V, V)`` sparse stiffness and lumped mass);
    ``eigenbasis``: the first ``n_eigen`` Laplacian eigenfunctions as a B-orthonormal
    :class:`~torchfmap.Basis` (``(V, n_eigen)`` values, eigenvalues ascending; None when
    ``n_eigen = 0``); ``distances``: geodesic distance rows in units of ``sqrt(area)``,
    computed on first use; ``kernels``: heat kernels of seed bases,
    ``(seed, relative time) -> (V,)``, computed on first use (a seed that refinement leaves in
    place is not solved again); ``scale``: the frame's coordinates are ``scale`` times the
    mesh's (``1 / sqrt(area)``: the unit-area frame; 1 for operators given by the caller), in
    which ``operators``, ``eigenbasis``, ``kernels`` and :meth:`gradient` live; ``derived``:
    per-shape quantities computed once by the layers above (:meth:`derive`), e.g. network inputs.

    ``dataclasses.replace`` shares the caches (``distances``, ``kernels``, ``derived``) with the
    copy: replace the eigenbasis that way (nothing cached depends on it), never the mesh, the
    operators or the scale (prepare the new shape instead).
    """

    mesh: Mesh
    operators: Operators
    eigenbasis: Basis | None
    distances: DistanceRows
    kernels: dict[tuple[int, float], np.ndarray] = field(default_factory=dict)
    scale: float = 1.0
    derived: dict = field(default_factory=dict, compare=False, repr=False)

    def derive(self, key, compute):
        """``compute()`` on first use of ``key`` (hashable), the stored value after (the same
        object: callers that hand it on copy it, as :func:`~torchfmap.nn.inputs.shape_arrays`)."""
        if key not in self.derived:
            self.derived[key] = compute()
        return self.derived[key]

    @property
    def frame(self) -> Mesh:
        """The mesh in the frame of the operators (``mesh.scaled(scale)``), built once."""
        return self.derive("frame", lambda: self.mesh if self.scale == 1.0 else self.mesh.scaled(self.scale))

    def gradient(self) -> dict[str, np.ndarray]:
        """The intrinsic gradient operator in the operators' frame
        (:func:`~torchfmap.operators.gradient_operator`; ``(E,)`` edge arrays), built once."""
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
    """Operators and ``n_eigen`` eigenpairs of ``mesh`` (the work :func:`~torchfmap.match` does
    per shape), in its unit-area frame: :func:`~torchfmap.laplacian` (``scheme=laplacian``;
    ``'auto'``: ``'cotan'``, or ``'robust'``, the intrinsic tufted Laplacian, for a mesh with
    non-manifold edges) of ``mesh.scaled(1 / sqrt(area))``. Given ``operators`` ``(L, B)`` are
    used as they are (the caller's frame, ``scale = 1``).

    Raises:
        ParameterError: ``n_eigen`` negative or not below the vertex count, an unknown
            Laplacian scheme, or more memory than is available (:func:`~torchfmap._util.checks.check_memory`).
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
    """``shape`` with at least ``n_eigen`` eigenpairs (extended in place when it has fewer: one
    eigendecomposition of the operators it holds, no second Laplacian). Quantities already
    derived (:attr:`PreparedShape.derived`) are kept, not recomputed."""
    if n_eigen and shape.n_eigen < n_eigen:  # the operators carry the frame
        shape.eigenbasis = laplacian_eigenbasis(shape.mesh, n_eigen, operators=shape.operators)
    return shape


def check_prepared(shapes, meshes: tuple[Mesh, Mesh]) -> tuple[PreparedShape, PreparedShape]:
    """``shapes`` checked to be prepared shapes of ``meshes``, in order.

    Raises:
        ParameterError: not a pair of :class:`PreparedShape` of these meshes.
    """
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
    """Heat kernels at ``seeds`` ``(S,)`` for each relative time (absolute ``t·|M|``), not
    orthonormalised: ``(V, T·S)`` values, time-major (small to large ``t``), provenance
    ``('diffusion', seed, t)``.

    Kernels are independent per seed: only the seeds missing a ``(seed, time)`` pair from
    ``shape.kernels`` are solved (to :data:`SEED_HEAT_TOL`), at every time of the call in one
    Krylov space (:func:`~torchfmap.operators.krylov.krylov_heat`: one factorisation and one
    set of solves for all the times, not one per time), and their missing pairs stored there;
    the factorisations are kept in ``shape.derived`` for the next seeds at those times.

    Raises:
        ParameterError: invalid seeds, seeds missing a connected component, or times not > 0.
    """
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
            shape.kernels.setdefault((int(s), t), K[i, :, j])  # pairs already held stay as they are
    values = np.stack([shape.kernels[int(s), t] for t in times for s in seeds], axis=1)
    prov = [Column("diffusion", int(s), t) for t in times for s in seeds]
    L, B = shape.operators
    return Basis(values, B, prov, stiffness=L)
