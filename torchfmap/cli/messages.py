"""The command line's one-line errors and warnings, the library's fixes said in flags."""

from __future__ import annotations

import re
import sys

#: The library's fixes in Python terms -> the same fix in the command line's terms.
CLI_TERMS = (
    (re.compile(r"`?allow_components=True`?"), "--allow-components"),
    (re.compile(r"`?basis='(\w+)'`?"), r"--basis \1"),
    (re.compile(r"`?refine='(\w+)'`?"), r"--refine \1"),
    (re.compile(r"`?k_final( >=| =)"), r"--k-final\1"),
    (re.compile(r"\bk_final=(\d+)"), r"--k-final \1"),
    (re.compile(r"drop k_final"), "drop --k-final"),
    (re.compile(r"drop times\b"), "drop --times"),
    (re.compile(r"\btimes are the heat times"), "--times are the heat times"),
    (re.compile(r"`?w_lap=([\w.]+)`?"), r"--w-lap \1"),
    (re.compile(r"`?identity=True`? \(CLI: --gt identity\)"), "--gt identity"),
    (re.compile(r"match\(whole, part, partial=True\) \(torchfmap match WHOLE PART --partial\)"), "--partial"),
    (re.compile(r"match\(whole, part, partial=True\)"), "torchfmap match WHOLE PART --partial"),
    (re.compile(r"\bpartial=True"), "--partial"),
    (
        re.compile(
            r"pass allow_unreferenced=True to load the mesh as it is and work on `mesh\.referenced\(\)`"
        ),
        "load it in Python with allow_unreferenced=True and save `mesh.referenced()`",
    ),
    (re.compile(r"the weights \(w_lap, w_orient\)"), "the weight --w-lap"),
    (re.compile(r"\(CLI: ([^)]*)\)"), r"(\1)"),
    (re.compile(r"keep one with `mesh\.largest_component\(\)`, or"), "keep the largest component, or"),
    (re.compile(r"\bk \(basis size\)"), "--k (basis size, default 50)"),
    (re.compile(r"\bmesh_x\b"), "the source mesh"),
    (re.compile(r"\bmesh_y\b"), "the target mesh"),
)


def in_cli_terms(text: str) -> str:
    """A library message with its Python fixes (``basis='x'``) said as flags (``--basis x``)."""
    for pattern, flag in CLI_TERMS:
        text = pattern.sub(flag, text)
    return text


def error_line(err: BaseException) -> str:
    """``torchfmap: error: ...``, naming the error class where it says more than 'error'."""
    name = type(err).__name__
    text = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
    text = in_cli_terms(text)
    plain = name in ("TorchFmapError", "FileWriteError", "FileReadError")
    return f"torchfmap: error: {text}" if plain else f"torchfmap: error ({name}): {text}"


def warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` of the command line: ``torchfmap: warning: <message>`` on stderr."""
    print(f"torchfmap: warning: {in_cli_terms(str(message))}", file=sys.stderr)
