"""A status line of named steps for long computations (:func:`torchfmap.match`'s ``progress``):
tqdm on stderr, naming the step that runs and the time since the start; nothing when disabled."""

from __future__ import annotations

from tqdm import tqdm


class Steps:
    """``steps('name')`` shows that step ``name`` starts now (the one before has ended), as
    ``desc: name [elapsed]``; ``close()`` (or leaving a ``with`` block) removes the line.
    Disabled (``enabled=False``, e.g. :data:`SILENT`), it holds nothing and shows nothing."""

    def __init__(self, desc: str, enabled: bool = True) -> None:
        self.desc = desc
        self._bar = tqdm(desc=desc, leave=False, bar_format="{desc} [{elapsed}]") if enabled else None

    def __call__(self, name: str) -> None:
        if self._bar is not None:
            self._bar.set_description_str(f"{self.desc}: {name}")  # redraws the line

    @property
    def enabled(self) -> bool:
        """Whether the line is shown (for callers that pass the choice on, e.g. to a bar)."""
        return self._bar is not None

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def __enter__(self) -> Steps:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: A disabled :class:`Steps` (no bar, no state): the default of the functions that take one.
SILENT = Steps("", enabled=False)
