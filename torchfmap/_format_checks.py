"""Sanity checks of mesh file bytes before parsing (OFF header counts, face lines and index
base; STL bytes), so a malformed file gets a message naming its problem and the fix instead
of a parser's error. Used by :mod:`torchfmap.io`, the home of every file format."""

from __future__ import annotations

from .errors import MeshError


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


def check_off(text: str, name: str) -> None:
    counts = off_header_counts(text)
    if counts is None:
        return
    n_v, n_f, have_v, have_f = counts
    if have_v < n_v or have_f < n_f:
        raise MeshError(
            f"{name!r} is truncated: its OFF header declares {n_v} vertices and {n_f} faces, the file "
            f"holds {have_v} vertex lines and {have_f} face lines. Fix: copy or export the file again."
        )
    # a face line starts with its corner count: under 3 is no face (trimesh would drop it, and
    # the mesh would load with a new hole)
    lines = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    start = len(lines) - have_f
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


def check_stl(data: bytes, name: str) -> None:
    """Refuse bytes that are neither binary STL (80-byte header, a triangle count ``n`` and
    ``50 n`` bytes) nor ASCII STL (``solid`` ... ``facet``)."""
    if len(data) >= 84 and len(data) == 84 + 50 * int.from_bytes(data[80:84], "little"):
        return
    head = data[:1024].lstrip().lower()
    if head.startswith(b"solid") and (b"facet" in data[:4096].lower() or len(data) < 4096):
        return
    raise MeshError(
        f"{name!r} is not an STL file: not binary STL (84-byte header + 50 bytes per triangle; "
        f"{len(data)} bytes here) and not ASCII STL (starting 'solid' with 'facet' lines). Fix: "
        "check the file and its extension."
    )
