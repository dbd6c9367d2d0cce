"""The README and the guides in docs/ run: every ``python`` block (each on its own, in a fresh
namespace: a reader may paste any one) and every ``bash`` block (each line through the shell,
from a copy of the repository's layout), verbatim. A block preceded by
``<!-- readme-test: skip: REASON -->`` is not run (an install, the test command itself,
minutes-long training or benchmarks); a block that reads ``../shared/data`` skips when that
folder is absent."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
BLOCK = re.compile(r"(<!-- readme-test: skip: (?P<why>.*?) -->\n)?```(?P<lang>\w+)\n(?P<body>.*?)```", re.S)


#: The documents whose blocks run: the README first, then the guides (a guide's block may use
#: a file an earlier README block wrote).
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def _blocks_of(doc: Path) -> list[tuple[str, str, str | None]]:
    """``(language, code, skip reason or None)`` of every fenced block of one document."""
    return [(m["lang"], m["body"], m["why"]) for m in BLOCK.finditer(doc.read_text(encoding="utf-8"))]


def readme_blocks() -> list[tuple[str, str, str | None]]:
    """``(language, code, skip reason or None)`` of every fenced block of :data:`DOCS`, in order."""
    return [block for doc in DOCS for block in _blocks_of(doc)]


def shell_commands(body: str) -> list[str]:
    """The commands of a bash block: continuation lines joined, comments kept for the shell."""
    return [c for c in body.replace("\\\n", " ").splitlines() if c.strip() and not c.lstrip().startswith("#")]


def test_every_block_is_run_or_says_why_not():
    blocks = readme_blocks()
    assert blocks, "no fenced blocks found in README.md"
    for lang, body, why in blocks:
        assert lang in ("python", "bash", "text"), f"unknown block language {lang!r}"
        assert why is None or why.strip(), "a skip marker needs a reason"
        assert body.strip(), "an empty block"


#: The skip reason of a guide's block that repeats README commands (run once, by the README).
REPEATED = "the README's own commands, which the README test runs"


def test_a_block_skipped_as_repeated_repeats_the_readme_verbatim():
    readme = REPO / "README.md"
    ran = {c for lang, body, why in _blocks_of(readme) if why is None for c in shell_commands(body)}
    repeated = [body for lang, body, why in readme_blocks() if why and why.strip() == REPEATED]
    assert repeated, "no guide block is marked as repeating the README"
    for body in repeated:
        missing = [c for c in shell_commands(body) if c not in ran]
        assert not missing, f"marked as README commands but not run by the README: {missing}"


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    """``work/`` with the repository's folders linked in, beside ``shared`` (the data folder
    when it exists), so that relative paths in the README resolve as from a clone."""
    root = tmp_path_factory.mktemp("readme")
    work = root / "work"
    work.mkdir()
    for name in ("torchfmap", "examples", "bench"):
        (work / name).symlink_to(REPO / name)
    if SHARED.exists():
        (root / "shared").symlink_to(SHARED)
    return work


@pytest.mark.slow
def test_readme_runs(workdir, monkeypatch):
    """All runnable blocks in order (python and shell share the working folder, so a file one
    writes, e.g. ``model.ckpt``, is there for the next)."""
    monkeypatch.chdir(workdir)
    env = {**os.environ, "XDG_CACHE_HOME": str(workdir / "cache"), "MPLBACKEND": "Agg"}
    monkeypatch.setenv("XDG_CACHE_HOME", env["XDG_CACHE_HOME"])
    monkeypatch.setenv("MPLBACKEND", "Agg")
    bindir = str(Path(sys.executable).parent)
    env["PATH"] = bindir + os.pathsep + env.get("PATH", "")
    ran = 0
    for lang, body, why in readme_blocks():
        if why is not None or lang == "text":
            continue
        if "../shared/data" in body and not SHARED.exists():
            continue
        if lang == "python":
            exec(compile(body, "README.md", "exec"), {"__name__": "__readme__"})  # self-contained
        else:
            for command in shell_commands(body):
                command = re.sub(r"^python3 ", f"{sys.executable} ", command)
                done = subprocess.run(
                    command, shell=True, env=env, capture_output=True, text=True, timeout=900
                )
                assert done.returncode == 0, f"{command}\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"
        ran += 1
    assert ran >= 6  # the blocks above exist and ran
