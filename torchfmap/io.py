"""Reading and writing meshes without ever changing vertex order.

Ground-truth correspondences are vertex indices, so a loader that merges, sorts or drops
vertices silently breaks them. :func:`load_mesh` goes through trimesh with ``process=False``
and ``maintain_order=True``; the one exception is STL, a triangle soup with no shared vertices,
where identical corners are merged **in order of first appearance** (the only vertex order an
STL file defines).
"""

from __future__ import annotations

import gzip
import io as _io
import os
from pathlib import Path

import numpy as np
import trimesh

from .errors import MeshError
from .mesh import Mesh

SUPPORTED_FORMATS = (".off", ".ply", ".obj", ".stl")


def _format_of(path: Path) -> tuple[str, bool]:
    suffixes = [s.lower() for s in path.suffixes]
    gz = bool(suffixes) and suffixes[-1] == ".gz"
    ext = suffixes[-2] if gz and len(suffixes) >= 2 else (suffixes[-1] if suffixes else "")
    if ext not in SUPPORTED_FORMATS:
        raise MeshError(
            f"cannot read {path.name!r}: unsupported extension {ext or '(none)'!r}. Fix: use one of "
            f"{', '.join(SUPPORTED_FORMATS)} (optionally .gz-compressed)."
        )
    return ext[1:], gz


def merge_soup(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge bit-identical vertices, keeping them in order of first appearance."""
    uniq, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # unique rows sorted by first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return vertices[np.sort(first)], rank[inverse.ravel()][faces]


def read_arrays(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3) float64, faces (F, 3) int64)`` of a mesh file, vertex order kept."""
    path = Path(path)
    if not path.exists():
        raise MeshError(f"mesh file {str(path)!r} does not exist. Fix: check the path.")
    fmt, gz = _format_of(path)
    try:
        if gz:
            with gzip.open(path, "rb") as fh:
                data = fh.read()
            loaded = trimesh.load(
                _io.BytesIO(data), file_type=fmt, process=False, maintain_order=True, force="mesh"
            )
        else:
            loaded = trimesh.load(path, file_type=fmt, process=False, maintain_order=True, force="mesh")
    except MeshError:
        raise
    except Exception as err:  # trimesh raises many types for malformed files
        raise MeshError(f"could not parse {path.name!r} as {fmt.upper()}: {err}") from err
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64).reshape(-1, 3)
    if fmt == "stl" and len(faces):
        vertices, faces = merge_soup(vertices, faces)
    return vertices, faces


def load_mesh(path: str | os.PathLike, *, validate: bool = True, **flags) -> Mesh:
    """Load a triangle mesh (.off/.ply/.obj/.stl, optionally .gz) keeping the file's vertex order.

    Args:
        path: file path.
        validate: run :func:`~torchfmap.mesh.validate_mesh`; extra keyword flags
            (``allow_components``, ``allow_unreferenced``, ``allow_nonmanifold``) go to it.

    Returns:
        a :class:`~torchfmap.Mesh` named after the file.
    """
    vertices, faces = read_arrays(path)
    name = Path(path).name.split(".")[0]
    return Mesh(vertices, faces, validate=validate, name=name, **flags)


def save_mesh(mesh: Mesh, path: str | os.PathLike) -> Path:
    """Write a mesh (format from the extension, .gz allowed), atomically, vertex order kept."""
    path = Path(path)
    fmt, gz = _format_of(path)
    data = mesh.to_trimesh().export(file_type=fmt)
    if isinstance(data, str):
        data = data.encode()
    if gz:
        data = gzip.compress(data)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)
    return path
