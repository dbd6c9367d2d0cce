"""Atomic checksummed files (``torchfmap._util.files``) behind ``Basis.save/load`` and the nn cache:
concurrent writers, failed writes and renames, killed writers, unwritable destinations."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from torchfmap import Basis, TorchFmapError
from torchfmap._util.files import atomic_write, load_arrays, save_arrays
from torchfmap.cli import main
from torchfmap.errors import CorruptFileError, FileWriteError

from ..conftest import DEMO, _basis, _err


def test_two_threads_saving_one_path_both_succeed(tmp_path):
    path = tmp_path / "basis.npz"
    bases = [_basis(value=1.0), _basis(value=2.0)]
    barrier = threading.Barrier(2)
    errors: list[BaseException] = []

    def worker(basis: Basis) -> None:
        try:
            for _ in range(15):
                barrier.wait()
                basis.save(path)
        except BaseException as err:  # reported below
            errors.append(err)
            barrier.abort()

    threads = [threading.Thread(target=worker, args=(b,)) for b in bases]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    back = Basis.load(path)  # one of the two, complete
    assert any(np.array_equal(back.values, b.values) for b in bases)
    assert [p.name for p in tmp_path.iterdir()] == ["basis.npz"]


def _fail_midway(fh, *args, **kwargs):
    fh.write(b"PK\x03\x04 half a zip")
    raise OSError("disk full (simulated)")


def test_failed_write_leaves_no_temp_file(tmp_path, monkeypatch):
    monkeypatch.setattr(np, "savez", _fail_midway)
    with pytest.raises(OSError, match="disk full"):
        _basis().save(tmp_path / "basis.npz")
    assert list(tmp_path.iterdir()) == []


def test_failed_rename_leaves_no_temp_file(tmp_path, monkeypatch):
    def no_replace(src, dst):
        raise PermissionError("destination locked (simulated)")

    monkeypatch.setattr("torchfmap._util.files.os.replace", no_replace)
    with pytest.raises(PermissionError):
        save_arrays(tmp_path / "a.npz", {"x": np.arange(3)})
    assert list(tmp_path.iterdir()) == []


def test_failed_overwrite_keeps_the_old_file_intact(tmp_path, monkeypatch):
    """A plain ``open(path, 'wb')`` would have truncated the old file before failing."""
    path = tmp_path / "basis.npz"
    old = _basis(value=1.0)
    old.save(path)
    monkeypatch.setattr(np, "savez", _fail_midway)
    with pytest.raises(OSError, match="disk full"):
        _basis(value=2.0).save(path)
    monkeypatch.undo()
    back = Basis.load(path)
    assert np.array_equal(back.values, old.values)
    assert [p.name for p in tmp_path.iterdir()] == ["basis.npz"]


def test_atomic_write_replaces_only_after_a_complete_write(tmp_path):
    path = tmp_path / "f.bin"
    path.write_bytes(b"old")

    def write(fh):
        fh.write(b"new, partial")
        assert path.read_bytes() == b"old"  # the destination is untouched while writing
        raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError):
        atomic_write(path, write)
    assert path.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["f.bin"]
    atomic_write(path, lambda fh: fh.write(b"new"))
    assert path.read_bytes() == b"new"


def test_checksum_verified_on_read(tmp_path):
    path = save_arrays(tmp_path / "a.npz", {"x": np.arange(5.0), "y": np.eye(2)})
    back = load_arrays(path)
    assert set(back) == {"x", "y"} and np.array_equal(back["x"], np.arange(5.0))
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["x"] = arrays["x"] + 1e-12
    np.savez(path, **arrays)
    with pytest.raises(CorruptFileError, match="checksum"):
        load_arrays(path)
    path.write_bytes(path.read_bytes()[:40])
    with pytest.raises(CorruptFileError, match="rebuild"):
        load_arrays(path)
    with pytest.raises(FileNotFoundError):
        load_arrays(tmp_path / "missing.npz")


def test_bytes_that_reach_the_disk_wrong_are_caught_before_the_rename(tmp_path, monkeypatch):
    """A save whose file on disk differs from what was meant (a flipped byte, as a bad disk or
    a concurrent scribbler would leave) is refused by the read-back check, and the old file
    stays."""
    import torchfmap._util.files as files
    from torchfmap._util.files import load_checked_bytes, save_checked_bytes

    path = tmp_path / "model.ckpt"
    save_checked_bytes(path, b"old weights")
    real_fsync = files.os.fsync

    def fsync_then_flip(fd):
        real_fsync(fd)
        tmp = next(tmp_path.glob(".model.ckpt.*.tmp"))
        data = bytearray(tmp.read_bytes())
        data[-3] ^= 0x01
        tmp.write_bytes(bytes(data))

    monkeypatch.setattr(files.os, "fsync", fsync_then_flip)
    with pytest.raises(CorruptFileError, match="checksum"):
        save_checked_bytes(path, b"new weights")
    monkeypatch.undo()
    assert load_checked_bytes(path) == b"old weights"
    assert [p.name for p in tmp_path.iterdir()] == ["model.ckpt"]


@pytest.mark.parametrize(
    "error", [PermissionError(13, "Permission denied"), OSError(28, "No space left on device")]
)
def test_unwritable_destination_is_named_with_the_fix(tmp_path, monkeypatch, error):
    """A read-only folder or a full disk (simulated: tests may run as root, who can write
    anywhere) gives the same error class and errno, naming the path, saying the old file is
    unchanged and how to fix it."""
    import builtins

    import torchfmap._util.files as files

    path = tmp_path / "a.npz"
    save_arrays(path, {"x": np.arange(3)})
    real_open = builtins.open

    def refusing_open(file, mode="r", *args, **kwargs):
        if "w" in mode and str(file).endswith(".tmp"):
            raise error
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(files, "open", refusing_open, raising=False)
    with pytest.raises(type(error)) as info:
        save_arrays(path, {"x": np.arange(4)})
    assert info.value.errno == error.errno
    assert str(path) in str(info.value) and "unchanged" in str(info.value) and "Fix:" in str(info.value)
    monkeypatch.undo()
    assert np.array_equal(load_arrays(path)["x"], np.arange(3))
    assert [p.name for p in tmp_path.iterdir()] == ["a.npz"]  # no temp litter
    save_arrays(path, {"x": np.arange(4)})  # the next save works and leaves nothing else
    assert [p.name for p in tmp_path.iterdir()] == ["a.npz"]


def test_temp_litter_of_killed_writers_is_removed_by_the_next_save(tmp_path, sphere2):
    """A writer killed mid-save leaves its hidden temp file; the next save of that path removes
    it (its process is gone), and keeps files of live writers."""
    import os
    import signal
    import subprocess
    import sys

    from torchfmap import Basis, laplacian_eigenbasis

    basis = laplacian_eigenbasis(sphere2, 4)
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


def test_a_failed_write_is_a_torchfmap_error_and_the_cli_says_so(tmp_path, monkeypatch, capsys):
    import builtins

    import torchfmap._util.files as files

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


def test_a_file_name_too_long_for_its_file_system_is_refused_with_its_limit(tmp_path, capsys):
    """The operating system would say only 'File name too long', about the temporary file; the
    name's length and the limit are said instead, before anything is written (the library's
    writer and the command line's output check)."""
    import os

    from torchfmap import ParameterError
    from torchfmap._util.files import TEMP_NAME_EXTRA, check_file_name

    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    long = tmp_path / ("a" * (limit - TEMP_NAME_EXTRA + 1) + ".txt")
    with pytest.raises(
        ParameterError, match=rf"allows {limit}.*Fix: a name of at most {limit - TEMP_NAME_EXTRA}"
    ):
        atomic_write(long, lambda fh: fh.write(b"x"))
    assert list(tmp_path.iterdir()) == []
    fits = tmp_path / ("b" * (limit - TEMP_NAME_EXTRA - 4) + ".txt")
    check_file_name(fits)
    atomic_write(fits, lambda fh: fh.write(b"x"))  # the longest name allowed is written
    assert fits.read_bytes() == b"x"
    a, b = f"{DEMO}/blob_a.off", f"{DEMO}/blob_b.off"
    assert main(["match", a, b, "--out", str(tmp_path / ("c" * 300 + ".txt")), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "file system allows" in err and "Errno" not in err
