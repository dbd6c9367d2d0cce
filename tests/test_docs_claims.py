"""The docs' checkable claims against the code: counts (shipped models), lists (the landmark
default's candidates), the quick start's extras and the extras the README names. Names the docs
cite are checked by ``test_docs_names.py``; figures live in ``bench/results``."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from torchfmap.matching.landmark_default import AUTO_KINDS
from torchfmap.nn.shipped import shipped_models

ROOT = Path(__file__).resolve().parents[1]
DOCS = {p.name: p.read_text() for p in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]}
WORDS = ["zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten"]


def _counted(pattern: str) -> list[tuple[str, int]]:
    """``(doc, count)`` for every '<number word> <pattern>' in the docs."""
    found = []
    for name, text in DOCS.items():
        for m in re.finditer(rf"\b({'|'.join(WORDS)})\s+{pattern}", text, flags=re.IGNORECASE):
            found.append((name, WORDS.index(m.group(1).lower())))
    return found


def test_the_count_of_shipped_models():
    claims = _counted(r"(pretrained models|networks are shipped|shipped models)")
    assert claims, "the README says how many models are shipped"
    n = len(shipped_models())
    assert all(count == n for _, count in claims), (claims, n)


def test_the_landmark_defaults_candidates():
    """The kinds table says which kinds ``basis='auto'`` chooses among, and how many."""
    table = DOCS["architecture.md"]
    rows = dict(re.findall(r"^\| `(\w+)` \| (.*) \|$", table, flags=re.MULTILINE))
    assert set(AUTO_KINDS) <= set(rows)
    for kind, text in rows.items():
        says = "candidate" in text and "not a candidate" not in text
        assert says == (kind in AUTO_KINDS), (kind, text)
    for _, count in _counted(r"candidates of `basis='auto'`"):
        assert count == len(AUTO_KINDS)


def test_the_quick_start_and_the_extras():
    """The extras the docs say the quick start installs are the ones it installs, and every extra
    the README describes is one pyproject.toml defines, and the other way round."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    readme = DOCS["README.md"]
    install = re.search(r'pip install "\.\[([\w,]+)\]"', readme)
    assert install, "the README's quick start installs the package with extras"
    quick = set(install.group(1).split(","))
    for name, text in DOCS.items():
        for m in re.finditer(r"quick[- ]start'?s?\s+`?(?:pip install \"\.)?\[([\w,]+)\]", text):
            assert set(m.group(1).split(",")) == quick, (name, m.group(0))
    extras = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"])
    sentence = readme[readme.index("Extras:") :].split("\n\n")[0]
    assert set(re.findall(r"`(\w+)`\s+\(", sentence)) == extras, sentence


def test_the_first_install_line_needs_only_pypi():
    """The quick start's first command works wherever pip reaches PyPI; PyTorch's own wheel index
    (unreachable offline: pip retries for minutes) is named after it, for the CPU build."""
    readme = DOCS["README.md"]
    block = readme[readme.index("## Install") :].split("```bash")[1].split("```")[0]
    first = next(line for line in block.splitlines() if "pip install" in line)
    assert "--index-url" not in first and "download.pytorch.org" not in first, first
