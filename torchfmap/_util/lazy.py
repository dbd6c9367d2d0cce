"""``torch`` for the classical modules, imported on first use.

The classical path (meshes, operators, bases, the default feature-aware ``match``) needs no
torch; the functional-map core and the sparse conversions do. They use :data:`torch`, a stand-in
whose first attribute access imports torch (about a second), so ``import torchfmap`` stays
light. ``torchfmap.nn`` imports torch directly.
"""

from __future__ import annotations

import importlib
from types import ModuleType


class LazyModule:
    """Attribute access goes to the module ``name``, imported on the first access."""

    def __init__(self, name: str) -> None:
        self._name = name

    def _module(self) -> ModuleType:
        return importlib.import_module(self._name)  # cached by Python in sys.modules

    def __getattr__(self, attribute: str):
        return getattr(self._module(), attribute)

    def __repr__(self) -> str:
        return f"<lazy module {self._name!r}>"


torch = LazyModule("torch")
