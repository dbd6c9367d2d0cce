"""Sanity checks of mesh file bytes before parsing (OFF, STL, PLY, OBJ), so that a malformed file gets
a :class:`MeshError` naming its problem and the fix; used by :mod:`torchfmap.io`."""

from __future__ import annotations

import numpy as np

from ..errors import MeshError


def off_header_counts(text: str) -> tuple[int, int, int, int] | None:
    """``(n_vertices, n_faces, vertex lines, face lines)`` declared and present in OFF text
    (comments and blank lines skipped); None if the header cannot be read."""
    lines = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines or not lines[0].split()[0].upper().endswith("OFF"):
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


def off_without_comments(text: str) -> str:
    """OFF text without its comments and blank lines (trimesh takes them only before the counts)."""
    lines = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
    return "\n".join(ln for ln in lines if ln) + "\n"


def check_off(text: str, name: str) -> None:
    counts = off_header_counts(text)
    if counts is None:
        return
    n_v, n_f, have_v, have_f = counts
    if n_v < 0 or n_f < 0:
        raise MeshError(
            f"{name!r}: its OFF header declares {n_v} vertices and {n_f} faces; counts cannot be "
            "negative. Fix: copy or export the file again."
        )
    if have_v < n_v or have_f < n_f:
        raise MeshError(
            f"{name!r} is truncated: its OFF header declares {n_v} vertices and {n_f} faces, the file "
            f"holds {have_v} vertex lines and {have_f} face lines. Fix: copy or export the file again."
        )
    if have_f > n_f:
        raise MeshError(
            f"{name!r} holds {have_v + have_f} vertex and face lines, its OFF header declares {n_v} "
            f"vertices and {n_f} faces: lines were added, doubled or the counts edited. Fix: copy or "
            "export the file again (or correct the header counts)."
        )
    lines = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    start = len(lines) - have_f  # a face line starts with its corner count: under 3, trimesh drops it
    _check_off_rows(lines[start - n_v : start], lines[start:], name)
    short = [
        (start + i, ln)
        for i, ln in enumerate(lines[start : start + n_f])
        if not ln.split()[0].lstrip("-").isdigit() or int(ln.split()[0]) < 3
    ]
    if short:
        where = ", ".join(f"{ln!r}" for _, ln in short[:3]) + (
            f" ({len(short)} in all)" if len(short) > 3 else ""
        )
        raise MeshError(
            f"{name!r} has face lines with fewer than 3 corners: {where}. An OFF face line is "
            "'n i_1 ... i_n' with n >= 3. Fix: remove or complete those lines (and the face "
            "count in the header)."
        )
    try:
        ids = [int(t) for ln in lines[start : start + n_f] for t in ln.split()[1 : 1 + int(ln.split()[0])]]
    except ValueError:
        return  # trimesh names what it cannot parse
    if ids and min(ids) < 0:  # some trimesh versions index from the end with it
        raise MeshError(
            f"{name!r} has face index {min(ids)}: OFF indices are 0..{n_v - 1}, never negative. Fix: "
            "check the file's face lines."
        )
    if ids and max(ids) >= n_v:
        if min(ids) >= 1 and max(ids) == n_v:
            raise MeshError(
                f"{name!r} has 1-based face indices: every index is in 1..{n_v} and none is 0, but OFF "
                "indices are 0-based. Fix: subtract 1 from every face index (the first number of a "
                "face line is its corner count: leave it)."
            )
        raise MeshError(
            f"{name!r} has face index {max(ids)}, outside the {n_v} vertices of its header (indices "
            f"0..{n_v - 1}). Fix: check the file's header counts and face lines."
        )


def _check_off_rows(vertex_lines: list[str], face_lines: list[str], name: str) -> None:
    """Vertex lines of 3 or more numbers, all of one length, and face lines ``n i_1 ... i_n``."""
    widths = {len(ln.split()) for ln in vertex_lines}
    bad = next((ln for ln in vertex_lines if not all(is_float(t) for t in ln.split())), None)
    if bad is not None or len(widths) > 1 or (widths and min(widths) < 3):
        raise MeshError(
            f"{name!r}: its OFF vertex lines are not all 3 or more numbers of one length ({bad!r} among them)"
            if bad is not None
            else f"{name!r}: its OFF vertex lines hold {sorted(widths)} values: a face line is read as a "
            "vertex or the header's counts do not match the file. Fix: copy or export the file again."
        )
    for ln in face_lines:
        fields = ln.split()
        if fields[0].isdigit() and len(fields) < 1 + int(fields[0]):
            raise MeshError(
                f"{name!r}: the OFF face line {ln!r} lists fewer corners than its count "
                f"{fields[0]}. Fix: copy or export the file again."
            )


def check_stl(data: bytes, name: str) -> None:
    """Refuse bytes that are neither binary STL (84-byte header, ``50 n`` bytes) nor ASCII STL."""
    if len(data) >= 84 and len(data) == 84 + 50 * int.from_bytes(data[80:84], "little"):
        return
    head = data[:1024].lstrip().lower()
    if head.startswith(b"solid") and (b"facet" in data[:4096].lower() or len(data) < 4096):
        _check_stl_vertices(data.decode("latin-1"), name)
        return
    raise MeshError(
        f"{name!r} is not an STL file: not binary STL (84-byte header + 50 bytes per triangle; "
        f"{len(data)} bytes here) and not ASCII STL (starting 'solid' with 'facet' lines). Fix: "
        "check the file and its extension."
    )


def _check_stl_vertices(text: str, name: str) -> None:
    """ASCII STL ``vertex`` lines hold three numbers."""
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if fields[:1] == ["vertex"] and not (len(fields) == 4 and all(is_float(t) for t in fields[1:])):
            raise MeshError(
                f"{name!r}:{number}: {line.strip()!r} is not an STL vertex ('vertex x y z'): the line "
                "is damaged. Fix: copy or export the file again."
            )


def check_ply(data: bytes, name: str) -> None:
    """Refuse an ASCII PLY file whose element lines disagree with its header (line count, values per
    line, list lengths); binary PLY is left to trimesh."""
    end = data.find(b"end_header")
    if end < 0:
        return
    header = [ln.split() for ln in data[:end].decode("latin-1").splitlines()]
    if not any(f[:2] == ["format", "ascii"] for f in header):
        return
    elements: list[list] = []  # [element name, count, scalar properties, list properties]
    integer_lists: set[bool] = set()
    for f in header:
        if f[:1] == ["element"] and len(f) >= 3:
            if not f[2].isdigit():
                raise MeshError(
                    f"{name!r}: its PLY header declares {f[2]!r} {f[1]} elements, not a count. Fix: "
                    "copy or export the file again."
                )
            elements.append([f[1], int(f[2]), 0, 0])
        elif f[:1] == ["property"] and elements:
            elements[-1][3 if f[1:2] == ["list"] else 2] += 1
            if f[1:2] == ["list"] and len(f) > 3:
                integer_lists.add(f[3] in _PLY_INTEGER_TYPES)
    newline = data.find(b"\n", end)
    body = data[newline + 1 :] if newline >= 0 else b""
    lines = [ln.split() for ln in body.decode("latin-1").splitlines() if ln.strip()]
    declared = sum(count for _, count, _, _ in elements)
    described = ", ".join(f"{count} {element}" for element, count, _, _ in elements)
    if len(lines) != declared:
        raise MeshError(
            f"{name!r}: its PLY header declares {described} (one line each), the file holds "
            f"{len(lines)} lines after end_header: cut, lines added or doubled, or the counts edited. "
            "Fix: copy or export the file again."
        )
    start = 0
    for element, count, scalars, lists in elements:
        for number, fields in enumerate(lines[start : start + count], start=start):
            if lists == 0:  # some trimesh versions read '12x' as 12
                good = len(fields) == scalars and all(is_float(t) for t in fields)
            elif lists == 1 and scalars == 0:
                good = fields[0].isdigit() and len(fields) == 1 + int(fields[0])
                if good and integer_lists == {True}:
                    good = all(t.lstrip("-").isdigit() for t in fields[1:])
            else:
                good = True  # several lists or lists beside scalars: trimesh checks
            if not good:
                raise MeshError(
                    f"{name!r}: line {number + 1} after end_header, {' '.join(fields)!r}, does not fit "
                    f"the header's {element} element ({scalars} value(s)"
                    f"{', a list' if lists else ''}). Fix: copy or export the file again."
                )
        start += count


#: PLY's integer property types.
_PLY_INTEGER_TYPES = {"char", "uchar", "short", "ushort", "int", "uint", "int8", "uint8", "int16",
                      "uint16", "int32", "uint32"}  # fmt: skip
#: The statements of the OBJ format.
_OBJ_STATEMENTS = {
    "v", "vt", "vn", "vp", "f", "l", "p", "g", "o", "s", "mg", "mtllib", "usemtl", "usemap", "maplib",
    "cstype", "deg", "bmat", "step", "curv", "curv2", "surf", "parm", "trim", "hole", "scrv", "sp", "end",
    "con", "bevel", "c_interp", "d_interp", "lod", "shadow_obj", "trace_obj", "ctech", "stech", "call", "csh",
}  # fmt: skip


def check_obj(text: str, name: str) -> None:
    """Refuse OBJ lines that start with no OBJ statement, vertex lines that are not 3 or more numbers
    and face lines whose corners are not non-zero integers (``i``, ``i/t``, ``i//n``, ``i/t/n``)."""
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split("#", 1)[0].split()
        if fields and fields[0] not in _OBJ_STATEMENTS:
            raise MeshError(
                f"{name!r}:{number}: {line.strip()!r} is no OBJ statement (v, vt, vn, f, g, o, usemtl, "
                "...): the line is damaged. Fix: copy or export the file again."
            )
        if not fields or fields[0] not in ("v", "f"):
            continue
        if fields[0] == "v":
            good = len(fields) >= 4 and all(is_float(t) for t in fields[1:])
        else:
            corners = [t.split("/", 1)[0] for t in fields[1:]]
            good = len(corners) >= 3 and all(c.lstrip("-").isdigit() and int(c) != 0 for c in corners)
        if not good:
            raise MeshError(
                f"{name!r}:{number}: {line.strip()!r} is not an OBJ "
                f"{'vertex (v x y z)' if fields[0] == 'v' else 'face (f i j k, 1-based vertex indices)'}. "
                "Fix: copy or export the file again."
            )


def read_obj(text: str, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(V, 3)`` float64 vertices (every ``v`` line) and ``(F, 3)`` int64 faces (polygons fanned, made
    0-based) of an OBJ text passed by :func:`check_obj`; :class:`MeshError` for a corner out of range."""
    vertices, faces = [], []
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split("#", 1)[0].split()
        if not fields or fields[0] not in ("v", "f"):
            continue
        if fields[0] == "v":
            vertices.append([float(t) for t in fields[1:4]])
            continue
        corners = [int(t.split("/", 1)[0]) for t in fields[1:]]
        corners = [c - 1 if c > 0 else len(vertices) + c for c in corners]
        if min(corners) < 0 or max(corners) >= len(vertices):
            raise MeshError(
                f"{name!r}:{number}: {line.strip()!r} names a vertex outside the {len(vertices)} defined "
                "before it. Fix: copy or export the file again."
            )
        faces.extend([corners[0], corners[i], corners[i + 1]] for i in range(1, len(corners) - 1))
    return (
        np.asarray(vertices, dtype=np.float64).reshape(-1, 3),
        np.asarray(faces, dtype=np.int64).reshape(-1, 3),
    )


def is_float(token: str) -> bool:
    """Whether ``token`` reads as a float (``nan`` and ``inf`` included)."""
    try:
        float(token)
        return True
    except ValueError:
        return False
