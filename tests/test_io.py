"""Loading keeps the file's vertex order for every format (round trip against the raw file); one
suffix rule (``.gz`` everywhere) for every reader, writer and folder listing; bad files are
named (truncated, 1-based, not STL, point clouds, non-manifold)."""

from __future__ import annotations

import gzip

import numpy as np
import pytest

from torchfmap import MeshError, MeshWarning, ParameterError, TorchFmapError, load_mesh, save_mesh
from torchfmap.bases.prepared import prepare_shape
from torchfmap.data import icosphere
from torchfmap.io import (
    find_file,
    is_mesh_file,
    load_points,
    mesh_files,
    read_index_table,
    read_landmark_pairs,
    read_landmarks,
    read_map,
    read_test_pairs,
    read_text,
    read_vts,
    shape_name,
    split_suffix,
    write_map,
)
from torchfmap.mesh import Mesh
from torchfmap.operators import laplacian

from .conftest import bumpy_blob, data_path, smallest_eigenvalues, with_fin


@pytest.fixture(scope="module")
def shuffled():
    """A sphere whose vertex order is random, so any reordering by a loader shows."""
    m = icosphere(2)
    return m.permuted(np.random.default_rng(7).permutation(m.n_vertices))


@pytest.mark.parametrize("ext", [".off", ".obj", ".ply", ".off.gz", ".obj.gz", ".ply.gz"])
def test_round_trip_keeps_order(tmp_path, shuffled, ext):
    path = save_mesh(shuffled, tmp_path / f"mesh{ext}")
    loaded = load_mesh(path)
    assert np.allclose(loaded.vertices, shuffled.vertices, atol=1e-7)
    assert np.array_equal(loaded.faces, shuffled.faces)


def raw_obj(path):
    v, f = [], []
    for ln in path.read_text().splitlines():
        parts = ln.split()
        if parts and parts[0] == "v":
            v.append(list(map(float, parts[1:4])))
        elif parts and parts[0] == "f":
            idx = [int(p.split("/")[0]) - 1 for p in parts[1:]]
            f.extend([idx[0], idx[i], idx[i + 1]] for i in range(1, len(idx) - 1))
    return np.array(v), np.array(f)


def raw_off(path):
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    nv, nf = map(int, lines[1].split()[:2])
    v = np.array([list(map(float, ln.split()[:3])) for ln in lines[2 : 2 + nv]])
    f = np.array([list(map(int, ln.split()[1:4])) for ln in lines[2 + nv : 2 + nv + nf]])
    return v, f


@pytest.mark.parametrize("ext", [".off", ".obj"])
def test_against_raw_text(tmp_path, shuffled, ext):
    path = save_mesh(shuffled, tmp_path / f"mesh{ext}")
    v, f = (raw_off if ext == ".off" else raw_obj)(path)
    loaded = load_mesh(path)
    assert np.allclose(loaded.vertices, v, atol=1e-12)
    assert np.array_equal(loaded.faces, f)


def test_obj_with_texture_indices_and_quads(tmp_path):
    """vt/vn indices that differ from v indices must not split or reorder vertices."""
    text = """# hand written
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0.5 0.5 1
vt 0.1 0.1
vt 0.9 0.9
vn 0 0 1
f 4/1/1 3/2/1 2/1/1 1/2/1
f 1/2/1 2/1/1 5/1/1
f 2/1/1 3/2/1 5/2/1
f 3/1/1 4/1/1 5/2/1
f 4/2/1 1/1/1 5/1/1
"""
    path = tmp_path / "pyramid.obj"
    path.write_text(text)
    v, f = raw_obj(path)
    mesh = load_mesh(path)
    assert np.allclose(mesh.vertices, v)
    assert mesh.n_vertices == 5 and mesh.n_faces == 6
    # same triangles up to the split diagonal of the quad
    assert set(map(tuple, np.sort(mesh.faces[2:], axis=1))) == set(map(tuple, np.sort(f[2:], axis=1)))


def test_obj_keeps_a_vertex_no_face_uses_and_reads_relative_corners(tmp_path):
    """A vertex no face references stays at its index (trimesh drops it, which renumbers every
    later vertex and so breaks ground truth); negative corners count back from the last vertex."""
    path = tmp_path / "tri.obj"
    path.write_text("v 0 0 0\nv 9 9 9\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\n")
    with pytest.raises(MeshError, match="not used by any face.*allow_unreferenced"):
        load_mesh(path)
    mesh = load_mesh(path, allow_unreferenced=True)
    assert mesh.vertices.tolist() == [[0, 0, 0], [9, 9, 9], [1, 0, 0], [0, 1, 0]]
    assert mesh.faces.tolist() == [[1, 2, 3]]
    path.write_text("v 0 0 0\nv 1 0 0\nf 1 2 3\nv 0 1 0\n")  # a corner defined after its face
    with pytest.raises(MeshError, match=r"tri\.obj':3: .*outside the 2 defined"):
        load_mesh(path)


def test_ply_binary_and_ascii(tmp_path, shuffled):
    for encoding in ("binary", "ascii"):
        data = shuffled.to_trimesh().export(file_type="ply", encoding=encoding)
        path = tmp_path / f"m_{encoding}.ply"
        path.write_bytes(data if isinstance(data, bytes) else data.encode())
        mesh = load_mesh(path)
        assert np.allclose(mesh.vertices, shuffled.vertices) and np.array_equal(mesh.faces, shuffled.faces)


def test_stl_merges_in_first_appearance_order(tmp_path, shuffled):
    path = tmp_path / "m.stl"
    path.write_bytes(shuffled.to_trimesh().export(file_type="stl"))
    mesh = load_mesh(path)
    corners = shuffled.vertices[shuffled.faces].reshape(-1, 3).astype(np.float32).astype(np.float64)
    _, first = np.unique(corners, axis=0, return_index=True)
    expected = corners[np.sort(first)]
    assert mesh.n_vertices == shuffled.n_vertices
    assert np.array_equal(mesh.vertices, expected)
    assert np.allclose(mesh.vertices[mesh.faces], shuffled.vertices[shuffled.faces], atol=1e-6)


def test_gzip_off_matches_plain(tmp_path):
    plain = data_path("tosca5k_dev", "cat0.off")
    gz = tmp_path / "cat0.off.gz"
    gz.write_bytes(gzip.compress(plain.read_bytes()))
    a, b = load_mesh(plain), load_mesh(gz)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    v, f = raw_off(plain)
    assert np.allclose(a.vertices, v, rtol=0, atol=1e-9) and np.array_equal(a.faces, f)


def test_bad_paths(tmp_path):
    with pytest.raises(MeshError, match="does not exist"):
        load_mesh(tmp_path / "nope.off")
    (tmp_path / "x.xyz").write_text("1 2 3")
    with pytest.raises(MeshError, match="unsupported extension '.xyz'"):
        load_mesh(tmp_path / "x.xyz")
    (tmp_path / "broken.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n")
    with pytest.raises(MeshError):
        load_mesh(tmp_path / "broken.off")


def test_save_is_atomic(tmp_path, shuffled):
    path = tmp_path / "m.off"
    save_mesh(shuffled, path)
    assert [p.name for p in tmp_path.iterdir()] == ["m.off"]  # no temp file left behind


def test_one_suffix_rule_and_mesh_listing(tmp_path):
    assert split_suffix("a/cat0.OFF.gz") == ("off", True) and split_suffix("m.txt") == ("txt", False)
    assert split_suffix("lion2cat") == ("", False) and split_suffix("x.gz") == ("", True)
    assert is_mesh_file("cat.ply.gz") and is_mesh_file("cat.STL") and not is_mesh_file("cat.vts.gz")
    assert shape_name("dir/cat0.off.gz") == "cat0"
    for name in ("b.off", "a.OBJ.gz", "c.txt", "d.vts.gz", ".b.off.123.tmp"):
        (tmp_path / name).write_text("")
    (tmp_path / "e.off").mkdir()  # a folder is not a mesh file
    assert [f.name for f in mesh_files(tmp_path)] == ["a.OBJ.gz", "b.off"]
    with pytest.raises(ParameterError, match="not a folder"):
        mesh_files(tmp_path / "b.off")
    assert find_file(tmp_path, "d.vts") == tmp_path / "d.vts.gz" and find_file(tmp_path, "z.vts") is None


READERS = [
    (read_map, "2\n0\n1\n", [2, 0, 1]),
    (read_vts, "3 7\n1 2\n", [2, 0]),
    (read_landmarks, "\ufeff# two\n4\n\n5  # end\n", [4, 5]),
    (read_landmark_pairs, "1 2\n3 4\n", [[1, 2], [3, 4]]),
    (read_test_pairs, "cat0\tcat1\n\nwolf0 wolf1 extra\n", [("cat0", "cat1"), ("wolf0", "wolf1")]),
    (lambda path: read_index_table(path, None, "table"), "1 2 3\n4 5 6\n", [[1, 2, 3], [4, 5, 6]]),
]


@pytest.mark.parametrize(("reader", "text", "expected"), READERS)
def test_every_reader_accepts_gz_the_same_way(tmp_path, reader, text, expected):
    plain, packed = tmp_path / "f.txt", tmp_path / "f.txt.gz"
    plain.write_bytes(text.encode())
    packed.write_bytes(gzip.compress(text.encode()))
    got_plain, got_packed = reader(plain), reader(packed)
    assert np.asarray(got_plain).tolist() == np.asarray(got_packed).tolist() == np.asarray(expected).tolist()


def test_write_map_round_trips_plain_and_gz(tmp_path):
    p2p = np.array([3, 0, 2, 2, 1])
    for name in ("m.txt", "m.txt.gz"):
        path = write_map(tmp_path / name, p2p)
        np.testing.assert_array_equal(read_map(path), p2p)
    assert gzip.decompress((tmp_path / "m.txt.gz").read_bytes()) == (tmp_path / "m.txt").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.txt", "m.txt.gz"]  # atomic: no temp files
    with pytest.raises(ParameterError, match="1-D integer"):
        write_map(tmp_path / "bad.txt", np.zeros((2, 2)))


def test_index_files_name_the_problem(tmp_path):
    bad = tmp_path / "lm.txt.gz"
    bad.write_text("1\n2\n")  # named .gz but not gzip data
    with pytest.raises(TorchFmapError, match="gzip"):
        read_landmarks(bad)
    with pytest.raises(TorchFmapError, match="cannot read the point map file"):
        read_map(tmp_path / "missing.txt")
    (tmp_path / "m.txt").write_text("1\n2 3\n")
    with pytest.raises(TorchFmapError, match=r"m.txt:2: expected 1 integer column"):
        read_map(tmp_path / "m.txt")
    (tmp_path / "v.vts").write_text("3\n1.5\n")
    with pytest.raises(TorchFmapError, match=r"v.vts:2: '1.5' is not 1 integer vertex index"):
        read_vts(tmp_path / "v.vts")
    (tmp_path / "pairs.txt").write_text("cat0 cat1\ncat2\n")
    with pytest.raises(TorchFmapError, match=r"pairs.txt:2: a test pair needs two shape names"):
        read_test_pairs(tmp_path / "pairs.txt")
    (tmp_path / "latin.txt").write_bytes(b"1\n\xe9\n")
    with pytest.raises(TorchFmapError, match="not UTF-8"):
        read_text(tmp_path / "latin.txt", "landmark")


def test_landmark_files_as_users_write_them(tmp_path):
    """A header line, commas (CSV) and semicolons are read; a word after the first line and a
    comma-separated file of the wrong width are refused naming the line and how to write it."""
    for text in ("source,target\n1,2\n3,4\n", "x y # header\n1 2\n3 4\n", "1;2\n3;4\n", "1, 2\n3 ,4\n"):
        (tmp_path / "lm.txt").write_text(text)
        np.testing.assert_array_equal(read_landmark_pairs(tmp_path / "lm.txt"), [[1, 2], [3, 4]])
    (tmp_path / "lm.txt").write_text("1 2\nfive six\n")
    with pytest.raises(TorchFmapError, match=r"lm.txt:2: 'five six' is not 2 integer.*only the first line"):
        read_landmark_pairs(tmp_path / "lm.txt")
    (tmp_path / "lm.txt").write_text("1,2\n3,4\n")
    with pytest.raises(TorchFmapError, match=r"expected 1 integer column\(s\) per line \(landmark\), got 2"):
        read_landmarks(tmp_path / "lm.txt")


def test_an_empty_mesh_file_says_so(tmp_path):
    for name in ("empty.off", "blank.obj", "empty.ply"):
        (tmp_path / name).write_text("" if name != "blank.obj" else "\n \n")
        with pytest.raises(MeshError, match=rf"'{name}' is empty .*Fix: copy or export"):
            load_mesh(tmp_path / name)


def test_one_based_off_faces_are_named_as_such(tmp_path):
    path = tmp_path / "one_based.off"
    path.write_text("OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 1 2 3\n3 1 2 4\n3 1 3 4\n3 2 3 4\n")
    with pytest.raises(MeshError, match=r"1-based face indices: every index is in 1\.\.4 and none is 0"):
        load_mesh(path)
    path.write_text("OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n3 0 1 9\n")
    with pytest.raises(MeshError, match="face index 9, outside the 4 vertices"):
        load_mesh(path)


def _off_text(mesh) -> str:
    lines = ["OFF", f"{mesh.n_vertices} {mesh.n_faces} 0"]
    lines += [" ".join(f"{c:.9g}" for c in v) for v in mesh.vertices]
    lines += ["3 " + " ".join(str(i) for i in f) for f in mesh.faces]
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("cut", [1, 5, 200])
def test_truncated_off_is_refused_naming_the_counts(tmp_path, sphere2, cut):
    """A file missing its last face lines used to load with a new hole (or an
    'allow_unreferenced' hint): the header's counts are now checked."""
    from torchfmap import MeshError, load_mesh

    text = _off_text(sphere2).splitlines()
    path = tmp_path / "cut.off"
    path.write_text("\n".join(text[:-cut]) + "\n")
    with pytest.raises(MeshError, match=r"truncated.*declares 162 vertices and 320 faces.*Fix"):
        load_mesh(path)


def test_off_with_latin1_comment_loads(tmp_path, sphere2):
    """A non-UTF-8 byte in a comment used to need an undeclared charset detector."""
    from torchfmap import load_mesh

    path = tmp_path / "latin.off"
    text = _off_text(sphere2).replace("OFF\n", "OFF\n# caf\xe9 (Latin-1)\n", 1)
    path.write_bytes(text.encode("latin-1"))
    np.testing.assert_allclose(load_mesh(path).vertices, sphere2.vertices, rtol=1e-8)


def test_mesh_errors_name_the_file_and_folders_are_refused(tmp_path, sphere2):
    from torchfmap import MeshError, load_mesh

    bad = sphere2.vertices.copy()
    path = tmp_path / "nan.off"
    path.write_text(_off_text(sphere2.copy(bad)).replace(_off_text(sphere2).splitlines()[2], "nan 0 0", 1))
    with pytest.raises(MeshError, match=r"nan\.off.*NaN"):
        load_mesh(path)
    with pytest.raises(MeshError, match="is a folder"):
        load_mesh(tmp_path)


def test_zero_based_vts_is_refused(tmp_path):
    from torchfmap.io import read_vts

    path = tmp_path / "a.vts"
    np.savetxt(path, [0, 4, 7], fmt="%d")
    with pytest.raises(ParameterError, match="1-based"):
        read_vts(path)


def test_landmark_file_with_bom_and_comments_is_read(tmp_path):
    from torchfmap.io import read_landmark_pairs

    lm = tmp_path / "lm.txt"
    lm.write_bytes("\ufeff# pairs\n1 2\n\n3 4  # a comment\n".encode())
    np.testing.assert_array_equal(read_landmark_pairs(str(lm)), [[1, 2], [3, 4]])


def test_off_face_line_with_two_indices_is_refused(tmp_path):
    from torchfmap import load_mesh

    path = tmp_path / "t.off"
    path.write_text("OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n2 0 1\n")
    with pytest.raises(MeshError, match="fewer than 3 corners: '2 0 1'"):
        load_mesh(path)


def test_point_cloud_ply_is_named_and_readable_end_to_end(tmp_path):
    import trimesh

    from torchfmap import load_mesh, load_points
    from torchfmap.operators import laplacian

    points = bumpy_blob(2).vertices
    path = tmp_path / "cloud.ply"
    trimesh.PointCloud(points).export(path)
    with pytest.raises(MeshError, match=r"and no faces: a point cloud.*mesh it first.*load_points"):
        load_mesh(path)
    loaded = load_points(path)
    np.testing.assert_allclose(loaded, points)
    ops = laplacian(loaded, scheme="robust")
    assert ops.stiffness.shape == (162, 162)


def test_garbage_named_stl_is_reported_as_not_stl(tmp_path):
    from torchfmap import load_mesh

    path = tmp_path / "junk.stl"
    path.write_bytes(np.random.default_rng(0).bytes(3000))
    with pytest.raises(MeshError, match="is not an STL file"):
        load_mesh(path)


def test_nonmanifold_file_loads_with_a_warning_and_robust_operators(tmp_path):
    base = bumpy_blob(2)
    v, f = with_fin(base)
    path = tmp_path / "fin.off"
    with pytest.warns(MeshWarning, match="non-manifold"):
        mesh = Mesh(v, f, allow_nonmanifold="warn")
    save_mesh(mesh, path)
    with pytest.warns(MeshWarning, match="1 non-manifold edges"):
        loaded = load_mesh(path)
    assert loaded.n_nonmanifold_edges == 1 and loaded.report.n_nonmanifold_edges == 1
    with pytest.raises(MeshError, match="non-manifold"):
        load_mesh(path, allow_nonmanifold=False)
    shape = prepare_shape(loaded, 6)
    L_robust, _ = laplacian(loaded.scaled(shape.scale), scheme="robust")
    assert abs(shape.operators[0] - L_robust).max() == 0
    # the tufted Laplacian stays positive semidefinite with one zero eigenvalue per component
    lam = smallest_eigenvalues(*shape.operators, 3)
    assert abs(lam[0]) < 1e-8 and lam[1] > 1e-6
    # a manifold mesh keeps the cotangent Laplacian
    assert prepare_shape(base, 0).operators[0].nnz == laplacian(base.scaled(1 / np.sqrt(base.area)))[0].nnz


# -- what the fuzz suite (tests/test_fuzz.py) found, one regression test each ---------------------
def test_off_comments_between_rows_load_and_added_or_shifted_lines_are_refused(tmp_path, sphere2):
    """A comment after the counts made trimesh's OFF reader fail; inline counts ('OFF V F 0')
    skipped the truncation check; a doubled line was silently dropped or shifted rows."""
    lines = _off_text(sphere2).splitlines()
    path = tmp_path / "m.off"
    path.write_text("\n".join(lines[:5] + ["# a comment between vertices"] + lines[5:]) + "\n")
    np.testing.assert_array_equal(load_mesh(path).faces, sphere2.faces)
    inline = [f"OFF {lines[1]}"] + lines[2:]
    path.write_text("\n".join(inline[:3] + inline[4:]) + "\n")  # one vertex line missing
    with pytest.raises(MeshError, match="truncated"):
        load_mesh(path)
    path.write_text("\n".join(lines + [lines[-1]]) + "\n")  # the last face doubled
    with pytest.raises(MeshError, match="lines were added, doubled"):
        load_mesh(path)
    counts = lines[1].split()
    swapped = [lines[0], f"{counts[1]} {counts[0]} 0"] + lines[2:]  # faces read as vertices
    path.write_text("\n".join(swapped) + "\n")
    with pytest.raises(MeshError, match="vertex lines hold"):
        load_points(path)


def test_ascii_ply_rows_must_fit_the_header(tmp_path, sphere2):
    """trimesh reads ASCII PLY numbers as one stream: a missing vertex line shifted every later
    row, a non-integer face index was truncated."""
    text = sphere2.to_trimesh().export(file_type="ply", encoding="ascii")
    text = text.decode() if isinstance(text, bytes) else text
    lines = text.splitlines()
    body = lines.index("end_header") + 1
    path = tmp_path / "m.ply"
    path.write_text("\n".join(lines[:body] + lines[body + 1 :]) + "\n")
    with pytest.raises(MeshError, match=r"m\.ply.*declares 162 vertex, 320 face.*holds 481 lines"):
        load_mesh(path)
    face = lines[-1].split()
    lines[-1] = " ".join(face[:2] + ["1.5"] + face[3:])
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(MeshError, match="does not fit the header's face element"):
        load_mesh(path)


def test_damaged_obj_lines_are_refused(tmp_path, sphere2):
    """A damaged statement ('12x 3 4' for 'f 2 3 4') or vertex ('v 0.1 12x 0') used to load
    without that face or with a changed vertex."""
    text = sphere2.to_trimesh().export(file_type="obj")
    lines = text.splitlines()
    path = tmp_path / "m.obj"
    at = next(i for i, ln in enumerate(lines) if ln.startswith("f "))
    path.write_text("\n".join(lines[:at] + ["12x" + lines[at][1:]] + lines[at + 1 :]) + "\n")
    with pytest.raises(MeshError, match=r"m\.obj':\d+: .*no OBJ statement"):
        load_mesh(path)
    at = next(i for i, ln in enumerate(lines) if ln.startswith("v "))
    path.write_text("\n".join(lines[:at] + ["v 0.1 12x 0"] + lines[at + 1 :]) + "\n")
    with pytest.raises(MeshError, match="is not an OBJ vertex"):
        load_mesh(path)


def test_a_damaged_first_entry_is_no_header(tmp_path):
    """'12x' on the first line was taken for a header and dropped: the landmarks lost one."""
    path = tmp_path / "l.txt"
    path.write_text("12x\n17\n29\n")
    with pytest.raises(TorchFmapError, match=r"l\.txt:1: '12x' is not"):
        read_landmarks(path)
    path.write_text("source,target\n3,5\n")
    np.testing.assert_array_equal(read_landmark_pairs(path), [[3, 5]])
