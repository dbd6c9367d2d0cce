"""Bad input gets a clear error naming the problem and the fix, never a hang or a silent wrong answer."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, basis_stack, diffusion_basis, heat_kernels, laplacian
from torchfmap.cli import main
from torchfmap.data import icosphere
from torchfmap.seeds import coverage_seeds

BAD_TOLERANCES = [0.0, -1.0, float("nan"), float("inf"), 2.0, 1.0, 1e-20]


@pytest.fixture(scope="module")
def sphere():
    return icosphere(2)


@pytest.mark.parametrize("tol", BAD_TOLERANCES)
def test_heat_tolerance_out_of_range_is_refused(sphere, tol):
    """tol <= 0 or NaN used to loop for ever growing local patches; tol >= 1 returned kernels
    that were mostly wrong; tol=0 divided by zero. Each is now refused before any work."""
    ops = laplacian(sphere)
    with pytest.raises(ParameterError, match=r"tol must be a relative accuracy.*Fix"):
        heat_kernels(ops, [0, 5], [1e-3], tol=tol, local=True, vertices=sphere.vertices)
    with pytest.raises(ParameterError, match="tol must be"):
        diffusion_basis(sphere, [0, 5], [1e-3], tol=tol)
    with pytest.raises(ParameterError, match="tol must be"):
        basis_stack(sphere, [0, 5], times=[1e-3], heat_tol=tol)


def test_heat_tolerance_in_range_is_accepted(sphere):
    """The bounds are inclusive at the bottom: the most demanding accepted tolerance still works."""
    K = heat_kernels(laplacian(sphere), [0], [1e-2], tol=1e-14)
    assert np.isfinite(K).all()


def test_cli_basis_larger_than_the_mesh_is_a_clear_error(tmp_path, sphere, capsys):
    from torchfmap import save_mesh

    path = save_mesh(sphere, tmp_path / "s.off")
    out = str(tmp_path / "b.npz")
    code = main(["basis", str(path), "--basis", "diffusion", "--k", str(sphere.n_vertices), "--out", out])
    assert code == 2
    assert f"--k {sphere.n_vertices} needs a mesh of more than" in capsys.readouterr().err


@pytest.mark.parametrize("t", [0.0, -1.0, float("nan"), float("inf")])
def test_coverage_seeds_bad_time(sphere, t):
    with pytest.raises(ParameterError, match="diffusion time must be finite and > 0"):
        coverage_seeds(sphere, t)


@pytest.mark.parametrize("which", ["all", "half"])
def test_flipped_faces_are_reoriented_and_reported(which):
    """A target with flipped faces (all, or every other one) used to be matched as its mirror
    image through the orientation term. The mesh is re-oriented on construction (closed
    components outward), with a MeshWarning, and matches exactly like the original."""
    from torchfmap import Mesh, MeshWarning, match

    from .conftest import bend, bumpy_blob

    x = bumpy_blob(2)
    y = x.copy(bend(x.vertices, 0.3))
    faces = y.faces.copy()
    rows = slice(None) if which == "all" else slice(None, None, 2)
    faces[rows] = faces[rows][:, ::-1]
    with pytest.warns(MeshWarning, match="reversed the corner order"):
        flipped = Mesh(y.vertices, faces)
    assert flipped.report.n_flipped_faces == len(faces[rows])
    np.testing.assert_array_equal(flipped.faces, y.faces)
    a = match(x, y, k=15, k_descriptors=30)
    b = match(x, flipped, k=15, k_descriptors=30)
    np.testing.assert_array_equal(a.p2p_yx, b.p2p_yx)


def test_consistent_mesh_is_left_alone(sphere):
    """An outward, consistent mesh is not touched (no warning, same faces)."""
    import warnings

    from torchfmap import Mesh

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = Mesh(sphere.vertices, sphere.faces)
    assert m.report.n_flipped_faces == 0
    np.testing.assert_array_equal(m.faces, sphere.faces)


def _off_text(mesh) -> str:
    lines = ["OFF", f"{mesh.n_vertices} {mesh.n_faces} 0"]
    lines += [" ".join(f"{c:.9g}" for c in v) for v in mesh.vertices]
    lines += ["3 " + " ".join(str(i) for i in f) for f in mesh.faces]
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("cut", [1, 5, 200])
def test_truncated_off_is_refused_naming_the_counts(tmp_path, sphere, cut):
    """A file missing its last face lines used to load with a new hole (or an
    'allow_unreferenced' hint): the header's counts are now checked."""
    from torchfmap import MeshError, load_mesh

    text = _off_text(sphere).splitlines()
    path = tmp_path / "cut.off"
    path.write_text("\n".join(text[:-cut]) + "\n")
    with pytest.raises(MeshError, match=r"truncated.*declares 162 vertices and 320 faces.*Fix"):
        load_mesh(path)


def test_off_with_latin1_comment_loads(tmp_path, sphere):
    """A non-UTF-8 byte in a comment used to need an undeclared charset detector."""
    from torchfmap import load_mesh

    path = tmp_path / "latin.off"
    text = _off_text(sphere).replace("OFF\n", "OFF\n# caf\xe9 (Latin-1)\n", 1)
    path.write_bytes(text.encode("latin-1"))
    np.testing.assert_allclose(load_mesh(path).vertices, sphere.vertices, rtol=1e-8)


def test_mesh_errors_name_the_file_and_folders_are_refused(tmp_path, sphere):
    from torchfmap import MeshError, load_mesh

    bad = sphere.vertices.copy()
    path = tmp_path / "nan.off"
    path.write_text(_off_text(sphere.copy(bad)).replace(_off_text(sphere).splitlines()[2], "nan 0 0", 1))
    with pytest.raises(MeshError, match=r"nan\.off.*NaN"):
        load_mesh(path)
    with pytest.raises(MeshError, match="is a folder"):
        load_mesh(tmp_path)


@pytest.mark.parametrize("alpha", [1e-6, 1e5, 1e12])
def test_eigenpairs_are_scale_covariant(alpha):
    """Scaling a mesh by alpha scales L's eigenvalues by 1/alpha² and the B-orthonormal
    eigenvectors by 1/alpha (cotan L is scale-free, B scales with alpha²). The fixed absolute
    shift used to make cost and result depend on units (wrong maps from 1e8 on)."""
    from torchfmap.operators import eigenpairs

    from .conftest import bumpy_blob

    mesh = bumpy_blob(4)  # above the dense limit: the shift-invert ARPACK path
    lam, phi = eigenpairs(*laplacian(mesh), 12)
    lam_s, phi_s = eigenpairs(*laplacian(mesh.scaled(alpha)), 12)
    # ARPACK converges each pair to ARPACK_TOL relative, in both runs
    np.testing.assert_allclose(lam_s * alpha**2, lam, rtol=1e-6, atol=1e-8 * lam[-1])
    np.testing.assert_allclose(np.abs(phi_s * alpha), np.abs(phi), atol=1e-4 * np.abs(phi).max())


def test_overflowing_scale_is_named(sphere):
    from torchfmap import MeshError, laplacian_eigenbasis

    with pytest.raises((ParameterError, MeshError), match="over- or underflows"):
        laplacian_eigenbasis(sphere.scaled(1e155), 5)


def test_geodesic_distance_between_components_is_infinite():
    """No path joins two components: their distance is inf (it was a finite constant, on which
    errors and farthest-point seeds were silently built); FPS then seeds every component."""
    from torchfmap import GeodesicSolver, Mesh, farthest_point_sampling

    a = icosphere(1)
    b = a.copy(a.vertices + 5.0)
    two = Mesh(
        np.vstack([a.vertices, b.vertices]),
        np.vstack([a.faces, b.faces + a.n_vertices]),
        allow_components=True,
    )
    d = GeodesicSolver(two).distance(0)
    assert np.isinf(d[a.n_vertices :]).all() and np.isfinite(d[: a.n_vertices]).all()
    seeds = farthest_point_sampling(two, 2)
    assert len(set(two.component_labels[seeds].tolist())) == 2


def test_evaluation_refuses_invalid_maps(sphere):
    """-1 used to wrap to the last vertex, a map in the wrong direction was scored, floats and
    out-of-range entries gave bare IndexErrors, max_points=0 gave NaN."""
    from torchfmap.eval import evaluate_map, geodesic_errors, gt_identity

    small = icosphere(1)
    n = sphere.n_vertices
    gt = gt_identity(small.n_vertices)
    good = np.arange(small.n_vertices)
    cases = {
        "outside": good - 1,  # holds -1
        "outside ": good + 1,  # holds n
        "integer": good.astype(float),
    }
    for match_text, p2p in cases.items():
        with pytest.raises(ParameterError, match=match_text.strip()):
            geodesic_errors(small, p2p, gt)
    with pytest.raises(ParameterError, match="looks like a map x -> y"):
        evaluate_map(small, sphere, good, gt)
    with pytest.raises(ParameterError, match="max_points"):
        geodesic_errors(small, good, gt, max_points=0)
    assert n > small.n_vertices


def test_zero_based_vts_is_refused(tmp_path):
    from torchfmap.io import read_vts

    path = tmp_path / "a.vts"
    np.savetxt(path, [0, 4, 7], fmt="%d")
    with pytest.raises(ParameterError, match="1-based"):
        read_vts(path)


def test_no_nan_from_bad_descriptor_parameters(sphere):
    from torchfmap import laplacian_eigenbasis
    from torchfmap.descriptors import hks, wks

    basis = laplacian_eigenbasis(sphere, 10)
    for t in (float("nan"), float("inf"), -1.0):
        with pytest.raises(ParameterError, match="HKS times must be finite"):
            hks(basis.eigenvalues, basis.values, abs_times=[t])
    for s in (0.0, -1.0, float("nan")):
        with pytest.raises(ParameterError, match="sigma_factor"):
            wks(basis.eigenvalues, basis.values, sigma_factor=s)


def test_overflowing_descriptors_are_refused(sphere):
    from torchfmap import laplacian_eigenbasis, solve_fmap

    basis = laplacian_eigenbasis(sphere, 8)
    F = np.full((sphere.n_vertices, 3), 1e300)
    with pytest.raises(ParameterError, match="overflow.*normalize_descriptors"):
        solve_fmap(basis, basis, F, F)


def test_singular_matrix_is_refused_by_factorize(sphere):
    """L alone is singular (constants in its kernel): spd=True used to return values ~1e16."""
    from torchfmap import factorize
    from torchfmap.errors import NotPositiveDefiniteError

    L, B = laplacian(sphere)
    with pytest.raises(NotPositiveDefiniteError, match="singular.*Fix"):
        factorize(L, spd=True)
    x = factorize(L + 1e-3 * B, spd=True).solve(B @ np.ones(sphere.n_vertices))
    assert np.isfinite(x).all()


def test_temp_litter_of_killed_writers_is_removed_by_the_next_save(tmp_path, sphere):
    """A writer killed mid-save leaves its hidden temp file; the next save of that path removes
    it (its process is gone), and keeps files of live writers."""
    import os
    import signal
    import subprocess
    import sys

    from torchfmap import Basis, laplacian_eigenbasis

    basis = laplacian_eigenbasis(sphere, 4)
    target = tmp_path / "b.npz"
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    child.send_signal(signal.SIGKILL)
    child.wait()
    dead = tmp_path / f".b.npz.{child.pid}.1.abc.tmp"
    dead.write_bytes(b"partial")
    alive = tmp_path / f".b.npz.{os.getpid()}.99.def.tmp"
    alive.write_bytes(b"in progress")
    basis.save(target)
    assert not dead.exists() and alive.exists()
    assert Basis.load(target).k == 4


def test_long_provenance_names_survive_save(tmp_path, sphere):
    """Provenance kinds were cut to 16 characters on save."""
    from torchfmap import Basis, Column, laplacian_eigenbasis

    b = laplacian_eigenbasis(sphere, 2)
    long = Basis(
        b.values, b.mass, [Column("a-rather-long-custom-kind-name"), Column("x")], stiffness=b.stiffness
    )
    back = Basis.load(long.save(tmp_path / "long.npz"))
    assert back.provenance[0].kind == "a-rather-long-custom-kind-name"


def test_zoomout_refuses_to_shrink(sphere):
    from torchfmap import laplacian_eigenbasis
    from torchfmap.fmap import zoomout

    b = laplacian_eigenbasis(sphere, 12)
    with pytest.raises(ParameterError, match="k_final=4 is below"):
        zoomout(np.eye(8), b, b, 4)


def test_match_on_a_small_mesh_names_the_real_limit():
    """A 42-vertex mesh with k=10 used to be told 'got k=100' (the hidden descriptor count)."""
    from torchfmap import match

    s = icosphere(1)
    result = match(s, s, k=10)
    assert result.p2p_yx.shape == (42,)
    with pytest.raises(ParameterError, match=r"k \(basis size\) must be an integer in \[1, 41\]"):
        match(s, s, k=60)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "cannot read the landmark pair file"),
        ("", "holds no entries"),
        ("1 2 3\n", "expected 2 integer column"),
        ("1\n", "expected 2 integer column"),
        ("1 x\n", "must be integer"),
    ],
)
def test_cli_landmark_files_give_clear_errors(tmp_path, sphere, capsys, content, message):
    from torchfmap import save_mesh

    path = save_mesh(sphere, tmp_path / "s.off")
    lm = tmp_path / "lm.txt"
    if content is not None:
        lm.write_text(content)
    code = main(["match", str(path), str(path), "--landmarks", str(lm), "--out", str(tmp_path / "m.txt")])
    assert code == 2 and message in capsys.readouterr().err


def test_landmark_file_with_bom_and_comments_is_read(tmp_path):
    from torchfmap.io import read_landmark_pairs

    lm = tmp_path / "lm.txt"
    lm.write_bytes("\ufeff# pairs\n1 2\n\n3 4  # a comment\n".encode())
    np.testing.assert_array_equal(read_landmark_pairs(str(lm)), [[1, 2], [3, 4]])


def test_cli_output_paths_are_checked_before_the_work(tmp_path, sphere, capsys):
    from torchfmap import save_mesh

    path = str(save_mesh(sphere, tmp_path / "s.off"))
    for out, message in ((tmp_path / "missing" / "m.txt", "no folder"), (tmp_path, "is a folder")):
        code = main(["match", path, path, "--k", "5", "--out", str(out)])
        assert code == 2 and message in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv",
    [
        ["basis", "MESH", "--basis", "diffusion", "--times", "1e-3,abc", "--out", "OUT"],
        ["basis", "MESH", "--k", "-2", "--out", "OUT"],
        ["match", "MESH", "MESH", "--k", "0", "--out", "OUT"],
        ["eval", "FOLDER", "--max-points", "-5"],
        ["eval", "FOLDER", "--max-pairs", "-1"],
        ["eval", "FOLDER", "--threads", "0"],
    ],
)
def test_cli_bad_numbers_are_usage_errors(tmp_path, sphere, capsys, argv):
    """Refused by argparse (usage + 'error: argument ...'), never a traceback after the work."""
    from torchfmap import save_mesh

    mesh = str(save_mesh(sphere, tmp_path / "s.off"))
    argv = [{"MESH": mesh, "OUT": str(tmp_path / "o.npz"), "FOLDER": str(tmp_path)}.get(a, a) for a in argv]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2 and "error: argument" in capsys.readouterr().err


def test_cli_eval_and_info_edge_cases(tmp_path, capsys):
    from torchfmap import Mesh, save_mesh

    assert main(["eval", str(tmp_path / "nowhere")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    s = icosphere(1)
    for name in ("a", "b"):
        save_mesh(s, tmp_path / f"{name}.off")
    (tmp_path / "test_pairs.txt").write_text("a c\n")
    assert main(["eval", str(tmp_path)]) == 2
    assert "does not hold" in capsys.readouterr().err
    tet = Mesh(np.eye(4, 3) + [0.1, 0.2, 0.3], [[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    assert main(["info", str(save_mesh(tet, tmp_path / "tet.off"))]) == 0


def test_checkpoints_are_checksummed_and_load_no_code(tmp_path):
    """Checkpoints had no checksum (38 of 40 byte flips loaded) and loaded with
    weights_only=False (pickled code from the file would run)."""
    import torch

    from torchfmap.errors import CorruptFileError
    from torchfmap.nn.checkpoints import read_checkpoint, save_checkpoint

    net = torch.nn.Linear(3, 2)
    path = save_checkpoint(tmp_path / "m.ckpt", net, {"k": 5}, note="x")
    back = read_checkpoint(path)
    torch.testing.assert_close(back["state_dict"]["weight"], net.weight.detach())
    data = bytearray(path.read_bytes())
    rng = np.random.default_rng(0)
    for i in rng.choice(len(data), 20, replace=False):
        flipped = bytearray(data)
        flipped[i] ^= 0xFF
        bad = tmp_path / "bad.ckpt"
        bad.write_bytes(bytes(flipped))
        with pytest.raises(CorruptFileError):
            read_checkpoint(bad)
    plain = tmp_path / "plain.pt"
    torch.save({"state_dict": net.state_dict()}, plain)  # no header: refused, never unpickled
    with pytest.raises(CorruptFileError, match="not a torchfmap checkpoint"):
        read_checkpoint(plain)


def test_core_refuses_overflow_and_half_precision():
    """float32 features ~1e20 overflowed the Gram matrix unnoticed (NaN maps); half and bfloat16
    failed inside LAPACK with 'not implemented'."""
    import torch

    from torchfmap.fmap import core

    A = torch.full((4, 3), 1e20, dtype=torch.float32)
    mask = torch.ones(4, 4, dtype=torch.float32)
    with pytest.raises(ParameterError, match="overflows torch.float32"):
        core.solve_rowwise(A, A, mask, 1.0, 0.1)
    for dtype in (torch.float16, torch.bfloat16):
        A = torch.randn(4, 3).to(dtype)
        with pytest.raises(ParameterError, match="needs float32 or float64"):
            core.solve_rowwise(A, A, mask.to(dtype), 1.0, 0.1)


def test_one_based_landmarks_are_flagged():
    """Landmarks read 1-based were accepted (0.022 -> 0.444 on the demo pair): when the
    pairs shifted by -1 fit the shapes' geodesic distances far better, match warns."""
    import warnings

    from torchfmap import match
    from torchfmap.data import demo_pair
    from torchfmap.eval import gt_from_map, landmarks_from_gt

    a, b, gt_ba = demo_pair()
    lm = landmarks_from_gt(a, gt_from_map(gt_ba), 8)
    with pytest.warns(UserWarning, match="read 1-based"):
        match(a, b, landmarks=lm + 1, k=20)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*1-based.*")
        match(a, b, landmarks=lm, k=20)


@pytest.mark.slow
def test_kill_during_save_leaves_a_valid_file_and_no_litter_after_the_next_save(tmp_path):
    """kill -9 at random moments while a process rewrites a basis: the path always holds a
    complete file (old or new, checksum verified), and the next save removes the dead
    writer's temp file."""
    import signal
    import subprocess
    import sys
    import time

    from torchfmap import Basis

    target = tmp_path / "big.npz"
    code = (
        "import numpy as np, scipy.sparse as sp, sys\n"
        "from torchfmap import Basis\n"
        "v = np.random.default_rng(0).normal(size=(400000, 16))\n"
        "b = Basis(v, sp.identity(400000, format='csr'))\n"
        "b.save(sys.argv[1]); print('ready', flush=True)\n"
        "while True: b.save(sys.argv[1])\n"
    )
    for delay in (0.05, 0.2, 0.5):
        with subprocess.Popen(
            [sys.executable, "-c", code, str(target)], stdout=subprocess.PIPE, text=True
        ) as child:
            assert child.stdout.readline().strip() == "ready"
            time.sleep(delay)
            child.send_signal(signal.SIGKILL)
            child.wait()
        assert Basis.load(target).values.shape == (400000, 16)
    small = Basis(np.ones((3, 1)), np.ones(3))
    small.save(target)
    assert not list(tmp_path.glob(".*.tmp"))
    assert Basis.load(target).k == 1


def test_unreferenced_vertices_are_refused_by_operators_and_referenced_removes_them(sphere):
    """Item 5: a mesh kept with allow_unreferenced=True loads, but operators (whose rows at such
    vertices would be all zero: singular solves) refuse it with the fix; ``referenced()`` gives
    the submesh and the ids that map results back, and the submesh matches like the original."""
    from torchfmap import Mesh, MeshError, match

    extra = np.vstack([sphere.vertices[:7], [[5.0, 5.0, 5.0]], sphere.vertices[7:]])
    faces = np.where(sphere.faces >= 7, sphere.faces + 1, sphere.faces)  # vertex 7 is unused
    mesh = Mesh(extra, faces, allow_unreferenced=True)
    with pytest.raises(MeshError, match=r"not used by any face.*mesh.referenced\(\)"):
        laplacian(mesh)
    with pytest.raises(MeshError, match="not used by any face"):
        match(mesh, mesh, k=10)
    sub, ids = mesh.referenced()
    assert sub.n_vertices == sphere.n_vertices and 7 not in ids
    np.testing.assert_array_equal(sub.vertices, sphere.vertices)
    np.testing.assert_array_equal(sub.faces, sphere.faces)
    np.testing.assert_array_equal(mesh.vertices[ids], sub.vertices)
    L_sub, L_ref = laplacian(sub), laplacian(sphere)
    assert abs(L_sub.stiffness - L_ref.stiffness).max() == 0 and abs(L_sub.mass - L_ref.mass).max() == 0


def test_misread_landmark_files_are_flagged_on_real_pairs():
    """FAUST_r 070 -> 071 with 7 ground-truth landmarks: read 1-based or with swapped columns,
    match warns and names the reading that fits; as given, it does not warn."""
    import warnings

    from torchfmap import load_mesh, match
    from torchfmap.eval import gt_from_vts, landmarks_from_gt
    from torchfmap.io import read_vts

    from .conftest import data_path

    folder = data_path("faust_r_train")
    x, y = (load_mesh(folder / f"tr_reg_{n}.off") for n in ("070", "071"))
    gt = gt_from_vts(*(read_vts(folder / "corres" / f"tr_reg_{n}.vts") for n in ("070", "071")))
    lm = landmarks_from_gt(x, gt, 7)
    with pytest.warns(UserWarning, match="read 1-based"):
        match(x, y, landmarks=lm + 1, k=20, basis="laplacian")
    with pytest.warns(UserWarning, match="columns swapped"):
        match(x, y, landmarks=lm[:, ::-1].copy(), k=20, basis="laplacian")
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*fit the shapes.*")
        match(x, y, landmarks=lm, k=20, basis="laplacian")
