"""Checks of :func:`torchfmap.match`'s arguments that need the library's types."""

from __future__ import annotations

import os
import warnings

import numpy as np

from ..bases import Basis
from ..errors import MapWarning, ParameterError
from ..fmap.refine import check_k_final
from ..kinds import BasisKind, get_kind, kind_of
from ..mesh import Mesh
from ..mesh_checks import coincident_groups
from ..operators.laplacian import laplacian, mass_matrix


def check_meshes(mesh_x, mesh_y) -> None:
    """Refuse inputs that are not :class:`~torchfmap.Mesh` objects, naming how to make one.

    Raises:
        ParameterError: ``mesh_x`` or ``mesh_y`` is not a Mesh."""
    for mesh, name in ((mesh_x, "mesh_x"), (mesh_y, "mesh_y")):
        if isinstance(mesh, Mesh):
            continue
        if isinstance(mesh, (str, os.PathLike)):
            fix = f"load it first: torchfmap.load_mesh({str(mesh)!r})"
        elif hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
            fix = "wrap it: torchfmap.Mesh(m.vertices, m.faces) (vertex order is kept)"
        else:
            fix = "torchfmap.load_mesh(path) or torchfmap.Mesh(vertices (V, 3), faces (F, 3))"
        raise ParameterError(f"{name} is a {type(mesh).__name__}, not a torchfmap Mesh. Fix: {fix}.")


#: A mesh whose boundary is at least this long (units of ``sqrt(area)``) looks cut (a plane cut: ~1).
PARTIAL_BOUNDARY = 0.5


def boundary_length(mesh: Mesh) -> float:
    """Total length of ``mesh``'s boundary edges over ``sqrt(area)`` (0 if closed), open seams left out."""
    edges = mesh.boundary_edges
    if not len(edges):
        return 0.0
    first = coincident_groups(mesh.vertices)
    keys = np.sort(first[edges], axis=1)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    edges = edges[counts[inverse.ravel()] == 1]
    lengths = np.linalg.norm(mesh.vertices[edges[:, 0]] - mesh.vertices[edges[:, 1]], axis=1)
    return float(lengths.sum() / np.sqrt(mesh.area))


def warn_if_partial(mesh_x: Mesh, mesh_y: Mesh, *, stacklevel: int = 3) -> None:
    """Warn (:class:`~torchfmap.errors.MapWarning`) when one mesh looks like a part of the other."""
    bx, by = boundary_length(mesh_x), boundary_length(mesh_y)
    which, cut, other = ("mesh_y", by, bx) if by >= bx else ("mesh_x", bx, by)
    if cut < PARTIAL_BOUNDARY or other > 0.5 * cut:
        return
    ratio = min(mesh_x.area, mesh_y.area) / max(mesh_x.area, mesh_y.area)
    warnings.warn(
        f"{which} looks partial: its boundary is {cut:.2f} sqrt(area) long against {other:.2f} for the "
        f"other mesh (area ratio {ratio:.2f}, if both are in the same units). A full-shape map "
        "assumes both shapes whole; on a part it can be near-random. Fix: match(whole, part, "
        "partial=True) (torchfmap match WHOLE PART --partial), with a few landmarks if you have them.",
        MapWarning,
        stacklevel=stacklevel,
    )


def check_unused(kind: BasisKind, refine, k_final, times) -> None:
    """Refuse settings that would change nothing in this call (``k_final``, ``times``)."""
    if k_final is not None and refine != "zoomout":
        raise ParameterError(
            f"k_final={k_final} is the size ZoomOut grows the basis to; without refine='zoomout' it "
            "changes nothing. Fix: refine='zoomout', or drop k_final."
        )
    if times is not None and not kind.needs_landmarks:
        raise ParameterError(
            f"times are the heat times of feature-aware bases; the {kind.name} basis has none, so "
            "they would change nothing. Fix: drop times, or basis='diffusion' (or another seeded kind)."
        )


def check_zoomout_sizes(kind: BasisKind, refine, k: int, k_final) -> None:
    """Refuse a ZoomOut that would shrink in a kind whose ZoomOut grows."""
    if refine == "zoomout" and kind.grows:
        check_k_final(k, k_final)


#: A given basis fits its mesh when its vertex areas are within this L1 distance of the mesh's own.
MASS_FIT_TOL = 1e-3
#: The mass schemes a basis's areas are compared with, most common first.
AREA_SCHEMES = ("voronoi", "barycentric", "robust")


class VertexAreas:
    """A mesh's vertex areas, summing to 1, in each of :data:`AREA_SCHEMES` (computed when needed)."""

    def __init__(self, mesh: Mesh) -> None:
        self.mesh = mesh
        self._areas: list[np.ndarray] = []

    def __iter__(self):
        for i, scheme in enumerate(AREA_SCHEMES):
            if i == len(self._areas):
                if scheme == "robust":
                    m = laplacian(self.mesh, scheme="robust").mass
                else:
                    m = mass_matrix(self.mesh, scheme)
                a = np.asarray(m.sum(axis=1), dtype=np.float64).ravel()
                self._areas.append(a / a.sum())
            yield self._areas[i]


def mass_mismatch(basis: Basis, mesh: Mesh | VertexAreas) -> float:
    """L1 distance of ``basis``'s and ``mesh``'s vertex areas in the best of :data:`AREA_SCHEMES`."""
    areas = mesh if isinstance(mesh, VertexAreas) else VertexAreas(mesh)
    b = np.asarray(basis.mass.sum(axis=1), dtype=np.float64).ravel()
    b = b / b.sum()
    best = np.inf
    for a in areas:
        best = min(best, float(np.abs(b - a).sum()))
        if best <= MASS_FIT_TOL:
            break
    return best


def check_given_bases(bases, mesh_x: Mesh, mesh_y: Mesh) -> tuple[Basis, Basis, bool]:
    """``(basis_x, basis_y, together)``: given bases checked, and whether built as a pair at the same seeds.

    Raises:
        ParameterError: not a pair of Basis objects, wrong vertex counts, or bases in the other order."""
    try:
        bx, by = bases
    except (TypeError, ValueError) as err:
        raise ParameterError("bases must be a pair (basis_x, basis_y) of Basis objects.") from err
    for b, mesh, name in ((bx, mesh_x, "x"), (by, mesh_y, "y")):
        if not isinstance(b, Basis):
            raise ParameterError(f"basis_{name} is a {type(b).__name__}, not a Basis. Fix: Basis.load(path).")
        if b.n_vertices != mesh.n_vertices:
            raise ParameterError(
                f"basis_{name} has {b.n_vertices} vertices but mesh_{name} has {mesh.n_vertices}. Fix: "
                "pass the basis built on that mesh (bases in the order source, target)."
            )
    areas = {"x": VertexAreas(mesh_x), "y": VertexAreas(mesh_y)}
    fit = {"x": mass_mismatch(bx, areas["x"]), "y": mass_mismatch(by, areas["y"])}
    if max(fit.values()) > MASS_FIT_TOL:
        if (
            mesh_x.n_vertices == mesh_y.n_vertices
            and max(mass_mismatch(bx, areas["y"]), mass_mismatch(by, areas["x"])) <= MASS_FIT_TOL
        ):
            raise ParameterError(
                "the given bases fit the meshes in the other order (their vertex areas are those of "
                "the other mesh). Fix: give the bases in the order source, target (CLI: --bases "
                "SRC.npz TGT.npz)."
            )
        for name, value in fit.items():
            if value > MASS_FIT_TOL:
                warnings.warn(
                    f"basis_{name}'s vertex areas are not mesh_{name}'s in any mass scheme torchfmap "
                    f"builds ({value / 2:.2g} of the area lies on other vertices): it was built on "
                    "another mesh with as many vertices (another pose or meshing), and the map is "
                    "then wrong, or with a mass of your own. Fix: build it on this mesh "
                    "(`torchfmap basis MESH --out FILE.npz`, or match without bases=), or pass the "
                    "meshes the bases were built on.",
                    MapWarning,
                    stacklevel=3,
                )
    seeded = any(c.seed >= 0 for b in (bx, by) for c in b.provenance)
    px, py = bx.pair_landmarks, by.pair_landmarks
    together = px is not None and py is not None and np.array_equal(px, py)
    if seeded and not together:
        warnings.warn(
            "the given bases have seeded columns but were not built together from the same "
            "landmark pairs, so their columns need not correspond and the map can be wrong. Fix: "
            "build them as a pair (`torchfmap basis SRC TGT --landmarks pairs.txt --out a.npz b.npz`, "
            "or match_bases()), or match with landmarks=... directly.",
            MapWarning,
            stacklevel=3,
        )
    return bx, by, seeded and together


def given_bases_kind(bases, mesh_x: Mesh, mesh_y: Mesh, basis) -> tuple[Basis, Basis, BasisKind, bool]:
    """``(basis_x, basis_y, kind, together)`` of given bases: ``kind`` is ``basis``, else ``'laplacian'`` for
    eigenfunctions only, else the kind they were built together by, else ``'stack'``."""
    bx, by, together = check_given_bases(bases, mesh_x, mesh_y)
    eigen_only = all(c.family == "laplacian" for b in (bx, by) for c in b.columns if c.kept)
    seeded = kind_of(bx) if together else None
    kind = get_kind(basis or ("laplacian" if eigen_only else seeded or "stack"))
    return bx, by, kind, together and kind.needs_landmarks
