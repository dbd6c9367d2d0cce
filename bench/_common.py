"""Helpers shared by every benchmark script in ``bench/``.

Importing this module puts the repository root first on ``sys.path``, so ``import torchfmap`` in
a script run as ``python3 bench/x.py`` loads this checkout, not an installed copy. Import it
before ``torchfmap``.

- output: :func:`fmt` (one number format), :func:`markdown` (one table format), :class:`Report`
  (prints sections to stdout and writes them to ``bench/results/<name>.md``), :func:`log`
  (progress to stderr);
- data: :func:`data_path` / :func:`require_data`, the only place that knows ``../shared/data``;
- timing: :func:`timed` (median of repeats), :func:`load1` / :func:`load_note` (load average, since
  another job may share the CPUs), :func:`traced_peak_mib` and :func:`status_mib` (memory).
"""

from __future__ import annotations

import gc
import math
import os
import statistics
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable, Iterable, Mapping, Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

BENCH_DIR = Path(__file__).resolve().parent
REPO_ROOT = BENCH_DIR.parent
#: Regenerated tables (git-ignored).
RESULTS_DIR = BENCH_DIR / "results"
#: Real meshes (TOSCA etc.), next to the repository, not part of it.
DATA_DIR = REPO_ROOT.parent / "shared" / "data"
MiB = 2**20

if str(REPO_ROOT) not in sys.path[:1]:
    sys.path.insert(0, str(REPO_ROOT))


# -- progress and load -------------------------------------------------------------------------
def log(msg: str) -> None:
    """Progress to stderr (tables go to stdout)."""
    print(msg, file=sys.stderr, flush=True)


def load1() -> float:
    """1-minute load average, recorded beside timings on a shared machine."""
    return os.getloadavg()[0]


def load_note() -> str:
    """``'load average 1/5/15 min a/b/c'``."""
    return "load average 1/5/15 min " + "/".join(f"{x:.1f}" for x in os.getloadavg())


def versions(*packages: str) -> str:
    """``'N CPUs; numpy x, scipy y, ...'`` for the table headers."""
    parts = [f"{os.cpu_count()} CPUs"]
    for name in ("numpy", *packages):
        try:
            parts.append(f"{name} {version(name)}")
        except PackageNotFoundError:
            parts.append(f"{name} (not installed)")
    return parts[0] + "; " + ", ".join(parts[1:])


# -- data --------------------------------------------------------------------------------------
def data_path(name: str) -> Path | None:
    """``<repo>/../shared/data/<name>`` (e.g. ``'tosca5k_dev/cat0.off'``), or None if absent."""
    path = DATA_DIR / name
    return path if path.exists() else None


def require_data(name: str) -> Path:
    """:func:`data_path`, or exit with a one-line message (no traceback) when it is absent."""
    path = data_path(name)
    if path is None:
        raise SystemExit(f"skipped: {DATA_DIR / name} not found (real meshes live in ../shared/data)")
    return path


def smal_split() -> tuple[list[str], list[str]]:
    """``(train, val)`` names of the ``smal_r_train`` animals for learned recipes: every 4th of
    the sorted names validates (8 of 32), the other 24 train; SMAL_r's own test split stays
    held out."""
    names = sorted(p.name.split(".")[0] for p in require_data("smal_r_train").glob("*.off.gz"))
    val = names[::4]
    return [n for n in names if n not in val], val


# -- formatting --------------------------------------------------------------------------------
def fmt(x: Any, digits: int | None = None) -> str:
    """One cell: floats with ``digits`` decimals if given, else 3 significant-ish (``.2e`` if tiny
    or huge, ``.3f`` below 100, ``.0f`` above); ints with thousands separators; the rest ``str``."""
    if isinstance(x, bool):
        return str(x)
    if isinstance(x, float):
        if math.isnan(x):
            return "nan"
        if digits is not None:
            return f"{x:.{digits}f}" if abs(x) < 100 else f"{x:.0f}"
        if x == 0.0:
            return "0"
        if abs(x) < 1e-3 or abs(x) >= 1e6:
            return f"{x:.2e}"
        return f"{x:.3f}" if abs(x) < 100 else f"{x:.0f}"
    if isinstance(x, int) or type(x).__name__.startswith(("int", "uint")):
        return f"{int(x):,}"
    return str(x)


def markdown(rows: Iterable[Mapping[str, Any] | Sequence[Any]], columns: Sequence[str] | None = None) -> str:
    """A markdown table. Rows are dicts (missing keys: empty cells) or sequences in column order;
    ``columns`` defaults to the keys of the dict rows in order of appearance."""
    rows = list(rows)
    if columns is None:
        columns = list(dict.fromkeys(c for r in rows if isinstance(r, Mapping) for c in r))

    def cell(x: Any) -> str:
        return fmt(x).replace("|", "\\|")  # a literal pipe would split the cell

    def line(cells: Iterable[Any]) -> str:
        return "| " + " | ".join(cell(c) for c in cells) + " |"

    out = [line(columns), "|" + "|".join("---" for _ in columns) + "|"]
    for r in rows:
        out.append(line(r.get(c, "") for c in columns) if isinstance(r, Mapping) else line(r))
    return "\n".join(out)


def int_list(text: str) -> list[int]:
    """``'5,10,20'`` -> ``[5, 10, 20]``."""
    return [int(s) for s in text.split(",") if s.strip()]


def str_list(text: str) -> list[str]:
    """``'a, b,'`` -> ``['a', 'b']``."""
    return [s.strip() for s in text.split(",") if s.strip()]


# -- results -----------------------------------------------------------------------------------
def write_results(name: str, text: str, folder: Path | None = None) -> Path:
    """Write ``<folder>/<name>.md`` (default ``bench/results``): temporary file, then rename."""
    folder = RESULTS_DIR if folder is None else Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.md"
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text.rstrip("\n") + "\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


class Report:
    """Sections printed to stdout as they come and written together to ``<name>.md``."""

    def __init__(self, name: str, folder: Path | None = None) -> None:
        self.name, self.folder = name, folder
        self.parts: list[str] = []

    def add(self, *texts: str) -> None:
        """Print ``texts`` (one paragraph each, blank line after) and keep them for :meth:`save`."""
        for text in texts:
            print(text + "\n", flush=True)
            self.parts.append(text)

    def table(self, title: str, rows, columns: Sequence[str] | None = None, note: str = "") -> None:
        """``### title``, the table of ``rows`` and an optional note below it."""
        self.add(f"### {title}" if not title.startswith("#") else title, markdown(rows, columns))
        if note:
            self.add(note)

    def save(self) -> Path:
        path = write_results(self.name, "\n\n".join(self.parts), self.folder)
        log(f"tables written to {path}")
        return path


# -- timing and memory -------------------------------------------------------------------------
def timed(
    fn: Callable[[], Any], repeats: int = 1, *, warmup: int = 0, max_repeat_s: float = math.inf
) -> tuple[float, int, Any]:
    """``(median seconds, calls timed, last result)`` of up to ``repeats`` calls after ``warmup``
    untimed ones; just one timed call if the first takes longer than ``max_repeat_s``. The previous
    result is freed (and ``gc.collect()`` run) before every timed call."""
    out = None
    for _ in range(warmup):
        out = fn()
    times: list[float] = []
    for _ in range(max(1, repeats)):
        out = None
        gc.collect()
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
        if times[0] > max_repeat_s:
            break
    return statistics.median(times), len(times), out


def traced_peak_mib(fn: Callable[[], Any]) -> tuple[float, Any]:
    """tracemalloc peak (MiB) above the start during one call of ``fn``, and its result.

    tracemalloc sees Python/numpy allocations only, not memory inside C/C++/Fortran libraries.
    """
    gc.collect()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        out = fn()
        return (tracemalloc.get_traced_memory()[1] - base) / MiB, out
    finally:
        tracemalloc.stop()


def status_mib(key: str) -> float:
    """A ``/proc/self/status`` entry (``VmRSS``, ``VmHWM``) in MiB; nan where unavailable."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def reset_peak_rss() -> bool:
    """Reset the ``VmHWM`` high-water mark (``/proc/self/clear_refs``); False where not allowed."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False
