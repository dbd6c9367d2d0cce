"""Every file format torchfmap reads or writes: meshes (vertex order kept), point maps, ``.vts``, landmark,
landmark-pair and test-pairs files, by the last suffix before an optional ``.gz`` (:func:`split_suffix`);
writes are atomic (:func:`torchfmap._util.files.atomic_write`). Index files are text, a row per line (``#``
comments, blank lines, a BOM ignored); a malformed one raises :class:`~torchfmap.errors.TorchFmapError`."""

from __future__ import annotations

import gzip
import io as _io
import os
import re
import warnings
import zlib
from pathlib import Path

import numpy as np
import trimesh

from ._util.files import atomic_write
from ._util.format_checks import check_obj, check_ply, is_float, off_without_comments, read_obj
from ._util.format_checks import check_off as _check_off
from ._util.format_checks import check_stl as _check_stl
from ._util.format_checks import off_header_counts as off_header_counts
from .errors import MeshError, ParameterError, TorchFmapError
from .mesh import Mesh, weld_vertices

#: Mesh formats (without the dot), each also readable and writable as ``<format>.gz``.
MESH_FORMATS = ("off", "ply", "obj", "stl")
SUPPORTED_FORMATS = tuple(f".{fmt}" for fmt in MESH_FORMATS)


def split_suffix(path: str | os.PathLike) -> tuple[str, bool]:
    """``(format, gzipped)`` of a file name: ``cat.OFF.gz`` -> ``('off', True)``, ``x`` -> ``('', False)``."""
    suffixes = [s.lower() for s in Path(path).suffixes]
    gz = bool(suffixes) and suffixes[-1] == ".gz"
    if gz:
        suffixes = suffixes[:-1]
    return (suffixes[-1][1:] if suffixes else ""), gz


def is_mesh_file(path: str | os.PathLike) -> bool:
    """Whether the name is one :func:`load_mesh` and :func:`mesh_files` take (:data:`MESH_FORMATS`[.gz])."""
    return split_suffix(path)[0] in MESH_FORMATS


def mesh_files(folder: str | os.PathLike) -> list[Path]:
    """A folder's mesh files (:func:`is_mesh_file`), by name; :class:`ParameterError` if not a folder."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ParameterError(f"{str(folder)!r} is not a folder. Fix: give the folder that holds the meshes.")
    return sorted((f for f in folder.iterdir() if f.is_file() and is_mesh_file(f)), key=lambda f: f.name)


def shape_name(path: str | os.PathLike) -> str:
    """The name of the shape in a file: the file name up to its first dot (``cat0.off.gz`` -> ``cat0``)."""
    return Path(path).name.split(".")[0]


def find_file(folder: str | os.PathLike, name: str) -> Path | None:
    """``folder/name`` or, if only that exists compressed, ``folder/name.gz``; None if neither."""
    return next((c for c in (Path(folder) / name, Path(folder) / f"{name}.gz") if c.is_file()), None)


def _format_of(path: Path) -> tuple[str, bool]:
    fmt, gz = split_suffix(path)
    if fmt not in MESH_FORMATS:
        raise MeshError(
            f"cannot read {path.name!r}: unsupported extension {'.' + fmt if fmt else '(none)'!r}. Fix: use "
            f"one of {', '.join(SUPPORTED_FORMATS)} (optionally .gz-compressed)."
        )
    return fmt, gz


def _read_bytes(path: str | os.PathLike, what: str, error: type[TorchFmapError] = TorchFmapError) -> bytes:
    try:
        with gzip.open(path, "rb") if split_suffix(path)[1] else open(path, "rb") as fh:
            return fh.read()
    except (OSError, EOFError, zlib.error) as err:
        raise error(
            f"cannot read the {what} file {str(path)!r} ({err}). Fix: check the path (a .gz name must "
            "hold gzip data)."
        ) from err


def _write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    if split_suffix(path)[1]:
        data = gzip.compress(data, mtime=0)
    return atomic_write(path, lambda fh: fh.write(data))


#: Text formats, decoded here (UTF-8, else Latin-1): trimesh would look for a charset detector.
TEXT_FORMATS = ("off", "obj")


def _existing_file(path, what: str) -> Path:
    path = Path(path)
    if not path.exists():
        raise MeshError(f"{what} file {str(path)!r} does not exist. Fix: check the path.")
    if path.is_dir():
        raise MeshError(
            f"{str(path)!r} is a folder, not a {what} file. Fix: give the path of one {what} file."
        )
    return path


def read_arrays(path: str | os.PathLike, *, points: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3) float64, faces (F, 3) int64)`` of a mesh file, vertex order kept. Raises
    :class:`MeshError` for a missing path, a folder, an unsupported extension, a malformed file, and a
    point cloud (:func:`load_points`; ``points=True`` returns its points with ``(0, 3)`` faces)."""
    path = _existing_file(path, "mesh")
    fmt, gz = _format_of(path)
    data = _read_bytes(path, "mesh", MeshError)
    if not data.strip():
        raise MeshError(
            f"{path.name!r} is empty ({len(data)} bytes): no vertices, no faces. Fix: copy or export the "
            "mesh again."
        )
    data = _checked_bytes(data, fmt, path.name)
    if fmt == "obj":  # trimesh drops the vertices no face references
        vertices, faces = read_obj(data.decode("utf-8"), path.name)
    else:
        try:
            loaded = trimesh.load(
                _io.BytesIO(data), file_type=fmt, process=False, maintain_order=True, force="mesh"
            )
        except Exception as err:  # trimesh raises many types for malformed files
            raise MeshError(
                f"could not parse {path.name!r} as {fmt.upper()} (the parser said: {err}). Fix: check "
                f"that the file is a {fmt.upper()} mesh (its extension names the format; open it in a "
                "viewer)."
            ) from err
        vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    if fmt == "stl" and len(faces):
        vertices, faces, _ = weld_vertices(vertices, faces, rtol=0)  # STL stores a soup
    if len(faces) == 0 and fmt in ("ply", "off", "obj"):
        cloud = _read_points(data, fmt)
        if points:
            return cloud, np.zeros((0, 3), dtype=np.int64)
        if n := len(cloud):
            raise MeshError(
                f"{path.name!r} holds {n} points and no faces: a point cloud, not a mesh, and matching needs "
                "a triangle mesh. Fix: mesh it first (e.g. screened Poisson reconstruction in MeshLab); its "
                f"operators alone come from torchfmap.io.load_points({path.name!r}) and laplacian(points, "
                "scheme='robust')."
            )
    return vertices, faces


def _checked_bytes(data: bytes, fmt: str, name: str) -> bytes:
    """Text decoded, checked by :mod:`torchfmap._util.format_checks`, OFF comments removed."""
    if fmt in TEXT_FORMATS:
        try:
            data.decode("utf-8")
        except UnicodeDecodeError:
            data = data.decode("latin-1").encode("utf-8")
    if fmt == "off":
        _check_off(data.decode("utf-8"), name)
        data = off_without_comments(data.decode("utf-8")).encode()
    elif fmt == "obj":
        check_obj(data.decode("utf-8"), name)
    elif fmt == "ply":
        check_ply(data, name)
    elif fmt == "stl":
        _check_stl(data, name)
    return data


def _read_points(data: bytes, fmt: str) -> np.ndarray:
    if fmt == "obj":
        return read_obj(data.decode("utf-8"), "")[0]
    try:
        loaded = trimesh.load(_io.BytesIO(data), file_type=fmt, process=False, maintain_order=True)
    except Exception:  # the file was parsed as a mesh already; no points means none
        return np.zeros((0, 3))
    return np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)


def load_points(path: str | os.PathLike) -> np.ndarray:
    """``(V, 3)`` float64 points of a point-cloud or mesh file (.ply/.off/.obj[.gz]) in file order, for
    :func:`~torchfmap.operators.laplacian` (``scheme='robust'``); :class:`MeshError` if missing or bad."""
    path = _existing_file(path, "point")
    fmt, _ = _format_of(path)
    if fmt not in ("ply", "off", "obj"):
        raise MeshError(f"{path.name!r}: point clouds are read from .ply/.off/.obj files. Fix: convert it.")
    data = _read_bytes(path, "point", MeshError)
    points = _read_points(_checked_bytes(data, fmt, path.name), fmt)
    if len(points) == 0:
        raise MeshError(f"{path.name!r} holds no points. Fix: check the file.")
    if not np.isfinite(points).all():
        raise MeshError(f"{path.name!r} has NaN or infinite coordinates. Fix: repair or remove those points.")
    return points


def load_mesh(path: str | os.PathLike, *, validate: bool = True, **flags) -> Mesh:
    """A :class:`~torchfmap.Mesh` named after the file (.off/.ply/.obj/.stl, optionally .gz), vertex
    order kept. Duplicated faces are dropped and non-manifold edges accepted, each with a
    :class:`~torchfmap.MeshWarning` (``allow_nonmanifold=False`` refuses them). ``validate`` runs
    :func:`~torchfmap.mesh.validate_mesh`, with the keyword ``flags`` (``allow_*``)."""
    vertices, faces = read_arrays(path)
    flags.setdefault("allow_nonmanifold", "warn")
    try:
        return Mesh(vertices, faces, validate=validate, name=shape_name(path), **flags)
    except MeshError as err:
        raise MeshError(f"{str(path)!r}: {err}") from err


def save_mesh(mesh: Mesh, path: str | os.PathLike) -> Path:
    """Write a mesh (format from the extension, .gz allowed), atomically, vertex order kept."""
    path = Path(path)
    fmt, _ = _format_of(path)
    data = mesh.to_trimesh().export(file_type=fmt)
    return _write_bytes(path, data.encode() if isinstance(data, str) else data)


def read_text(path: str | os.PathLike, what: str) -> str:
    """A UTF-8 file's text (BOM dropped); ``what`` names it in the :class:`TorchFmapError` if unreadable."""
    data = _read_bytes(path, what)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise TorchFmapError(
            f"the {what} file {str(path)!r} is not UTF-8 text ({err}). Fix: save it as text."
        ) from err


def _fields(line: str) -> list[str]:
    """The fields of one line: ``#`` starts a comment; white space, commas and semicolons separate."""
    return _SEPARATORS.split(line.split("#", 1)[0].strip()) if line.split("#", 1)[0].strip() else []


def _parse_rows(text: str, path, columns: int | None, what: str) -> np.ndarray:
    """The careful parser: skips a header line of words (e.g. ``source,target``), names the first bad line."""
    rows, width, first = [], columns, True
    for number, line in enumerate(text.splitlines(), start=1):
        fields = _fields(line)
        if not fields:
            continue
        if first and all(_HEADER_WORD.match(f) and not is_float(f) for f in fields):
            first = False
            continue  # a header line: words only, e.g. 'source,target' (a damaged number is no word)
        first = False
        width = len(fields) if width is None else width
        if len(fields) != width:
            raise TorchFmapError(
                f"{path}:{number}: expected {width} integer column(s) per line ({what}), got "
                f"{len(fields)}: {line.strip()!r}. Fix: {_one_entry(what, width)}."
            )
        if not all(f.lstrip("+-").isdigit() for f in fields):
            raise TorchFmapError(
                f"{path}:{number}: {line.strip()!r} is not {width} integer vertex index(es) ({what}). Fix: "
                f"{_one_entry(what, width)}; only the first line may be a header, comments start with #."
            )
        rows.append([int(f) for f in fields])
    if not rows:
        raise TorchFmapError(f"the {what} file {str(path)!r} holds no entries. Fix: one entry per line.")
    try:
        return np.array(rows, dtype=np.int64)
    except OverflowError as err:
        raise TorchFmapError(f"{path}: a {what} index does not fit in 64 bits. Fix: check the file.") from err


_NOT_INTEGER_TEXT = re.compile(r"[^0-9\s+\-\ufeff]")
_LONG_NUMBER = re.compile(r"\d{19,}")  # may not fit in int64
_HEADER_WORD = re.compile(r"[A-Za-z_][A-Za-z0-9_.\-]*$")
_SEPARATORS = re.compile(r"[\s,;]+")


def _one_entry(what: str, width: int) -> str:
    if width == 2:
        return f"one {what} per line, two 0-based vertex indices 'i j' (or 'i,j')"
    return f"one {what} entry per line, {width} integer(s) each"


def read_index_table(path: str | os.PathLike, columns: int | None, what: str) -> np.ndarray:
    """``(N, columns)`` integer rows of a text file (``columns=None``: any, the same on every line); raises
    :class:`TorchFmapError` naming the file and line for an unreadable, empty, ragged or non-integer file."""
    text = read_text(path, what)
    body = "\n".join(line.split("#", 1)[0] for line in text.splitlines())
    if _NOT_INTEGER_TEXT.search(body) or _LONG_NUMBER.search(body):
        # e.g. '1.5' (truncated by some loadtxt) or 10**30 (wrapped to a negative by numpy 2.0's)
        return _parse_rows(text, path, columns, what)
    try:  # fast path for well-formed files; the careful parser names the problem otherwise
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # an empty file is reported below
            data = np.loadtxt(_io.StringIO(text), dtype=np.int64, ndmin=2, comments="#")
        if data.size and (columns is None or data.shape[1] == columns):
            return data
    except (ValueError, OverflowError):
        pass
    return _parse_rows(text, path, columns, what)


def read_landmarks(path: str | os.PathLike) -> np.ndarray:
    """``(L,)`` 0-based vertex indices, one per line (a landmark file)."""
    return read_index_table(path, 1, "landmark")[:, 0]


def read_landmark_pairs(path: str | os.PathLike) -> np.ndarray:
    """``(L, 2)`` 0-based pairs ``source_vertex target_vertex`` (``x y``), one per line."""
    return read_index_table(path, 2, "landmark pair")


def read_map(path: str | os.PathLike) -> np.ndarray:
    """``(V_y,)`` 0-based point map (:func:`write_map`): line ``v`` holds target vertex ``v``'s source."""
    return read_index_table(path, 1, "point map")[:, 0]


def write_map(path: str | os.PathLike, p2p_yx: np.ndarray) -> Path:
    """Write a point map ``(V_y,)`` as :func:`read_map` reads it, atomically; returns the path."""
    p2p_yx = np.asarray(p2p_yx)
    if p2p_yx.ndim != 1 or not np.issubdtype(p2p_yx.dtype, np.integer):
        raise ParameterError(
            f"a point map is a 1-D integer array, got shape {p2p_yx.shape} and dtype {p2p_yx.dtype}. "
            "Fix: pass p2p_yx (one source vertex per target vertex)."
        )
    text = "".join(f"{int(v)}\n" for v in p2p_yx)
    return _write_bytes(path, text.encode())


def read_vts(path: str | os.PathLike) -> np.ndarray:
    """``(P,)`` 0-based indices of a 1-based ``.vts`` file (column 1); :class:`ParameterError` for ids < 1."""
    ids = read_index_table(path, None, ".vts")[:, 0]
    if ids.min() < 1:
        raise ParameterError(
            f"{str(path)!r} holds vertex id {int(ids.min())}: .vts files are 1-based. Fix: if this file is "
            "0-based, read it with read_index_table and add no offset (gt_from_vts takes 0-based arrays)."
        )
    return ids - 1


def read_test_pairs(path: str | os.PathLike) -> list[tuple[str, str]]:
    """``[(name_x, name_y), ...]``: the first two shape names of every line of a test-pairs file, in
    order; :class:`TorchFmapError` for an unreadable or empty file or a line with one name."""
    pairs = []
    for number, line in enumerate(read_text(path, "test pairs").splitlines(), start=1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        if len(fields) < 2:
            raise TorchFmapError(
                f"{path}:{number}: a test pair needs two shape names, got {line.strip()!r}. Fix: write "
                "'source target' on each line."
            )
        pairs.append((fields[0], fields[1]))
    if not pairs:
        raise TorchFmapError(
            f"the test pairs file {str(path)!r} holds no pairs. Fix: one 'source target' per line."
        )
    return pairs
