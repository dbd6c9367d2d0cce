"""Scored pairs kept as they finish (``torchfmap.evaluate.saved_pairs``, ``torchfmap eval --out``): a rerun
resumes from them after Ctrl-C, a killed worker or a full disk; another run's file is refused,
never overwritten."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from torchfmap import ParameterError, save_mesh
from torchfmap.cli import main
from torchfmap.evaluate.collection import evaluate_pairs
from torchfmap.evaluate.saved_pairs import SavedPairs
from torchfmap.evaluate.scores import discover_pairs

from ..conftest import _err, _identity_folder, bend, bumpy_blob

ROW = re.compile(r"^\| (m\d+) \| (m\d+) \| ([0-9.]+) \|", re.M)


def _rows(text: str) -> dict[tuple[str, str], str]:
    return {(a, b): err for a, b, err in ROW.findall(text)}


def test_a_rerun_reads_the_kept_pairs_and_other_settings_are_refused(tmp_path, capsys, monkeypatch):
    folder = _identity_folder(tmp_path)
    out = tmp_path / "scores.npz"
    args = ["eval", str(folder), "--gt", "identity", "--pairs", "all", "--k", "20", "--threads", "1"]
    assert main([*args, "--out", str(out), "--max-pairs", "2"]) == 0
    first = _rows(capsys.readouterr().out)
    assert len(first) == 2 and out.is_file()
    # the next run scores only the 4 pairs the file lacks; the kept ones are read, not matched
    calls = []
    import torchfmap.evaluate.collection as collection

    real = collection._evaluate_chunk
    monkeypatch.setattr(
        collection, "_evaluate_chunk", lambda pairs, *a, **k: calls.append(len(pairs)) or real(pairs, *a, **k)
    )
    assert main([*args, "--out", str(out)]) == 0
    captured = capsys.readouterr()
    rows = _rows(captured.out)
    assert "resuming: 2 of 6 pairs" in captured.err and sum(calls) == 4
    assert len(rows) == 6 and all(rows[key] == value for key, value in first.items())
    # the same table as a run without the file (errors are stored exactly)
    assert main(args) == 0
    assert _rows(capsys.readouterr().out) == rows
    # other settings: refused, the file untouched
    before = out.read_bytes()
    assert main([*args, "--k", "30", "--out", str(out)]) == 2
    assert "other settings" in _err(capsys) and out.read_bytes() == before
    with pytest.raises(ParameterError, match="FILE.npz"):
        SavedPairs(tmp_path / "scores.csv", {})


def test_a_full_disk_warns_once_and_the_run_goes_on(tmp_path, monkeypatch):
    """Every write fails (ENOSPC): the run finishes, one warning, the file keeps its last write."""
    import errno

    import torchfmap.evaluate.saved_pairs as saved_pairs

    folder = _identity_folder(tmp_path)
    pairs = list(discover_pairs(folder, True, "all"))
    saved = SavedPairs(tmp_path / "s.npz", {"k": 20})
    results = evaluate_pairs(pairs[:2], k=20, on_results=saved.add)
    saved.flush()
    kept = saved.path.read_bytes()

    def full(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(saved_pairs, "save_arrays", full)
    monkeypatch.setattr(saved_pairs, "SAVE_INTERVAL", 0.0)
    with pytest.warns(UserWarning, match="could not save the scored pairs.*No space left") as caught:
        results += evaluate_pairs(pairs[2:], k=20, on_results=saved.add)
        saved.flush()
    assert len(caught) == 1 and len(results) == len(pairs) == len(saved.results)
    assert saved.path.read_bytes() == kept
    back = SavedPairs(saved.path, {"k": 20}).results
    assert [(r.source, r.target) for r in back] == [(r.source, r.target) for r in results[:2]]
    np.testing.assert_array_equal(back[1].errors, results[1].errors)


def _sixteen_shapes(tmp_path: Path) -> tuple[Path, Path, int, list[str]]:
    """``(folder, out, number of pairs, eval command)``: 16 meshes of 642 vertices, 240 pairs, a
    minute of work or more with 2 workers, so a signal after the first chunk comes while most of
    it remains."""
    folder = tmp_path / "set"
    folder.mkdir()
    x = bumpy_blob(3)
    for i in range(16):
        save_mesh(x.copy(bend(x.vertices, 0.05 + 0.04 * i)), folder / f"m{i:02d}.off")
    out = tmp_path / "scores.npz"
    cmd = [sys.executable, "-m", "torchfmap", "eval", str(folder), "--pairs", "all", "--workers", "2"]
    return folder, out, 16 * 15, [*cmd, "--threads", "1", "--k", "30", "--out", str(out)]


def _start(cmd: list[str]) -> tuple[subprocess.Popen, list[str]]:
    """The command with Ctrl-C as in a terminal (a suite started in the background inherits SIGINT
    ignored), its stderr and stdout collected by threads (their only readers: see ``_finish``)."""
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    err: list[str] = []
    proc.out_text = []
    proc.readers = [
        threading.Thread(target=lambda s=stream, t=sink: t.extend(iter(lambda: s.read(1), "")), daemon=True)
        for stream, sink in ((proc.stderr, err), (proc.stdout, proc.out_text))
    ]
    for reader in proc.readers:
        reader.start()
    return proc, err


def _finish(proc: subprocess.Popen, timeout: float) -> str:
    """The command's stdout once it exits within ``timeout`` seconds (else it is killed and the
    test fails: a hang is a failure, not a stuck suite), read to the end by ``_start``'s threads
    (``communicate`` would read the pipes too, taking part of them from those threads)."""
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        for pid in [*_workers(proc.pid), proc.pid]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        pytest.fail(f"the command did not exit within {timeout} s")
    for reader in proc.readers:
        reader.join(timeout=timeout)
    assert not any(r.is_alive() for r in proc.readers), "a child still holds the command's output open"
    return "".join(proc.out_text)


def _wait_for_progress(proc, err, total: int) -> int:
    progress = re.compile(rf"\b([1-9]\d*)/{total}\b")
    deadline = time.monotonic() + 240
    while not progress.search("".join(err)) and time.monotonic() < deadline:
        assert proc.poll() is None, "".join(err)
        time.sleep(0.05)
    if not progress.search("".join(err)):
        proc.kill()
        pytest.fail(f"no chunk finished in time: {''.join(err)[-500:]}")
    return int(progress.findall("".join(err))[-1])


def _workers(pid: int) -> list[int]:
    """The pool's worker processes among ``pid``'s children (not the resource tracker)."""
    children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    return [int(c) for c in children if b"resource_tracker" not in Path(f"/proc/{c}/cmdline").read_bytes()]


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="finds the workers through /proc (Linux)")
def test_a_killed_worker_keeps_the_finished_pairs_and_the_rerun_resumes(tmp_path):
    folder, out, n_pairs, cmd = _sixteen_shapes(tmp_path)
    proc, err = _start(cmd)
    done = _wait_for_progress(proc, err, n_pairs)
    assert done < n_pairs / 2
    t0 = time.monotonic()
    os.kill(_workers(proc.pid)[0], signal.SIGKILL)  # as the kernel's out-of-memory killer would
    out_text = _finish(proc, 60)
    assert proc.returncode == 1 and time.monotonic() - t0 < 10, (proc.returncode, "".join(err)[-500:])
    assert "a worker process died" in "".join(err) and "the same command resumes" in "".join(err)
    printed = _rows(out_text)
    assert len(printed) >= done and _kept(out) == set(printed)
    # the rerun (the first 5 pairs, to stay short) reads the kept ones and scores only the rest
    first = [(p[0], p[1]) for p in discover_pairs(folder, None, "all")][:5]
    overlap = [key for key in first if key in printed]
    again = subprocess.run(
        [*cmd, "--max-pairs", "5", "--workers", "1"], capture_output=True, text=True, timeout=240
    )  # fmt: skip
    assert again.returncode == 0, again.stderr[-500:]
    assert f"resuming: {len(overlap)} of 5 pairs" in again.stderr or not overlap
    rows = _rows(again.stdout)
    assert set(rows) == set(first) and all(rows[k] == printed[k] for k in overlap)


def _kept(path: Path) -> set[tuple[str, str]]:
    from torchfmap._util.files import load_arrays

    return {(str(a), str(b)) for a, b in load_arrays(path)["names"]}


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="finds the workers through /proc (Linux)")
def test_ctrl_c_with_two_workers_exits_promptly_and_keeps_the_finished_pairs(tmp_path):
    """Ctrl-C after the first chunks: within 3 s (the workers are terminated, not waited for),
    exit 130, the rows scored so far printed with a footer saying so, and kept in the file (the
    rerun's resuming is tested with a killed worker above)."""
    folder, out, n_pairs, cmd = _sixteen_shapes(tmp_path)
    proc, err = _start(cmd)
    done = _wait_for_progress(proc, err, n_pairs)
    t0 = time.monotonic()
    os.kill(proc.pid, signal.SIGINT)
    out_text = _finish(proc, 30)
    assert proc.returncode == 130 and time.monotonic() - t0 < 3.0
    printed = _rows(out_text)
    assert len(printed) >= done and _kept(out) == set(printed)
    assert "interrupted after" in out_text and "| **all** |" in out_text


def test_a_second_eval_on_a_file_in_use_is_refused_with_one_line(tmp_path, capsys):
    """``eval --out S`` holds ``S.lock`` while it runs: a second run on the same file while the
    first lives is refused at once with one line naming the file and the fix, and writes nothing;
    once the holder is gone, its lock is taken over."""
    folder = _identity_folder(tmp_path)
    out = tmp_path / "scores.npz"
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        Path(f"{out}.lock").write_text(str(holder.pid))
        args = ["eval", str(folder), "--gt", "identity", "--max-pairs", "1", "--k", "10", "--out", str(out)]
        assert main(args) != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "being written by another process" in err[0] and str(out) in err[0]
        assert not out.exists()
    finally:
        holder.kill()
        holder.wait()
    assert main(args) == 0 and out.exists() and not Path(f"{out}.lock").exists()


def test_ctrl_c_before_any_pair_finishes_names_no_file(tmp_path, capsys, monkeypatch):
    """Interrupted before the first pair is scored, ``eval --out S`` does not tell the user the
    finished pairs are in ``S`` (there are none and no file was written)."""
    import torchfmap.cli.commands as commands
    from torchfmap.errors import EvaluationInterrupted

    def interrupted(pairs, **kw):
        raise EvaluationInterrupted([], len(pairs))

    monkeypatch.setattr(commands, "evaluate_pairs", interrupted)
    folder = _identity_folder(tmp_path)
    out = tmp_path / "scores.npz"
    assert main(["eval", str(folder), "--gt", "identity", "--k", "10", "--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert "interrupted after 0" in err and str(out) not in err and not out.exists()
