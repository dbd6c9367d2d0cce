"""A tqdm status line of named steps for long computations (:func:`torchfmap.match`'s ``progress``)."""

from __future__ import annotations

from tqdm import tqdm


class Steps:
    """``steps('name')`` shows ``desc: name [elapsed]`` on stderr; ``close()`` (or leaving a ``with``
    block) removes the line. Disabled (``enabled=False``, e.g. :data:`SILENT`), it shows nothing."""

    def __init__(self, desc: str, enabled: bool = True) -> None:
        self.desc = desc
        self._bar = tqdm(desc=desc, leave=False, bar_format="{desc} [{elapsed}]") if enabled else None

    def __call__(self, name: str) -> None:
        if self._bar is not None:
            self._bar.set_description_str(f"{self.desc}: {name}")

    @property
    def enabled(self) -> bool:
        """Whether the line is shown."""
        return self._bar is not None

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def __enter__(self) -> Steps:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: A disabled :class:`Steps`: the default of the functions that take one.
SILENT = Steps("", enabled=False)
