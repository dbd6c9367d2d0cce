"""Every public callable is exercised by at least one test module (a textual check): every
public *function* is called in a test (``name(`` appears), every public class is named (built,
raised or checked with ``isinstance``; exceptions and result types are not built by users).

The public API is ``__all__`` of each package that defines one; modules without ``__all__``
(``eval``, ``descriptors``, ``seeds``) contribute the public functions and classes they define
themselves (names not starting with ``_`` whose ``__module__`` is that module).
"""

from __future__ import annotations

import importlib
import inspect
import re
from pathlib import Path

MODULES = (
    "torchfmap",
    "torchfmap.bases",
    "torchfmap.operators",
    "torchfmap.fmap",
    "torchfmap.data",
    "torchfmap.nn",
    "torchfmap.nn.functional",
    "torchfmap.evaluate.scores",
    "torchfmap.descriptors",
    "torchfmap.seeds",
)
TESTS = Path(__file__).resolve().parent


def public_callables(module_name: str) -> dict[str, object]:
    module = importlib.import_module(module_name)
    names = getattr(module, "__all__", None)
    if names is None:
        names = [
            n
            for n, obj in vars(module).items()
            if not n.startswith("_") and getattr(obj, "__module__", None) == module_name
        ]
    return {
        n: getattr(module, n)
        for n in names
        if callable(getattr(module, n)) and not inspect.ismodule(getattr(module, n))
    }


def test_every_public_callable_appears_in_a_test():
    text = "\n".join(
        p.read_text(encoding="utf-8")
        for p in sorted(TESTS.rglob("test_*.py"))
        if p.name != Path(__file__).name
    )
    missing = []
    for module_name in MODULES:
        for name, obj in sorted(public_callables(module_name).items()):
            called = rf"\b{re.escape(name)}\(" if inspect.isfunction(obj) else rf"\b{re.escape(name)}\b"
            if not re.search(called, text):
                missing.append(f"{module_name}.{name}")
    assert not missing, (
        f"public functions never called (classes never named) in tests/**/test_*.py: {missing}"
    )


def test_collection_finds_the_api():
    """Guard against a vacuous pass: the collection must see well-known names."""
    assert "solve_fmap" in public_callables("torchfmap.fmap")
    assert "hks" in public_callables("torchfmap.descriptors")
    assert "bijectivity_error" in public_callables("torchfmap.evaluate.scores")
    assert "SoftPointMap" in public_callables("torchfmap.nn")
