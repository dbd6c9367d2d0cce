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

from ._files import atomic_write
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


#: Text formats: decoded here (UTF-8, else Latin-1) so a stray non-UTF-8 byte in a comment
#: does not send trimesh looking for an optional charset detector.
TEXT_FORMATS = ("off", "obj")


def _decode(data: bytes) -> bytes:
    try:
        data.decode("utf-8")
        return data
    except UnicodeDecodeError:
        return data.decode("latin-1").encode("utf-8")


def off_header_counts(text: str) -> tuple[int, int, int, int] | None:
    """``(n_vertices, n_faces, vertex lines, face lines)`` declared and present in OFF text.

    Comments (``#``) and blank lines are skipped; the counts may follow ``OFF`` on its line.
    None if the header cannot be read (trimesh then reports the parse error).
    """
    lines = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines or not lines[0].upper().endswith("OFF"):
        return None
    head = lines[0].split()[1:]
    rest = lines[1:]
    if not head:
        if not rest:
            return None
        head, rest = rest[0].split(), rest[1:]
    try:
        n_v, n_f = int(head[0]), int(head[1])
    except (IndexError, ValueError):
        return None
    return n_v, n_f, min(len(rest), n_v), max(0, len(rest) - n_v)


def _check_off(text: str, name: str) -> None:
    counts = off_header_counts(text)
    if counts is None:
        return
    n_v, n_f, have_v, have_f = counts
    if have_v < n_v or have_f < n_f:
        raise MeshError(
            f"{name!r} is truncated: its OFF header declares {n_v} vertices and {n_f} faces, the file "
            f"holds {have_v} vertex lines and {have_f} face lines. Fix: copy or export the file again."
        )


def read_arrays(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3) float64, faces (F, 3) int64)`` of a mesh file, vertex order kept.

    Raises :class:`MeshError` for a missing path, a folder, an unsupported extension, an OFF
    file shorter than its header says, and anything trimesh cannot parse.
    """
    path = Path(path)
    if not path.exists():
        raise MeshError(f"mesh file {str(path)!r} does not exist. Fix: check the path.")
    if path.is_dir():
        raise MeshError(f"{str(path)!r} is a folder, not a mesh file. Fix: give the path of one mesh file.")
    fmt, gz = _format_of(path)
    try:
        with gzip.open(path, "rb") if gz else open(path, "rb") as fh:
            data = fh.read()
        if fmt in TEXT_FORMATS:
            data = _decode(data)
        if fmt == "off":
            _check_off(data.decode("utf-8"), path.name)
        loaded = trimesh.load(
            _io.BytesIO(data), file_type=fmt, process=False, maintain_order=True, force="mesh"
        )
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
    try:
        return Mesh(vertices, faces, validate=validate, name=name, **flags)
    except MeshError as err:
        raise MeshError(f"{str(path)!r}: {err}") from err


def save_mesh(mesh: Mesh, path: str | os.PathLike) -> Path:
    """Write a mesh (format from the extension, .gz allowed), atomically, vertex order kept."""
    path = Path(path)
    fmt, gz = _format_of(path)
    data = mesh.to_trimesh().export(file_type=fmt)
    if isinstance(data, str):
        data = data.encode()
    if gz:
        data = gzip.compress(data)
    return atomic_write(path, lambda fh: fh.write(data))
