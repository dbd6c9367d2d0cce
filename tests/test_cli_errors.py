"""Bad input through the files and the CLI: every failure a torchfmap error with a fix (never a
traceback), silent failures made loud, the CLI's help and flags consistent."""

from __future__ import annotations

import io
import pickle
import subprocess
import sys
import warnings

import numpy as np
import pytest

from torchfmap import MapWarning, MeshError, MeshWarning, ParameterError, TorchFmapError, match, save_mesh
from torchfmap.cli import build_parser, main
from torchfmap.errors import CorruptFileError, FileReadError, FileWriteError

from .conftest import bend, bumpy_blob

DEMO = "torchfmap/data/demo"


def _err(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


# -- checkpoints ---------------------------------------------------------------------------


def _checked(path, payload: bytes):
    from torchfmap._files import save_checked_bytes

    return save_checked_bytes(path, payload)


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
def test_foreign_pickle_behind_a_valid_header_is_refused_not_run(tmp_path, capsys):
    """A pickle of ``os.system`` with a valid checksummed header: refused as a corrupt
    checkpoint (API and CLI), and the payload never runs."""
    from torchfmap.nn.checkpoints import load_checkpoint

    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            import os

            return (os.system, (f"touch {marker}",))

    path = _checked(tmp_path / "evil.ckpt", pickle.dumps(Payload()))
    with pytest.raises(CorruptFileError, match="not a weights-only torch file.*Nothing in it was run"):
        load_checkpoint(path)
    src, tgt = f"{DEMO}/blob_a.off", f"{DEMO}/blob_b.off"
    assert main(["match", src, tgt, "--checkpoint", str(path), "--out", str(tmp_path / "m.txt")]) == 2
    assert "holds no torchfmap checkpoint" in _err(capsys)
    assert not marker.exists()


def test_checkpoint_without_weights_or_with_weights_that_do_not_fit(tmp_path):
    import torch

    from torchfmap.nn.checkpoints import load_checkpoint, read_checkpoint, save_checkpoint
    from torchfmap.nn.config import TrainConfig, build_model

    buffer = io.BytesIO()
    torch.save({"config": {}}, buffer)
    path = _checked(tmp_path / "noweights.ckpt", buffer.getvalue())
    with pytest.raises(CorruptFileError, match=r"without \['state_dict'\]"):
        read_checkpoint(path)
    config = TrainConfig(k=8, n_wks=8, width=8, c_out=8)
    net = build_model(config)[0]
    good = save_checkpoint(tmp_path / "good.ckpt", net, config)
    ckpt = read_checkpoint(good)
    ckpt["state_dict"]["head.weight"] = torch.zeros(3, 3)  # wrong size for the recorded network
    buffer = io.BytesIO()
    torch.save(ckpt, buffer)
    bad = _checked(tmp_path / "bad.ckpt", buffer.getvalue())
    with pytest.raises(
        ParameterError, match="weights do not fit.*size mismatch.*Fix: the config and the weights"
    ):
        load_checkpoint(bad)
    ckpt["state_dict"] = [1, 2]
    buffer = io.BytesIO()
    torch.save(ckpt, buffer)
    with pytest.raises(ParameterError, match="not a state dict"):
        load_checkpoint(_checked(tmp_path / "list.ckpt", buffer.getvalue()))


# -- files: reading and writing --------------------------------------------------------------


def test_missing_input_files_are_torchfmap_errors_with_exit_1(tmp_path, capsys):
    from torchfmap.bases import Basis

    with pytest.raises(FileReadError, match="cannot read the basis file") as info:
        Basis.load(tmp_path / "none.npz")
    assert isinstance(info.value, FileNotFoundError) and isinstance(info.value, TorchFmapError)
    src, tgt = f"{DEMO}/blob_a.off", f"{DEMO}/blob_b.off"
    out = str(tmp_path / "m.txt")
    assert (
        main(["match", src, tgt, "--bases", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--out", out])
        == 1
    )
    err = _err(capsys)
    assert "cannot read the basis file" in err and "Fix:" in err and "[Errno" not in err


def test_a_failed_write_is_a_torchfmap_error_and_the_cli_says_so(tmp_path, monkeypatch, capsys):
    import builtins

    import torchfmap._files as files

    real_open = builtins.open

    def full_disk(file, mode="r", *args, **kwargs):
        if "w" in mode and str(file).endswith(".tmp"):
            raise OSError(28, "No space left on device")
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(files, "open", full_disk, raising=False)
    with pytest.raises(FileWriteError) as info:
        files.save_arrays(tmp_path / "a.npz", {"x": np.arange(3)})
    assert info.value.errno == 28 and isinstance(info.value, TorchFmapError)
    out = tmp_path / "b.npz"
    assert main(["basis", f"{DEMO}/blob_a.off", "--k", "10", "--out", str(out), "--quiet"]) == 1
    err = _err(capsys)
    assert "could not write" in err and "free disk space" in err and not out.exists()


def test_a_cache_that_cannot_store_falls_back_to_computing(tmp_path, monkeypatch, caplog):
    import torchfmap.nn.data as data

    cache = data.PrecomputeCache(tmp_path / "cache")

    def refuse(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(data, "save_arrays", refuse)
    with caplog.at_level("WARNING", logger="torchfmap.nn.data"):
        arrays = cache.get("key", lambda: {"a": np.arange(4)})
    assert np.array_equal(arrays["a"], np.arange(4))
    assert "computed without the cache" in caplog.text


# -- train: folders, Ctrl-C ------------------------------------------------------------------


def test_train_refuses_a_folder_without_pairs_a_file_and_a_missing_folder(tmp_path, capsys):
    one = tmp_path / "one"
    one.mkdir()
    save_mesh(bumpy_blob(2), one / "a.off")
    base = ["--out", str(tmp_path / "m.ckpt"), "--no-cache", "--quiet", "--max-steps", "1", "--k", "8"]
    assert main(["train", str(one), *base]) == 2
    assert "no pair of shapes to train on (1 mesh: a)" in _err(capsys)
    for target in (one / "a.off", tmp_path / "missing"):
        assert main(["train", str(target), *base]) == 2
        assert "is not a folder" in _err(capsys)


def test_ctrl_c_during_train_says_where_the_checkpoint_stands_and_exits_130(tmp_path, monkeypatch, capsys):
    import importlib

    # the module: the attribute torchfmap.nn.train is the function
    train_module = importlib.import_module("torchfmap.nn.train")

    folder = tmp_path / "two"
    folder.mkdir()
    x = bumpy_blob(2)
    for i, s in enumerate((0.1, 0.3)):
        save_mesh(x.copy(bend(x.vertices, s)), folder / f"b{i}.off")
    real = train_module.train

    def one_step_then_interrupt(*args, **kwargs):
        real(*args, **{**kwargs, "max_steps": 1})  # writes the checkpoint at step 1
        raise KeyboardInterrupt

    monkeypatch.setattr(train_module, "train", one_step_then_interrupt)
    ckpt = tmp_path / "m.ckpt"
    args = ["train", str(folder), "--out", str(ckpt), "--no-cache", "--quiet", "--max-steps", "5", "--k", "8"]
    assert main(args) == 130
    err = _err(capsys)
    assert "interrupted" in err and "holds step 1" in err and "--resume" in err


def test_broken_pipe_ends_quietly(tmp_path):
    cmd = f"{sys.executable} -m torchfmap info {DEMO}/blob_a.off | head -c 10"
    done = subprocess.run(
        ["bash", "-c", f"set -o pipefail; {cmd}"], capture_output=True, text=True, timeout=120
    )
    assert "Traceback" not in done.stderr and "BrokenPipe" not in done.stderr


# -- silent or misleading input --------------------------------------------------------------


def test_off_face_line_with_two_indices_is_refused(tmp_path):
    from torchfmap import load_mesh

    path = tmp_path / "t.off"
    path.write_text("OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n2 0 1\n")
    with pytest.raises(MeshError, match="fewer than 3 corners: '2 0 1'"):
        load_mesh(path)


def test_duplicated_faces_are_dropped_with_a_warning_and_the_operators_are_unchanged():
    from torchfmap import Mesh
    from torchfmap.operators import laplacian

    mesh = bumpy_blob(1)
    doubled = np.concatenate([mesh.faces, mesh.faces[[3]][:, ::-1]])  # the same face, another corner order
    with pytest.warns(MeshWarning, match="dropped 1 duplicated faces"):
        twin = Mesh(mesh.vertices, doubled, allow_nonmanifold=True)
    assert twin.n_faces == mesh.n_faces
    a, b = laplacian(mesh), laplacian(twin)
    assert abs(a.stiffness - b.stiffness).max() == 0 and abs(a.mass - b.mass).max() == 0


def test_layers_refuse_what_the_functions_refuse():
    import torch

    from torchfmap.nn import functional as F
    from torchfmap.nn.modules import RegularizedFMSolver
    from torchfmap.nn.networks import DiffusionNet

    for w in (float("nan"), float("inf"), -1.0):
        with pytest.raises(ParameterError, match="solver weights must be finite"):
            RegularizedFMSolver(w_lap=w)
    feats = torch.randn(1, 5, 3, dtype=torch.float64)
    d = dict(dtype=torch.float64)
    basis = F.BasisBatch(
        torch.randn(1, 5, 2, **d),
        torch.ones(1, 5, **d),
        torch.zeros(1, 2, **d),
        torch.eye(2, **d)[None],
        torch.ones(1, 2, **d),
    )
    with pytest.raises(ParameterError, match="solver weights must be finite"):
        F.fmap_solve(feats, feats, basis, basis, w_lap=float("nan"))
    from .test_nn_networks import _batch

    shape = _batch(bumpy_blob(1))
    net = DiffusionNet(c_in=shape.inputs.shape[-1], c_out=4, width=8, n_blocks=1).double()
    inputs = shape.inputs.double().clone()
    inputs[0, 3, 0] = float("nan")
    with pytest.raises(ParameterError, match="DiffusionNet inputs contain NaN"):
        net(inputs, shape.basis, shape.grad)


def test_point_cloud_ply_is_named_and_readable_end_to_end(tmp_path):
    import trimesh

    from torchfmap import load_mesh, load_points
    from torchfmap.operators import laplacian

    points = bumpy_blob(2).vertices
    path = tmp_path / "cloud.ply"
    trimesh.PointCloud(points).export(path)
    with pytest.raises(MeshError, match=r"holds 162 points and no faces: a point cloud.*load_points"):
        load_mesh(path)
    loaded = load_points(path)
    np.testing.assert_allclose(loaded, points)
    ops = laplacian(loaded, kind="robust")
    assert ops.stiffness.shape == (162, 162)


def test_garbage_named_stl_is_reported_as_not_stl(tmp_path):
    from torchfmap import load_mesh

    path = tmp_path / "junk.stl"
    path.write_bytes(np.random.default_rng(0).bytes(3000))
    with pytest.raises(MeshError, match="is not an STL file"):
        load_mesh(path)


def test_a_collapsed_map_warns():
    x = bumpy_blob(2)
    y = x.copy(bend(x.vertices, 0.3))
    with pytest.warns(MapWarning, match="has collapsed"):
        match(x, y, k=20, w_lap=1e12)
    with warnings.catch_warnings():
        warnings.simplefilter("error", MapWarning)
        match(x, y, k=20)  # a healthy map: no warning


def test_empty_times_are_refused(capsys):
    x = bumpy_blob(1)
    with pytest.raises(ParameterError, match="diffusion times must be finite"):
        match(x, x, landmarks=[[0, 0], [5, 5], [9, 9]], basis="diffusion", times=[], k=10)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["match", "a.off", "b.off", "--out", "m.txt", "--times", ""])
    assert "times must not be empty" in capsys.readouterr().err
    for flag in ("--lr", "--minutes"):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["train", "f", "--out", "m.ckpt", flag, "nan"])


# -- basis -> match --bases --------------------------------------------------------------------


def test_basis_pair_corresponds_and_unrelated_bases_warn(tmp_path, capsys):
    x = bumpy_blob(2)
    y = x.copy(bend(x.vertices, 0.3))
    px, py = save_mesh(x, tmp_path / "x.off"), save_mesh(y, tmp_path / "y.off")
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("3 3\n60 60\n120 120\n")
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    assert (
        main(
            [
                "basis",
                str(px),
                str(py),
                "--landmarks",
                str(pairs),
                "--k",
                "20",
                "--out",
                str(a),
                str(b),
                "--quiet",
            ]
        )
        == 0
    )
    out = tmp_path / "m.txt"
    capsys.readouterr()
    assert main(["match", str(px), str(py), "--bases", str(a), str(b), "--out", str(out), "--quiet"]) == 0
    assert "warning" not in capsys.readouterr().err  # the CLI prints warnings as 'torchfmap: warning:'
    from torchfmap.bases import Basis, prepare_shape
    from torchfmap.pipeline import match_bases

    built = match_bases(
        prepare_shape(x, 0), prepare_shape(y, 0), "diffusion", 20, np.loadtxt(pairs, dtype=int)
    )
    for saved, fresh in zip((Basis.load(a), Basis.load(b)), built[:2], strict=True):
        # match's own pair; the meshes went through OFF text (9 significant digits), so the
        # values agree to far below any seed mismatch (a wrong seed changes whole columns)
        np.testing.assert_allclose(saved.values, fresh.values, rtol=0, atol=1e-6 * np.abs(fresh.values).max())
        np.testing.assert_array_equal(saved.pair_landmarks, built[2])
    lm = tmp_path / "seeds.txt"
    lm.write_text("3\n60\n120\n")
    for mesh, path in ((px, a), (py, b)):  # one at a time: each mesh seeded on its own
        assert (
            main(["basis", str(mesh), "--landmarks", str(lm), "--k", "20", "--out", str(path), "--quiet"])
            == 0
        )
    main(["match", str(px), str(py), "--bases", str(a), str(b), "--out", str(out), "--quiet"])
    assert "torchfmap: warning: the given bases have seeded columns but were not built" in _err(capsys)
    assert main(["basis", str(px), "--k", "10", "--out", str(tmp_path / "lap.txt")]) == 2
    assert "a basis file is .npz" in _err(capsys)
    assert main(["basis", str(px), str(py), "--k", "10", "--out", str(a)]) == 2
    assert "one --out file per mesh" in _err(capsys)


# -- help and messages ------------------------------------------------------------------------


@pytest.mark.parametrize("command", ["basis", "match", "eval", "train"])
def test_help_shows_each_default_once_and_none_for_required_options(command, capsys):
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: None)" not in text and "(default: False)" not in text
    for line in text.split("--")[1:]:
        assert line.count("default") <= 1, line


def test_error_lines_name_the_class_once(tmp_path, capsys):
    assert main(["info", str(tmp_path / "none.off")]) == 2
    err = _err(capsys)
    assert err.startswith("torchfmap: error (MeshError): ") and "TorchFmapError" not in err


# -- eval and train flags ------------------------------------------------------------------


def _identity_folder(tmp_path):
    folder = tmp_path / "set"
    folder.mkdir()
    x = bumpy_blob(2)
    for i, s in enumerate((0.1, 0.3, 0.5)):
        save_mesh(x.copy(bend(x.vertices, s)), folder / f"m{i}.off")
    return folder


def test_eval_scores_saved_maps_and_passes_its_match_settings(tmp_path, monkeypatch, capsys):
    import torchfmap.commands as commands
    from torchfmap.eval import discover_pairs

    folder = _identity_folder(tmp_path)
    maps = tmp_path / "maps"
    maps.mkdir()
    pairs = list(discover_pairs(folder))
    for a, b, *_ in pairs:  # the identity for the first pair, a constant map for the rest
        n = 162
        p2p = np.arange(n) if (a, b) == pairs[0][:2] else np.zeros(n, dtype=int)
        (maps / f"{a}-{b}.txt").write_text("\n".join(map(str, p2p)) + "\n")
    assert main(["eval", str(folder), "--maps", str(maps), "--quiet"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| m")]
    assert rows[0].split("|")[3].strip() == "0.0000"  # the exact map scores 0
    assert all(float(r.split("|")[3]) > 0.1 for r in rows[1:])  # the constant map is far off
    (maps / f"{pairs[1][0]}-{pairs[1][1]}.txt").unlink()
    assert main(["eval", str(folder), "--maps", str(maps), "--quiet"]) == 2
    assert f"no saved map {pairs[1][0]}-{pairs[1][1]}.txt" in _err(capsys)
    assert main(["eval", str(folder), "--maps", str(maps), "--basis", "laplacian"]) == 2
    assert "takes no matching options" in _err(capsys)

    seen = {}

    def record(pairs, **kwargs):
        seen.update(kwargs, paths=[p for pair in pairs for p in pair[2:4]])
        return []

    monkeypatch.setattr(commands, "evaluate_pairs", record)
    monkeypatch.chdir(tmp_path)
    try:
        main(["eval", "set", "--k-final", "30", "--w-lap", "0.5", "--k", "12", "--quiet"])
    except ValueError:  # no results to print: the settings were recorded
        pass
    assert seen["k_final"] == 30 and seen["w_lap"] == 0.5 and seen["k"] == 12
    assert all(p.is_absolute() for p in seen["paths"])  # sent resolved, for workers elsewhere


def test_resume_with_a_spent_budget_is_refused(tmp_path, capsys):
    folder = _identity_folder(tmp_path)
    ckpt = tmp_path / "m.ckpt"
    args = ["train", str(folder), "--out", str(ckpt), "--no-cache", "--quiet", "--k", "8"]
    assert main([*args, "--max-steps", "2"]) == 0
    capsys.readouterr()
    assert main([*args, "--max-steps", "2", "--resume"]) == 2
    err = _err(capsys)
    assert "already spent its budget --max-steps 2 (done: 2 steps)" in err and "larger budget" in err


def test_eval_reads_landmark_pairs_per_pair_from_a_folder(tmp_path, capsys):
    """``eval --landmarks DIR``: each pair's landmarks come from DIR/<source>-<target>.txt; the
    result equals passing the same pairs to match() directly."""
    from torchfmap import load_mesh
    from torchfmap.collection import LandmarkFiles, evaluate_pairs
    from torchfmap.eval import discover_pairs, evaluate_map

    folder = _identity_folder(tmp_path)
    lms = tmp_path / "lm"
    lms.mkdir()
    pairs = list(discover_pairs(folder))
    for a, b, *_ in pairs:
        (lms / f"{a}-{b}.txt").write_text("3 3\n60 60\n120 120\n")
    results = evaluate_pairs(pairs, gt_landmarks=LandmarkFiles(lms), k=12, threads=1)
    for (_, _, pa, pb, gt), r in zip(pairs, results, strict=True):
        x, y = load_mesh(pa), load_mesh(pb)
        p2p = match(x, y, landmarks=np.array([[3, 3], [60, 60], [120, 120]]), k=12).p2p_yx
        np.testing.assert_array_equal(r.errors, evaluate_map(x, y, p2p, gt)[1])
    assert main(["eval", str(folder), "--landmarks", str(lms), "--k", "12", "--quiet"]) == 0
    capsys.readouterr()
    (lms / f"{pairs[0][0]}-{pairs[0][1]}.txt").unlink()
    assert main(["eval", str(folder), "--landmarks", str(lms), "--quiet"]) == 2
    assert "no landmark file" in _err(capsys)
    assert main(["eval", str(folder), "--landmarks", str(lms), "--gt-landmarks", "3"]) == 2
    assert "pass one of them" in _err(capsys)
