"""``torch`` for the classical modules, imported on first attribute access, so that ``import
torchfmap`` stays light (``torchfmap.nn`` imports torch directly)."""

from __future__ import annotations

import importlib
from types import ModuleType


class LazyModule:
    """Attribute access goes to the module ``name``, imported on the first access."""

    def __init__(self, name: str) -> None:
        self._name = name

    def _module(self) -> ModuleType:
        return importlib.import_module(self._name)

    def __getattr__(self, attribute: str):
        return getattr(self._module(), attribute)

    def __repr__(self) -> str:
        return f"<lazy module {self._name!r}>"


torch = LazyModule("torch")
