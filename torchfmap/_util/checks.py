"""Input checks shared by several modules, the one home of each (imports only :mod:`.errors`): vertex
indices, landmark pairs, point maps, seeds per component, symmetry of a stiffness, lumped masses,
tolerances, times, counts and memory. Every error names the problem and the fix (``... Fix: ...``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from ..errors import ParameterError, SeedError

if TYPE_CHECKING:  # the mesh module sits above this one
    from ..mesh import Mesh

#: Safety factor of :func:`symmetry_tolerance` over the worst-case summation error.
SYMMETRY_SAFETY = 8.0


def check_vertex_indices(indices, n_vertices: int, what: str = "sources") -> np.ndarray:
    """A 1-D, non-empty array of distinct vertex indices in range, as int64 (integral floats accepted);
    else :class:`SeedError`."""
    idx = np.atleast_1d(np.asarray(indices))
    if idx.size == 0:
        raise SeedError(f"{what} is empty. Fix: give at least one vertex index.")
    if idx.ndim != 1:
        raise SeedError(
            f"{what} must be a 1-D list of vertex indices, got shape {idx.shape}. Fix: pass a flat "
            "list or array (e.g. `np.ravel(...)`)."
        )
    if not np.issubdtype(idx.dtype, np.integer):
        if np.issubdtype(idx.dtype, np.floating) and np.all(np.mod(idx, 1) == 0):
            idx = idx.astype(np.int64)
        else:
            raise SeedError(
                f"{what} must be integer vertex indices, got dtype {idx.dtype}. Fix: pass 0-based "
                "integer indices (e.g. `np.asarray(idx, dtype=int)`)."
            )
    bad = idx[(idx < 0) | (idx >= n_vertices)]
    if bad.size:
        raise SeedError(
            f"{what} {bad[:8].tolist()} are out of range for a mesh of {n_vertices} vertices. "
            "Fix: indices are 0-based and must be < V (1-based files need `- 1`)."
        )
    uniq, counts = np.unique(idx, return_counts=True)
    if (counts > 1).any():
        raise SeedError(
            f"{what} contain duplicates {uniq[counts > 1][:8].tolist()}. Fix: remove repeated "
            "vertices (e.g. `np.unique(seeds)` if order does not matter)."
        )
    return idx.astype(np.int64)


def check_landmark_pairs(landmarks, n_x: int, n_y: int) -> np.ndarray:
    """``(L, 2)`` int pairs ``(vertex on x, vertex on y)``, validated (shape, range, no duplicates
    on either side); raises :class:`ParameterError` / :class:`SeedError`."""
    pairs = np.asarray(landmarks)
    if pairs.ndim != 2 or pairs.shape[1] != 2 or len(pairs) == 0:
        raise ParameterError(f"landmarks must be (L, 2) pairs (x vertex, y vertex), got shape {pairs.shape}.")
    if np.issubdtype(pairs.dtype, np.integer) and n_x != n_y and pairs.min() >= 0:
        fits = pairs[:, 0].max() < n_x and pairs[:, 1].max() < n_y
        fits_swapped = pairs[:, 1].max() < n_x and pairs[:, 0].max() < n_y
    else:
        fits = fits_swapped = True
    if not fits and fits_swapped:
        raise SeedError(
            f"landmark pairs index outside the meshes (x has {n_x} vertices, y {n_y}), but they would "
            "fit with the two columns swapped. Fix: each pair is (source vertex, target vertex); "
            "swap the columns (landmarks[:, ::-1])."
        )
    check_vertex_indices(pairs[:, 0], n_x, "source landmarks")
    check_vertex_indices(pairs[:, 1], n_y, "target landmarks")
    return pairs.astype(np.int64)


def check_p2p(p2p, n_target: int | None, n_source: int, name: str = "p2p") -> np.ndarray:
    """A ``(n_target,)`` (any length when None) int64 point map into ``[0, n_source)``, or
    :class:`ParameterError`."""
    p2p = np.asarray(p2p)
    if p2p.ndim != 1 or p2p.shape != (n_target or len(p2p),):
        want = "" if n_target is None else f" ({n_target})"
        raise ParameterError(
            f"{name} must have one entry per vertex{want}, got shape {p2p.shape}. Fix: a 1-D array of "
            "integers, the source vertex of each target vertex."
        )
    if not np.issubdtype(p2p.dtype, np.integer):
        raise ParameterError(f"{name} must hold integer vertex indices, got {p2p.dtype}.")
    if p2p.size and (p2p.min() < 0 or p2p.max() >= n_source):
        raise ParameterError(
            f"{name} has indices outside [0, {n_source}) (min {int(p2p.min())}, max {int(p2p.max())}). "
            "Fix: maps are 0-based, target -> source; a map in the other direction must be inverted first."
        )
    return p2p.astype(np.int64)


def check_seeds_cover_components(mesh: Mesh, seeds: np.ndarray) -> None:
    """Raise :class:`SeedError` if a connected component (with faces) of ``mesh`` has no seed."""
    labels = mesh.component_labels
    used = np.unique(labels[np.unique(mesh.faces)])
    missing = np.setdiff1d(used, labels[seeds])
    if len(missing):
        example = int(np.flatnonzero(labels == missing[0])[0])
        raise SeedError(
            f"{len(missing)} connected component(s) have no seed (e.g. the one holding vertex "
            f"{example}); harmonic and Dirichlet problems are undefined there. Fix: add a seed on "
            "every component, or keep one with `mesh.largest_component()`."
        )


def symmetry_tolerance(A) -> float:
    """Largest ``|A - Aᵀ|_max`` that counts as round-off: ``8 · m · eps · |A|_max``, ``m`` the most
    stored entries of a row (``V`` for a dense matrix): a bound on summing ``m`` terms in two orders."""
    if sp.issparse(A):
        A = sp.csr_matrix(A)
        m = int(np.diff(A.indptr).max()) if A.shape[0] else 1
        scale = float(abs(A).max()) if A.nnz else 0.0
    else:
        A = np.asarray(A)
        m = A.shape[-1] if A.ndim == 2 else 1
        scale = float(np.abs(A).max()) if A.size else 0.0
    return SYMMETRY_SAFETY * max(m, 1) * np.finfo(np.float64).eps * scale


def symmetry_defect(A) -> float:
    """``|A - Aᵀ|_max`` (infinite for a non-square matrix)."""
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        return float("inf")
    if sp.issparse(A):
        A = sp.csr_matrix(A)
        return float(abs(A - A.T).max()) if A.nnz else 0.0
    A = np.asarray(A)
    return float(np.abs(A - A.T).max()) if A.size else 0.0


def is_symmetric(A) -> bool:
    """Whether the square (sparse or dense) matrix ``A`` is symmetric up to round-off
    (:func:`symmetry_tolerance`)."""
    return bool(symmetry_defect(A) <= symmetry_tolerance(A))


def check_symmetric(
    L, what: str, fix: str = "build L with laplacian(mesh, scheme='cotan') or scheme='robust'"
) -> None:
    """Raise :class:`ParameterError` unless ``L`` is symmetric (:func:`is_symmetric`); ``what`` needs it
    (``'heat kernels'``), ``fix`` says what to do instead."""
    defect, tol = symmetry_defect(L), symmetry_tolerance(L)
    if not defect <= tol:
        raise ParameterError(
            f"{what} need a symmetric Laplacian, but |L - Lᵀ|_max = {defect:.2e} exceeds the "
            f"round-off tolerance {tol:.1e} (mean-value weights are not self-adjoint). Fix: {fix}."
        )


def lumped_diagonal(B) -> np.ndarray | None:
    """The diagonal ``(V,)`` of a mass matrix ``B`` if it is diagonal (stored zeros ignored), else None;
    a ``(V,)`` array is taken as the diagonal itself."""
    if not sp.issparse(B):
        B = np.asarray(B)
        if B.ndim == 1:
            return B
        d = np.diagonal(B).copy()
        return d if not (B - np.diag(d)).any() else None
    B = sp.csr_matrix(B)
    rows = np.repeat(np.arange(B.shape[0]), np.diff(B.indptr))
    if np.any(B.data[rows != B.indices]):
        return None
    return B.diagonal()


def check_lumped_mass(
    B, what: str = "torch layers", fix: str = "build the mass with mass='voronoi' or 'barycentric'"
) -> np.ndarray:
    """The diagonal ``(V,)`` of a lumped mass ``B``; :class:`ParameterError` if ``B`` is not diagonal."""
    d = lumped_diagonal(B)
    if d is None:
        raise ParameterError(
            f"{what} need a lumped (diagonal) mass, but this mass matrix has off-diagonal entries "
            f"(e.g. mass='fem'). Fix: {fix}."
        )
    return d


#: Smallest relative tolerance an iterative method is asked for.
TOL_MIN = 1e-14
#: Tolerances must be below this.
TOL_MAX = 1.0


def check_tolerance(tol, what: str = "tol") -> float:
    """A relative accuracy target as a float in ``[TOL_MIN, TOL_MAX)``, else :class:`ParameterError`."""
    try:
        value = float(tol)
    except (TypeError, ValueError) as err:
        raise ParameterError(f"{what} must be a number, got {tol!r}. Fix: e.g. {what}=1e-6.") from err
    if not np.isfinite(value) or not TOL_MIN <= value < TOL_MAX:
        raise ParameterError(
            f"{what} must be a relative accuracy in [{TOL_MIN:g}, {TOL_MAX:g}), got {tol!r}. "
            f"Fix: e.g. {what}=1e-6 (smaller is more accurate and slower)."
        )
    return value


def check_times(times, what: str = "diffusion times", fix: str = "t > 0") -> np.ndarray:
    """``times`` as a non-empty float64 array, every one finite and > 0; else :class:`ParameterError`."""
    out = np.atleast_1d(np.asarray(times, dtype=np.float64))
    if out.size == 0 or not np.all(np.isfinite(out)) or np.any(out <= 0):
        raise ParameterError(f"{what} must be finite and > 0, got {out.tolist()}. Fix: {fix}.")
    return out


def check_count(value, low: int, high: int, what: str) -> int:
    """An integer in ``[low, high]`` as ``int``; bools, floats (``20.0``) and out-of-range values raise
    :class:`ParameterError`."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not low <= value <= high:
        raise ParameterError(f"{what} must be an integer in [{low}, {high}], got {value!r}.")
    return int(value)


#: Bytes per vertex of a prepared shape besides its eigenvectors.
BYTES_PER_VERTEX = 2048
#: float64 ``(V,)`` vectors held per eigenpair.
EIGEN_VECTORS = 4


def available_memory() -> int | None:
    """Bytes of memory available (``MemAvailable`` of ``/proc/meminfo``); None where unreadable."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def check_memory(n_vertices: int, n_eigen: int, what: str) -> None:
    """Raise :class:`ParameterError` if ``n_vertices`` with ``n_eigen`` eigenpairs need more memory
    (:data:`BYTES_PER_VERTEX`, :data:`EIGEN_VECTORS`) than is available now."""
    needed = n_vertices * (BYTES_PER_VERTEX + 8 * EIGEN_VECTORS * n_eigen)
    available = available_memory()
    if available is not None and needed > available:
        raise ParameterError(
            f"{what}: {n_vertices} vertices and {n_eigen} eigenpairs need about {needed / 2**30:.1f} GiB, "
            f"and {available / 2**30:.1f} GiB of memory is available. Fix: decimate or remesh the mesh "
            "(torchfmap.remesh, or MeshLab's quadric edge collapse), ask for fewer eigenpairs (k), or "
            "free memory."
        )
