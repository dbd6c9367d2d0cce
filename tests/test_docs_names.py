"""README.md and docs/*.md against the code: every name they cite in backticks that looks
like code (a dotted path, a call, a class or a constant) exists in torchfmap (or is an external
library's, a builtin, or a field of the object it is read from); and their checkable claims
(the shipped-model count, the landmark default's candidates, the quick start's extras, the
first install line). Figures live in ``bench/results``."""

from __future__ import annotations

import builtins
import dataclasses
import importlib
import inspect
import pkgutil
import re
from pathlib import Path

import pytest

import torchfmap
from torchfmap.matching.landmark_default import AUTO_KINDS
from torchfmap.nn.shipped import shipped_models

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
DOC_TEXTS = {p.name: p.read_text() for p in DOCS}
#: Prefixes of names that belong to other libraries (or to Python / math notation).
EXTERNAL = {
    "torch", "np", "numpy", "scipy", "trimesh", "potpourri3d", "pymeshlab", "plotly", "matplotlib",
    "os", "sys", "tqdm", "pytest", "pyFM", "math", "sqrt", "exp", "diag", "argparse", "pip", "K_t",
}  # fmt: skip
#: Names of variables in the docs and the class whose attribute they read (``result.kind``).
VARIABLES = {
    "result": "MatchResult", "mesh": "Mesh", "basis": "Basis", "shape": "PreparedShape",
    "KINDS": "BasisKind", "kind": "BasisKind", "config": "TrainConfig", "Column": "Column",
}  # fmt: skip
#: Module-level names of the test files (the docs cite a few, e.g. ``LAZY_TORCH``).
TEST_NAMES = {
    m.group(1)
    for path in Path(__file__).parent.rglob("*.py")
    for m in re.finditer(r"^([A-Z][A-Z0-9_]*)\s*[:=]", path.read_text(encoding="utf-8"), flags=re.M)
}
SPAN = re.compile(r"`([^`\n]+)`")
NAME = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*")
FILE = re.compile(r"\.(py|md|txt|npz|ckpt|off|ply|obj|png|csv|html|gz|toml|vts|yaml|sh|json|pt)$")


def _modules() -> dict:
    mods = {"torchfmap": torchfmap}
    for info in pkgutil.walk_packages(torchfmap.__path__, "torchfmap."):
        if not info.name.endswith("__main__"):
            mods[info.name] = importlib.import_module(info.name)
    return mods


MODULES = _modules()
CLASSES = {
    name: obj
    for mod in MODULES.values()
    for name, obj in vars(mod).items()
    if inspect.isclass(obj) and getattr(obj, "__module__", "").startswith("torchfmap")
}


def _has(obj, name: str):
    """``(found, value)``: an attribute, a submodule or a dataclass field of ``obj``."""
    if hasattr(obj, name):
        return True, getattr(obj, name)
    sub = f"{getattr(obj, '__name__', '')}.{name}"
    if inspect.ismodule(obj) and sub in MODULES:
        return True, MODULES[sub]
    if inspect.isclass(obj) and dataclasses.is_dataclass(obj) and name in obj.__dataclass_fields__:
        return True, None
    if inspect.isclass(obj) and name in getattr(obj, "__annotations__", {}):
        return True, None
    return False, None


def _chain(obj, parts) -> bool:
    for part in parts:
        if obj is None:  # a field: its own attributes are not checked
            return True
        found, obj = _has(obj, part)
        if not found:
            return False
    return True


def resolves(dotted: str) -> bool:
    parts = dotted.split(".")
    head = parts[0]
    if head in EXTERNAL or hasattr(builtins, head) or dotted in TEST_NAMES:
        return True
    if head in ("torchfmap", "tf"):  # the README's snippets import torchfmap as tf
        return _chain(torchfmap, parts[1:])
    if head in VARIABLES and _chain(CLASSES[VARIABLES[head]], parts[1:]):
        return True
    roots = [torchfmap, *(m for n, m in MODULES.items() if n.split(".")[-1] == head)]
    if _chain(torchfmap, parts) or any(_chain(m, parts[1:]) for m in roots[1:]):
        return True
    owners = [*MODULES.values(), *CLASSES.values()]  # a bare name or a method, wherever it lives
    return any(_chain(owner, parts) for owner in owners)


def cited_names(text: str) -> set[str]:
    """Backticked spans of ``text`` (outside code blocks) that look like code names."""
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    out = set()
    for span in SPAN.findall(text):
        bare = re.sub(r"\[[^\]]*\]", "", span).strip()  # KINDS["x"].y -> KINDS.y
        call = re.match(r"([A-Za-z_][\w.]*)\(", bare)
        name = call.group(1) if call else bare
        if not NAME.fullmatch(name) or FILE.search(name):
            continue
        dotted = "." in name
        cls = re.fullmatch(r"[A-Z][a-z0-9]+[A-Z]\w*", name)
        const = re.fullmatch(r"[A-Z][A-Z0-9]*_[A-Z0-9_]+", name)
        if dotted or call or cls or const:
            out.add(name)
    return out


def test_the_checker_flags_a_missing_name_and_accepts_real_ones():
    found = cited_names(
        "`torchfmap.match`, `pipeline.no_such_thing`, `W_LAP_SMOOTH`, `k` and `fmap_to_p2p(C)`"
    )
    assert found == {"torchfmap.match", "pipeline.no_such_thing", "W_LAP_SMOOTH", "fmap_to_p2p"}
    assert resolves("torchfmap.match") and resolves("fmap_to_p2p") and resolves("result.kind")
    assert not resolves("pipeline.no_such_thing")


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_every_name_the_docs_cite_exists(doc):
    if not doc.exists():
        pytest.skip(f"{doc.name} is not next to the tests (installed package)")
    missing = sorted(n for n in cited_names(doc.read_text(encoding="utf-8")) if not resolves(n))
    assert not missing, f"{doc.name} cites names the code does not have: {missing}"


WORDS = ["zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten"]


def _counted(pattern: str) -> list[tuple[str, int]]:
    """``(doc, count)`` for every '<number word> <pattern>' in the docs."""
    found = []
    for name, text in DOC_TEXTS.items():
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
    table = DOC_TEXTS["architecture.md"]
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
    readme = DOC_TEXTS["README.md"]
    install = re.search(r'pip install "\.\[([\w,]+)\]"', readme)
    assert install, "the README's quick start installs the package with extras"
    quick = set(install.group(1).split(","))
    for name, text in DOC_TEXTS.items():
        for m in re.finditer(r"quick[- ]start'?s?\s+`?(?:pip install \"\.)?\[([\w,]+)\]", text):
            assert set(m.group(1).split(",")) == quick, (name, m.group(0))
    extras = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"])
    sentence = readme[readme.index("Extras:") :].split("\n\n")[0]
    assert set(re.findall(r"`(\w+)`\s+\(", sentence)) == extras, sentence


def test_the_first_install_line_needs_only_pypi():
    """The quick start's first command works wherever pip reaches PyPI; PyTorch's own wheel index
    (unreachable offline: pip retries for minutes) is named after it, for the CPU build."""
    readme = DOC_TEXTS["README.md"]
    block = readme[readme.index("## Install") :].split("```bash")[1].split("```")[0]
    first = next(line for line in block.splitlines() if "pip install" in line)
    assert "--index-url" not in first and "download.pytorch.org" not in first, first
