"""Fuzzing every file torchfmap reads: meshes (OFF and its NOFF/COFF variants, PLY, OBJ, STL,
plain and ``.gz``), point files, ``.vts`` ground truth, landmark and landmark-pair files, point
maps, test-pairs files, saved bases (``.npz``), checkpoints and training-cache entries.

Each reader starts from a valid file and is fed mutations drawn by hypothesis (:func:`check`).
The property: the reader returns what the mutation allows, or raises a
:class:`~torchfmap.errors.TorchFmapError` whose message names the file; any other exception, a
call over :data:`TIME_LIMIT` seconds (a hang) or a result the mutation does not allow fails.
What a mutation allows (its *verdict*):

- ``same``: the file means the same (comments, CRLF line ends, a byte-order mark, separators, a
  header line, gzip): the original result;
- ``refuse``: the file is malformed in a way its format can tell (counts that disagree with the
  content, NaN or infinite coordinates, indices outside the vertices, no content, undecodable
  text, an altered checksummed file): an error;
- ``prefix``: a cut at a line end of a format that declares no counts (OBJ, ASCII STL, index
  tables): an error or the original's first rows (nothing reordered or altered);
- ``last_row``: a cut inside the last line, which no text format can tell from a file without a
  final newline: an error or the original with its last row dropped or changed;
- ``valid``: bytes overwritten at random (a digit changed into another digit cannot be detected):
  an error or a well-formed result (finite coordinates, faces within the vertices).

``tests/test_fuzz.py`` runs a bounded number of examples per reader in CI;
``python -m bench robustness --case fuzz`` runs many and tabulates the outcomes.
"""

from __future__ import annotations

import gzip
import io
import pickle
import signal
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchfmap.errors import TorchFmapError

#: Seconds one read may take: the files are a few kilobytes and parse in milliseconds; the
#: bound leaves room for a loaded CI machine and catches a hang or a runaway allocation.
TIME_LIMIT = 10.0


# -- the valid files -----------------------------------------------------------------------------
def seed_mesh():
    """42 vertices, 80 faces: an icosphere with a fixed jitter (no symmetry hides a reordering)."""
    from torchfmap import Mesh
    from torchfmap.data import icosphere

    base = icosphere(1)
    rng = np.random.default_rng(0)
    return Mesh(base.vertices + 0.05 * rng.normal(size=base.vertices.shape), base.faces, name="seed")


def off_text(mesh, variant: str) -> str:
    """OFF text of ``mesh``: ``plain``, ``inline`` (counts on the ``OFF`` line), ``noff``
    (normals), ``coff`` (colours) or ``comments``."""
    v, f = mesh.vertices, mesh.faces
    head = {"noff": "NOFF", "coff": "COFF"}.get(variant, "OFF")
    extra = {"noff": " 0 0 1", "coff": " 255 128 0 255"}.get(variant, "")
    lines = [f"{head} {len(v)} {len(f)} 0"] if variant == "inline" else [head, f"{len(v)} {len(f)} 0"]
    if variant == "comments":
        lines.insert(1, "# written by the fuzz suite")
    lines += [f"{x!r} {y!r} {z!r}{extra}" for x, y, z in v.tolist()]
    lines += [f"3 {a} {b} {c}" for a, b, c in f.tolist()]
    return "\n".join(lines) + "\n"


def trimesh_bytes(mesh, fmt: str, **kwargs) -> bytes:
    data = mesh.to_trimesh().export(file_type=fmt, **kwargs)
    return data.encode() if isinstance(data, str) else data


# -- the readers ---------------------------------------------------------------------------------
@dataclass
class Reader:
    """A reader under test: ``make(folder) -> (path, bytes)`` writes nothing, ``read(path)`` reads,
    ``text`` says whether line mutations apply, ``counted`` whether the format declares its
    element counts (so a cut line is detectable), ``kind`` the family of mutations."""

    name: str
    suffix: str
    make: Callable[[], bytes]
    read: Callable[[Path], object]
    kind: str  # 'mesh', 'table', 'binary_mesh', 'checked'
    text: bool = True
    counted: bool = False
    comment: str | None = None  # how a comment line starts, when the format has them


def _load_mesh(path):
    from torchfmap.io import load_mesh

    return load_mesh(path)


def _load_points(path):
    from torchfmap.io import load_points

    return load_points(path)


def _table(fn_name):
    def read(path):
        from torchfmap import io as tio

        return getattr(tio, fn_name)(path)

    return read


def _table_bytes(rows: list[list[int]]) -> bytes:
    return "".join(" ".join(str(v) for v in row) + "\n" for row in rows).encode()


def _read_basis(path):
    from torchfmap.bases.basis import Basis

    return Basis.load(path)


def _basis_bytes() -> bytes:
    from torchfmap.bases.prepared import prepare_shape

    basis = prepare_shape(seed_mesh(), 6).eigenbasis
    with tempfile.TemporaryDirectory() as tmp:
        return Path(basis.save(Path(tmp) / "b.npz")).read_bytes()


def _read_checkpoint(path):
    from torchfmap.nn.checkpoints import load_checkpoint

    return load_checkpoint(path)


def tiny_checkpoint(path: Path) -> Path:
    """A tiny recipe network's checkpoint (width 8, one block), written by the library's writer."""
    from torchfmap.nn.checkpoints import save_checkpoint
    from torchfmap.nn.config import TrainConfig, build_model

    config = TrainConfig(k=8, n_wks=8, width=8, c_out=8, n_blocks=1)
    return save_checkpoint(path, build_model(config)[0], config)


def _checkpoint_bytes() -> bytes:
    with tempfile.TemporaryDirectory() as tmp:
        return tiny_checkpoint(Path(tmp) / "c.pt").read_bytes()


def _read_cache(path):
    from torchfmap.nn.data import PrecomputeCache

    return PrecomputeCache(path.parent).load(path.stem)


def _cache_bytes() -> bytes:
    from torchfmap._util.files import save_arrays
    from torchfmap.nn.data import CACHE_CHECKSUM_KEY

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "e.npz"
        save_arrays(path, {"evals": np.linspace(0, 1, 5), "evecs": np.eye(6, 5)}, CACHE_CHECKSUM_KEY)
        return path.read_bytes()


def ply_points(mesh) -> bytes:
    """An ASCII PLY point cloud of the mesh's vertices (no faces)."""
    head = f"ply\nformat ascii 1.0\nelement vertex {mesh.n_vertices}\n"
    head += "property float x\nproperty float y\nproperty float z\nend_header\n"
    return (head + "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in mesh.vertices.tolist())).encode()


def readers() -> dict[str, Reader]:
    """Every reader, by name."""
    mesh = seed_mesh()

    def off(variant):
        return lambda: off_text(mesh, variant).encode()

    def trimesh_file(fmt, **kwargs):
        return lambda: trimesh_bytes(mesh, fmt, **kwargs)

    def indices(values):
        return lambda: _table_bytes([list(np.atleast_1d(v)) for v in values])

    text_off = dict(kind="mesh", counted=True, comment="#")
    binary = dict(kind="binary_mesh", text=False, counted=True)
    table = dict(kind="table", comment="#")
    out = [
        Reader("off", ".off", off("plain"), _load_mesh, **text_off),
        Reader("off inline counts", ".off", off("inline"), _load_mesh, **text_off),
        Reader("noff", ".off", off("noff"), _load_mesh, **text_off),
        Reader("coff", ".off", off("coff"), _load_mesh, **text_off),
        Reader("off.gz", ".off.gz", off("comments"), _load_mesh, **text_off),
        Reader("ply ascii", ".ply", trimesh_file("ply", encoding="ascii"), _load_mesh, "mesh", counted=True),
        Reader("ply binary", ".ply", trimesh_file("ply"), _load_mesh, **binary),
        Reader("obj", ".obj", trimesh_file("obj"), _load_mesh, "mesh", comment="#"),
        Reader("stl binary", ".stl", trimesh_file("stl"), _load_mesh, **binary),
        Reader("stl ascii", ".stl", trimesh_file("stl_ascii"), _load_mesh, "mesh"),
        Reader("points ply", ".ply", lambda: ply_points(mesh), _load_points, "points", counted=True),
        Reader("points off", ".off", off("plain"), _load_points, "points", counted=True, comment="#"),
        Reader("map", ".txt", indices(np.arange(40) * 7 % 42), _table("read_map"), "table", comment="#"),
        Reader("vts", ".vts", indices(np.arange(1, 41) * 5 % 42 + 1), _table("read_vts"), **table),
        Reader("landmarks", ".txt", indices([3, 17, 29, 40]), _table("read_landmarks"), "table", comment="#"),
        Reader("landmark pairs", ".txt", indices([[3, 5], [17, 2], [29, 31], [40, 0]]),
               _table("read_landmark_pairs"), "table", comment="#"),
        Reader("test pairs", ".txt", lambda: b"tr_reg_080 tr_reg_081\ntr_reg_082 tr_reg_083\ncat0 cat1\n",
               _table("read_test_pairs"), "names", comment="#"),
        Reader("basis npz", ".npz", _basis_bytes, _read_basis, "checked", text=False),
        Reader("checkpoint", ".pt", _checkpoint_bytes, _read_checkpoint, "checked", text=False),
        Reader("cache entry", ".npz", _cache_bytes, _read_cache, "cache", text=False),
    ]  # fmt: skip
    return {r.name: r for r in out}


# -- where the rows are --------------------------------------------------------------------------
def _is_blank(line: bytes, comment: str | None) -> bool:
    body = line.split(comment.encode(), 1)[0] if comment else line
    return not body.strip()


def layout(reader: Reader, lines: list[bytes]) -> tuple[list[int], list[int], list[tuple[int, int]]]:
    """``(vertex line ids, face line ids, count tokens (line id, token id))`` of a text file.
    Tables: every non-blank line is a row (listed as vertex lines); no faces, no counts."""
    data = [i for i, ln in enumerate(lines) if not _is_blank(ln, reader.comment)]
    if reader.kind in ("table", "names"):
        return data, [], []
    first = lines[data[0]].split()
    if first[0].endswith(b"OFF"):  # OFF, NOFF, COFF; counts inline or on the next line
        if len(first) > 1:
            counts, start = [(data[0], 1), (data[0], 2)], 1
        else:
            counts, start = [(data[1], 0), (data[1], 1)], 2
        n_v = int(lines[counts[0][0]].split()[counts[0][1]])
        return data[start : start + n_v], data[start + n_v :], counts
    if first[0] == b"ply":
        end = next(i for i in data if lines[i].strip() == b"end_header")
        counts = [(i, 2) for i in data if lines[i].startswith(b"element ")]
        n_v = int(lines[counts[0][0]].split()[2])
        body = [i for i in data if i > end]
        return body[:n_v], body[n_v:], counts
    vertex = [i for i in data if lines[i].split()[0] in (b"v", b"vertex")]
    face = [i for i in data if lines[i].split()[0] == b"f"]
    return vertex, face, []


# -- mutations -----------------------------------------------------------------------------------
@dataclass
class Mutant:
    """A mutated file: its bytes, what it may give (the module docstring's verdicts) and how it
    was made (for the failure message)."""

    data: bytes
    verdict: str
    what: str


def _replace_token(line: bytes, index: int, token: bytes) -> bytes:
    tokens = line.split()
    tokens[index % len(tokens)] = token
    return b" ".join(tokens)


def _join(lines: list[bytes]) -> bytes:
    return b"\n".join(lines)


def text_mutant(draw, reader: Reader, data: bytes, n_vertices: int) -> Mutant:
    """One mutation of a text file, drawn with hypothesis's ``draw``."""
    lines = data.split(b"\n")  # a final newline leaves a last empty entry
    vertex, face, counts = layout(reader, lines)
    rows = vertex + face
    table = reader.kind in ("table", "names")
    ops = ["crlf", "trailing_blanks", "truncate_line", "truncate_byte", "overwrite", "empty", "letters"]
    if reader.comment:
        ops += ["comment", "non_utf8_comment"]
    if table:
        ops += ["bom", "big_int", "extra_column"]
        ops += ["commas", "header"] if reader.kind == "table" else []
    else:
        ops += ["nan_inf"]
    if face:
        ops += ["bad_index", "float_index"]
    if counts:
        ops += ["huge_count", "delete_line", "duplicate_line"] + (["swap_counts"] if len(counts) > 1 else [])
    op = draw(st.sampled_from(ops))
    if op == "crlf":
        return Mutant(data.replace(b"\n", b"\r\n"), "same", op)
    if op == "bom":
        return Mutant(b"\xef\xbb\xbf" + data, "same", op)
    if op == "trailing_blanks":
        return Mutant(data + b"\n  \n\t\n", "same", op)
    if op == "header":
        header = draw(st.sampled_from([b"source target", b"index", b"# map", b"vertex,id"]))
        return Mutant(header + b"\n" + data, "same", f"header {header!r}")
    if op == "commas":
        sep = draw(st.sampled_from([b",", b", ", b";", b"\t"]))
        return Mutant(_join([sep.join(ln.split()) for ln in lines]), "same", f"separator {sep!r}")
    if op in ("comment", "non_utf8_comment"):
        at = draw(st.integers(1, len(lines) - 1))
        text = b"# note" if op == "comment" else b"# caf\xe9 \xff\xfe"
        verdict = "refuse" if op == "non_utf8_comment" and table else "same"
        return Mutant(_join(lines[:at] + [text] + lines[at:]), verdict, f"{op} before line {at}")
    if op == "empty":
        return Mutant(draw(st.sampled_from([b"", b"\n", b"  \n\n", b"# nothing\n"])), "refuse", op)
    if op == "truncate_line":
        at = draw(st.integers(0, len(lines) - 1))
        kept, dropped = lines[:at], lines[at:]
        if all(_is_blank(ln, reader.comment) for ln in dropped):
            verdict = "same"
        else:
            verdict = "refuse" if reader.counted else "prefix"
        return Mutant(_join(kept) + (b"\n" if kept else b""), verdict, f"cut before line {at}")
    if op == "truncate_byte":
        at = draw(st.integers(0, len(data) - 1))
        cut = data[:at]
        line = cut.count(b"\n")
        later = lines[line + 1 :]
        if not cut.strip():
            verdict = "refuse"
        elif at == 0 or data[at - 1 : at] == b"\n":
            verdict = (
                "same"
                if all(_is_blank(ln, reader.comment) for ln in lines[line:])
                else ("refuse" if reader.counted else "prefix")
            )
        elif all(_is_blank(ln, reader.comment) for ln in later):
            verdict = "last_row" if line in rows else "intact"
        else:
            verdict = "refuse" if reader.counted else "last_row"
        return Mutant(cut, verdict, f"cut at byte {at} (line {line})")
    if op == "overwrite":
        at = draw(st.integers(0, len(data) - 1))
        junk = draw(st.binary(min_size=1, max_size=4))
        return Mutant(data[:at] + junk + data[at + len(junk) :], "valid", f"bytes {junk!r} at {at}")
    if op == "delete_line":
        at = draw(st.sampled_from(rows))
        return Mutant(_join(lines[:at] + lines[at + 1 :]), "refuse", f"line {at} deleted")
    if op == "duplicate_line":
        at = draw(st.sampled_from(rows))
        return Mutant(_join(lines[: at + 1] + lines[at:]), "refuse", f"line {at} doubled")
    if op == "swap_counts":
        (li, ti), (lj, tj) = counts[:2]
        new = list(lines)
        a, b = lines[li].split()[ti], lines[lj].split()[tj]
        new[li] = _replace_token(new[li], ti, b)
        new[lj] = _replace_token(new[lj], tj, a)
        return Mutant(_join(new), "refuse", "vertex and face counts swapped")
    if op == "huge_count":
        li, ti = draw(st.sampled_from(counts[:2]))
        value = draw(st.sampled_from([b"1000000000", b"99999999999999999999", b"-5", b"4294967296"]))
        new = list(lines)
        new[li] = _replace_token(new[li], ti, value)
        return Mutant(_join(new), "refuse", f"count {value!r} on line {li}")
    if op == "nan_inf":
        at = draw(st.sampled_from(vertex))
        value = draw(st.sampled_from([b"nan", b"inf", b"-inf", b"1e999", b"NaN"]))
        fields = lines[at].split()
        first = 1 if fields[0] in (b"v", b"vertex") else 0
        token = first + draw(st.integers(0, 2))
        new = list(lines)
        new[at] = _replace_token(lines[at], token, value)
        return Mutant(_join(new), "refuse", f"{value!r} in line {at}")
    if op in ("bad_index", "float_index"):
        at = draw(st.sampled_from(face))
        obj = lines[at].split()[0] == b"f"
        if op == "float_index":
            value = b"1.5"
        else:
            bad = [-(n_vertices + 1), 0, n_vertices + 1] if obj else [-1, n_vertices, n_vertices + 7]
            value = str(draw(st.sampled_from(bad + [10**12, 2**63]))).encode()
        new = list(lines)
        new[at] = _replace_token(lines[at], 1 + draw(st.integers(0, 2)), value)
        return Mutant(_join(new), "refuse", f"face index {value!r} in line {at}")
    if op == "letters":
        at = draw(st.sampled_from(rows))
        value = draw(st.sampled_from([b"12x", b"1e", b"0x1F", b"-", b"\xc2\xbd", b"1,5.2"]))
        new = list(lines)
        new[at] = _replace_token(lines[at], draw(st.integers(0, 3)), value)
        verdict = "valid" if reader.kind == "names" else "refuse"
        return Mutant(_join(new), verdict, f"{value!r} in line {at}")
    if op == "big_int":
        at = draw(st.sampled_from(rows))
        new = list(lines)
        new[at] = _replace_token(lines[at], 0, b"1" + b"0" * 30)
        return Mutant(_join(new), "valid" if reader.kind == "names" else "refuse", f"10**30 in line {at}")
    if op == "extra_column":
        at = draw(st.sampled_from(rows))
        new = list(lines)
        new[at] = lines[at] + b" 7"
        verdict = "valid" if reader.kind == "names" else "refuse"
        return Mutant(_join(new), verdict, f"a third column on line {at}")
    raise AssertionError(op)


def binary_mesh_mutant(draw, reader: Reader, data: bytes) -> Mutant:
    """One mutation of a binary PLY or STL file."""
    ply = data.startswith(b"ply")
    body = data.index(b"end_header\n") + len(b"end_header\n") if ply else 84
    op = draw(st.sampled_from(["truncate", "overwrite", "huge_count", "nan", "empty", "append"]))
    if op in ("truncate", "overwrite"):  # binary counts catch any cut, not a changed digit
        return _cut_or_overwrite(draw, data, op, "valid")
    if op == "empty":
        return Mutant(b"", "refuse", op)
    if op == "append":
        return Mutant(data + draw(st.binary(min_size=1, max_size=64)), "intact", "bytes appended")
    if op == "huge_count":
        if ply:
            value = draw(st.sampled_from([b"1000000000", b"99999999999999999999", b"-5"]))
            which = draw(st.sampled_from([b"element vertex ", b"element face "]))
            start = data.index(which) + len(which)
            end = data.index(b"\n", start)
            return Mutant(data[:start] + value + data[end:], "refuse", f"{which!r}{value!r}")
        value = draw(st.sampled_from([2**32 - 1, 10**6, 0]))
        return Mutant(data[:80] + np.uint32(value).tobytes() + data[84:], "refuse", f"count {value}")
    # a NaN or an infinity in a vertex coordinate (float32 in both files)
    value = np.float32(draw(st.sampled_from([np.nan, np.inf, -np.inf]))).tobytes()
    i = draw(st.integers(0, 20))
    if ply:
        at = body + 12 * i + 4 * draw(st.integers(0, 2))
    else:
        at = 84 + 50 * i + 12 + 4 * draw(st.integers(0, 8))
    return Mutant(data[:at] + value + data[at + 4 :], "refuse", f"{value!r} at byte {at}")


def _cut_or_overwrite(draw, data: bytes, op: str, overwritten: str) -> Mutant:
    """``data`` cut at a drawn byte (verdict ``refuse``) or with 1-4 drawn bytes written over it
    (verdict ``overwritten``, or ``intact`` when the bytes happen to be the same)."""
    at = draw(st.integers(0, len(data) - 1))
    if op == "truncate":
        return Mutant(data[:at], "refuse", f"cut at byte {at}")
    junk = draw(st.binary(min_size=1, max_size=4))
    mutated = data[:at] + junk + data[at + len(junk) :]
    return Mutant(mutated, overwritten if mutated != data else "intact", f"bytes {junk!r} at {at}")


def _reseal(payload: bytes) -> bytes:
    """A checksummed file around ``payload`` (a file that passes the checksum but holds other
    content: the checksum guards against accidents, the readers must still check what they read)."""
    import hashlib

    from torchfmap._util.files import CHECKED_MAGIC

    return CHECKED_MAGIC + hashlib.sha256(payload).hexdigest().encode() + b"\n" + payload


class _RunsCode:
    """Unpickling this would create the marker file: a file that can run code."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (Path(self.marker),))


def checkpoint_mutant(draw, data: bytes, marker: Path) -> Mutant:
    import torch

    op = draw(st.sampled_from(["truncate", "overwrite", "reseal_bytes", "reseal_pickle", "foreign", "edit"]))
    if op in ("truncate", "overwrite"):  # the checksum sees any change
        return _cut_or_overwrite(draw, data, op, "refuse")
    if op == "reseal_bytes":
        return Mutant(_reseal(draw(st.binary(max_size=256))), "refuse", "random payload, valid checksum")
    if op == "reseal_pickle":
        payload = pickle.dumps({"state_dict": _RunsCode(str(marker)), "config": {}})
        return Mutant(_reseal(payload), "refuse", "a pickle that runs code, valid checksum")
    buffer = io.BytesIO()
    if op == "foreign":
        torch.save({"model": torch.nn.Linear(2, 2).state_dict()}, buffer)
        return Mutant(buffer.getvalue(), "refuse", "another project's torch.save")
    from torchfmap.nn.checkpoints import read_checkpoint

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "c.pt"
        path.write_bytes(data)
        ckpt = read_checkpoint(path)
    edit = draw(st.sampled_from([
        "drop state_dict", "drop config", "drop network", "state_dict list", "config text",
        "config unknown key", "config bad value", "class os:system", "kwargs bogus", "weight resized",
        "weight nan", "network text",
    ]))  # fmt: skip
    name = next(iter(ckpt["state_dict"]))
    if edit.startswith("drop "):
        ckpt.pop(edit[5:])
    elif edit == "state_dict list":
        ckpt["state_dict"] = list(ckpt["state_dict"].values())
    elif edit == "config text":
        ckpt["config"] = "k=8"
    elif edit == "config unknown key":
        ckpt["config"]["bogus"] = 1
    elif edit == "config bad value":
        ckpt["config"]["k"] = -3
    elif edit == "class os:system":
        ckpt["network"]["class"] = "os:system"
    elif edit == "kwargs bogus":
        ckpt["network"]["kwargs"] = {"bogus": 1}
    elif edit == "weight resized":
        ckpt["state_dict"][name] = torch.zeros(3, 3)
    elif edit == "weight nan":
        ckpt["state_dict"][name] = torch.full_like(ckpt["state_dict"][name], float("nan"))
    elif edit == "network text":
        ckpt["network"] = "DiffusionNet"
    torch.save(ckpt, buffer)
    return Mutant(_reseal(buffer.getvalue()), "refuse", f"valid checksum, {edit}")


def arrays_mutant(draw, reader: Reader, data: bytes) -> Mutant:
    """Mutations of checksummed ``.npz`` files (bases, cache entries)."""
    from torchfmap._util.files import CHECKSUM_KEY, load_arrays, save_arrays
    from torchfmap.nn.data import CACHE_CHECKSUM_KEY

    key = CACHE_CHECKSUM_KEY if reader.kind == "cache" else CHECKSUM_KEY
    ops = ["truncate", "overwrite", "empty", "not_zip"] + (["edit"] if reader.kind == "checked" else [])
    op = draw(st.sampled_from(ops))
    if op in ("truncate", "overwrite"):
        # a byte of the zip's padding or an unused header field may change nothing that is read
        return _cut_or_overwrite(draw, data, op, "intact")
    if op == "empty":
        return Mutant(b"", "refuse", op)
    if op == "not_zip":
        return Mutant(draw(st.binary(min_size=1, max_size=128)), "refuse", "random bytes")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "b.npz"
        path.write_bytes(data)
        arrays = load_arrays(path, key)
        edit = draw(st.sampled_from([
            "drop values", "drop mass_data", "drop prov_kind", "values nan", "values 1-D", "mass index",
            "prov short", "mass_data short", "values object", "version",
        ]))  # fmt: skip
        if edit.startswith("drop "):
            arrays.pop(edit[5:])
        elif edit == "values nan":
            arrays["values"] = arrays["values"].copy()
            arrays["values"][draw(st.integers(0, 41)), 0] = np.nan
        elif edit == "values 1-D":
            arrays["values"] = arrays["values"][:, 0]
        elif edit == "mass index":
            arrays["mass_row"] = arrays["mass_row"].copy()
            arrays["mass_row"][0] = draw(st.sampled_from([-1, 42, 10**9]))
        elif edit == "prov short":
            arrays["prov_seed"] = arrays["prov_seed"][:-1]
        elif edit == "mass_data short":
            arrays["mass_data"] = arrays["mass_data"][:-1]
        elif edit == "values object":
            arrays["values"] = arrays["values"].astype(str)
        elif edit == "version":
            arrays["version"] = np.array(99)
        path.unlink()
        save_arrays(path, arrays, key)
        return Mutant(path.read_bytes(), "refuse", f"valid checksum, {edit}")


# -- the property --------------------------------------------------------------------------------
class _Hang(Exception):
    pass


def _alarm(signum, frame):
    raise _Hang


def _rows(result) -> list:
    """A result as a list of comparable rows."""
    if hasattr(result, "faces"):
        rows = [("v", tuple(r)) for r in result.vertices.tolist()]
        return rows + [("f", tuple(r)) for r in result.faces.tolist()]
    if isinstance(result, np.ndarray):
        return [tuple(np.atleast_1d(r).tolist()) for r in result]
    return list(result)


def _split(result) -> tuple[list, list]:
    rows = _rows(result)
    return [r for r in rows if r[0] != "f"], [r for r in rows if r[0] == "f"]


def _prefix(got: list, want: list, last_changed: bool) -> bool:
    if len(got) > len(want):
        return False
    body = got[:-1] if last_changed and got else got
    return body == want[: len(body)]


def _well_formed(reader: Reader, result) -> bool:
    if hasattr(result, "faces"):
        v, f = result.vertices, result.faces
        return bool(np.isfinite(v).all() and len(v) and f.min() >= 0 and f.max() < len(v))
    if reader.kind == "points":
        return result.ndim == 2 and result.shape[1] == 3 and bool(np.isfinite(result).all())
    if reader.kind == "names":
        return all(isinstance(a, str) and isinstance(b, str) for a, b in result)
    return isinstance(result, np.ndarray) and result.dtype == np.int64 and len(result) > 0


def judge(reader: Reader, path: Path, mutant: Mutant, expected) -> str:
    """Read ``path`` (holding ``mutant``) and check the result against the verdict; returns
    ``'loaded'`` or ``'refused'``, raises ``AssertionError`` when the property fails."""
    where = f"{reader.name}, {mutant.what} (verdict {mutant.verdict})"
    previous = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, TIME_LIMIT)
    try:
        result = reader.read(path)
    except _Hang:
        raise AssertionError(f"{where}: no answer within {TIME_LIMIT} s") from None
    except TorchFmapError as err:
        if path.name not in str(err):
            raise AssertionError(f"{where}: the error does not name the file: {err}") from None
        if mutant.verdict == "same":
            raise AssertionError(f"{where}: a file that means the same was refused: {err}") from None
        return "refused"
    except Exception as err:
        raise AssertionError(f"{where}: {type(err).__name__} instead of a torchfmap error: {err}") from err
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    if reader.kind == "cache":  # an unusable entry reads as None: rebuilt, never used
        if result is None:
            return "refused"
        if mutant.verdict in ("refuse", "intact", "same") and set(result) != set(expected):
            raise AssertionError(f"{where}: an altered cache entry was used")
        return "loaded"
    if mutant.verdict == "refuse":
        raise AssertionError(f"{where}: loaded instead of refused: {_rows(result)[:3]} ...")
    if reader.kind in ("checked",):
        return "loaded"
    if mutant.verdict in ("same", "intact"):
        if _rows(result) != _rows(expected):
            raise AssertionError(f"{where}: loaded a different result from a file that means the same")
    elif mutant.verdict in ("prefix", "last_row"):
        last = mutant.verdict == "last_row"
        (gv, gf), (wv, wf) = _split(result), _split(expected)
        if not (_prefix(gv, wv, last) and _prefix(gf, wf, last)):
            raise AssertionError(f"{where}: loaded rows that are not the file's first rows")
    if not _well_formed(reader, result):
        raise AssertionError(f"{where}: loaded a malformed result")
    return "loaded"


def check(name: str, examples: int, tally: Counter | None = None, seed: int = 0) -> Counter:
    """Run ``examples`` mutations of reader ``name``'s valid file (derandomised from ``seed``);
    returns the tally of outcomes (``loaded`` / ``refused`` per verdict, ``slowest_ms``). Raises
    ``AssertionError`` (with hypothesis's smallest failing example) when the property fails."""
    reader = readers()[name]
    original = reader.make()
    tally = Counter() if tally is None else tally
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        path = folder / f"shape{reader.suffix}"
        path.write_bytes(gzip.compress(original, mtime=0) if reader.suffix.endswith(".gz") else original)
        expected = reader.read(path)
        marker = folder / "code-ran"
        n_vertices = len(seed_mesh().vertices)

        @settings(
            max_examples=examples, deadline=None, derandomize=True, database=None, print_blob=False,
            suppress_health_check=list(HealthCheck),
        )  # fmt: skip
        @given(st.data())
        def run(data):
            draw = data.draw
            if reader.kind in ("mesh", "table", "names", "points"):
                mutant = text_mutant(draw, reader, original, n_vertices)
            elif reader.kind == "binary_mesh":
                mutant = binary_mesh_mutant(draw, reader, original)
            elif reader.name == "checkpoint":
                mutant = checkpoint_mutant(draw, original, marker)
            else:
                mutant = arrays_mutant(draw, reader, original)
            payload = mutant.data
            if reader.suffix.endswith(".gz"):
                payload = gzip.compress(payload, mtime=0)
                if draw(st.booleans()) and len(payload) > 1:  # the gzip stream itself cut
                    payload = payload[: draw(st.integers(0, len(payload) - 1))]
                    mutant = Mutant(mutant.data, "refuse", mutant.what + ", gzip stream cut")
            path.write_bytes(payload)
            start = time.perf_counter()
            outcome = judge(reader, path, mutant, expected)
            tally["slowest_ms"] = max(tally["slowest_ms"], round(1000 * (time.perf_counter() - start)))
            tally[f"{outcome} ({mutant.verdict})"] += 1
            tally["examples"] += 1
            if marker.exists():
                raise AssertionError(f"{reader.name}, {mutant.what}: the file ran code")

        _ = seed  # one derandomised sequence per reader; more examples explore further
        run()
    return tally


# -- the bench case ------------------------------------------------------------------------------
def fuzz_case(cfg, report) -> None:
    """Does every reader load what a mutated file allows or refuse it naming the file (never
    another exception, a hang or a silently changed result)? Outcomes per reader and verdict."""
    import logging

    from .common import log

    names = list(readers()) if cfg.readers == "all" else [n.strip() for n in cfg.readers.split(",")]
    rows = []
    cache_log = logging.getLogger("torchfmap.nn.data")
    level = cache_log.level
    cache_log.setLevel(logging.ERROR)  # an unusable cache entry is logged before it is rebuilt
    try:
        for name in names:
            log(f"fuzz {name}: {cfg.examples} examples")
            start = time.perf_counter()
            try:
                tally, failure = check(name, cfg.examples), ""
            except Exception as err:  # AssertionError, or a group of them (several distinct failures)
                found = getattr(err, "exceptions", [err])
                tally, failure = Counter(), " / ".join(str(e).splitlines()[0][:160] for e in found)
            loaded = sum(v for k, v in tally.items() if k.startswith("loaded"))
            refused = sum(v for k, v in tally.items() if k.startswith("refused"))
            verdicts = Counter()
            for key, value in tally.items():
                if key.startswith(("loaded", "refused")):
                    verdicts[key.split("(")[1].rstrip(")")] += value
            rows.append({
                "method": name, "examples": tally["examples"], "loaded": loaded, "refused": refused,
                "mutations by verdict": ", ".join(f"{k} {v}" for k, v in sorted(verdicts.items())),
                "slowest [ms]": tally["slowest_ms"], "seconds": round(time.perf_counter() - start, 1),
                "property": failure or "holds",
            })  # fmt: skip
    finally:
        cache_log.setLevel(level)
    report.table(
        "Readers under mutation",
        rows,
        note=(
            "Verdicts (bench/fuzz.py): same = must load the original; refuse = must raise a torchfmap "
            "error naming the file; prefix / last_row = an error or the original's first rows (a cut "
            "the format cannot detect); valid = an error or a well-formed result; intact = an error or "
            "the original. 'property' is 'holds' or hypothesis's smallest failing example."
        ),
    )
    report.rows_csv(rows)


CASES = {"fuzz": fuzz_case}
