"""Old names kept working for a while: renamed keyword arguments and moved or renamed module
attributes warn (``DeprecationWarning``) with the new name, then behave as the new one.

One home for the project's deprecation aliases, so each says the same thing and is found in
one place when the old names are finally dropped.
"""

from __future__ import annotations

import functools
import importlib
import warnings


def warn_renamed(old: str, new: str, *, stacklevel: int = 3) -> None:
    """Warn that ``old`` is now ``new`` (a ``DeprecationWarning`` pointing at the caller)."""
    message = f"{old} is now {new}. Fix: use {new}, same meaning."
    warnings.warn(message, DeprecationWarning, stacklevel=stacklevel)


def _called_name(func) -> str:
    """How a user calls ``func``: its name, or its class's for a constructor (``Column(...)``)."""
    return func.__qualname__.removesuffix(".__init__") if func.__name__ == "__init__" else func.__name__


def renamed_keywords(**old_to_new: str):
    """Decorator: keyword arguments under their old names (``old=new`` pairs) are passed on under
    the new ones, with a warning; giving both raises ``TypeError``. The signature users see is the
    new one (``functools.wraps``)."""

    def wrap(func):
        @functools.wraps(func)
        def inner(*args, **kwargs):
            for old, new in old_to_new.items():
                if old in kwargs:
                    # a class's constructor is named as the class is called: Column(kind=...)
                    name = (
                        func.__qualname__.removesuffix(".__init__")
                        if func.__name__ == "__init__"
                        else func.__name__
                    )
                    if new in kwargs:
                        raise TypeError(f"{name}() got both {old}= (the old name) and {new}=.")
                    warn_renamed(f"{name}({old}=...)", f"{name}({new}=...)")
                    kwargs[new] = kwargs.pop(old)
            return func(*args, **kwargs)

        return inner

    return wrap


def module_aliases(module: str, aliases: dict[str, str]):
    """A module ``__getattr__`` serving old attribute names: ``aliases`` maps each old name to
    ``'new'`` (an attribute of ``module`` itself) or ``'package.module.new'`` (elsewhere)."""

    def __getattr__(name: str):
        if name not in aliases:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        target = aliases[name]
        where, _, attr = target.rpartition(".")
        where = where or module
        warn_renamed(f"{module}.{name}", f"{where}.{attr}")
        return getattr(importlib.import_module(where), attr)

    return __getattr__
