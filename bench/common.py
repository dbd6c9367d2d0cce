"""What every case of every suite shares: settings, the results writer, number and table format,
timing and memory, the real-data folder and the synthetic test meshes.

- settings: :class:`Settings` (a case's merged configuration, read as attributes);
- output: :func:`fmt` (one number format), :func:`markdown` (one table format), :class:`Report`
  (sections printed to stdout and written together to ``bench/results/<suite>_<case>.md``, the
  rows to ``.csv``, an optional ``.png``), :func:`log` (progress to stderr);
- data: :func:`data_path` / :func:`require_data` (:class:`Skip` when absent), the only place that
  knows ``../shared/data``; :func:`bench_mesh` (irregular closed synthetic meshes);
- timing: :func:`timed` (median of repeats), :func:`attempt` (a failure becomes a table cell),
  :func:`load1` / :func:`load_note` (load average, since another job may share the CPUs),
  :func:`traced_peak_mib`, :func:`status_mib`, :func:`reset_peak_rss` (memory).
"""

from __future__ import annotations

import csv
import gc
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
import tracemalloc
from collections.abc import Callable, Iterable, Mapping, Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull

import torchfmap

BENCH_DIR = Path(__file__).resolve().parent
REPO_ROOT = BENCH_DIR.parent
CONFIG_DIR = BENCH_DIR / "configs"
RESULTS_DIR = BENCH_DIR / "results"
#: Real meshes (TOSCA, FAUST_r, SMAL_r...), next to the repository, not part of it
#: (``python -m bench ... --data FOLDER`` points elsewhere).
DATA_DIR = REPO_ROOT.parent / "shared" / "data"
#: Derived dev data (``python -m tools.remesh``), git-ignored.
LOCAL_DATA_DIR = BENCH_DIR / "data"
MiB = 2**20


class Skip(Exception):
    """A case cannot run here (data or an optional library absent): reported, not a failure."""


class Settings(dict):
    """A case's settings (defaults of ``bench/configs/<suite>.json``, then ``--quick``, ``--config``
    and ``--set``), read as attributes: ``cfg.k``. A missing key raises ``KeyError`` naming it."""

    def __getattr__(self, key: str) -> Any:
        try:
            return self[key]
        except KeyError:
            raise AttributeError(f"setting {key!r} is not in this case's configuration") from None


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
    """``'N CPUs; numpy x, scipy y, ...'`` for the report headers."""
    parts = []
    for name in ("numpy", *packages):
        try:
            parts.append(f"{name} {version(name)}")
        except PackageNotFoundError:
            parts.append(f"{name} (not installed)")
    return f"{os.cpu_count()} CPUs; " + ", ".join(parts)


def code_state() -> str:
    """``git describe`` of the checkout (which code the figures are of)."""
    try:
        cmd = ["git", "describe", "--always", "--dirty"]
        out = subprocess.run(cmd, cwd=REPO_ROOT, capture_output=True, text=True, check=False).stdout.strip()
    except OSError:
        out = ""
    return f"git {out or '?'}"


# -- data --------------------------------------------------------------------------------------
def data_path(name: str) -> Path | None:
    """``<data>/<name>`` (e.g. ``'tosca5k_dev/cat0.off'``), or None if absent."""
    path = DATA_DIR / name
    return path if path.exists() else None


def require_data(name: str) -> Path:
    """:func:`data_path`, or :class:`Skip` naming what is missing."""
    path = data_path(name)
    if path is None:
        raise Skip(f"{DATA_DIR / name} not found (real meshes live in ../shared/data; --data FOLDER)")
    return path


_BUMP_CENTRES = np.array([[0.0, 0.0, 1.0], [1.0, 0.3, -0.2], [-0.5, -0.8, 0.1], [0.2, 0.9, -0.6]])
_BUMP_WIDTHS = np.array([0.5, 0.35, 0.7, 0.25])
_BUMP_HEIGHTS = np.array([1.0, 0.8, -0.6, 0.9])


def bench_mesh(n_vertices: int, seed: int = 0):
    """An irregular closed genus-0 :class:`torchfmap.Mesh` with exactly ``n_vertices`` vertices.

    Fibonacci-sphere points get a deterministic tangential jitter (a fifth of the point spacing),
    are triangulated by their convex hull (faces oriented outward), then displaced radially by
    ``r = 1 + 0.3 * sum_k h_k exp(-(d_k / w_k)^2)`` (``d_k`` the angular distance to bump ``k``)
    and stretched by 1.6 along x, so the surface is neither a sphere nor convex.
    """
    if n_vertices < 4:
        raise ValueError(f"bench_mesh needs at least 4 vertices, got {n_vertices}.")
    k = np.arange(n_vertices) + 0.5
    z = 1.0 - 2.0 * k / n_vertices
    rho, phi = np.sqrt(1.0 - z**2), np.pi * (3.0 - np.sqrt(5.0)) * k
    p = np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)
    jitter = np.random.default_rng(seed).normal(size=p.shape) * 0.2 * np.sqrt(4.0 * np.pi / n_vertices)
    jitter -= np.einsum("ij,ij->i", jitter, p)[:, None] * p  # keep it tangential
    p = p + jitter
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    hull = ConvexHull(p)
    if len(hull.vertices) != n_vertices:
        raise RuntimeError(f"convex hull used {len(hull.vertices)} of {n_vertices} points.")
    f = hull.simplices.astype(np.int64)
    x = p[f]
    normals = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    inward = np.einsum("ij,ij->i", normals, x.sum(axis=1)) < 0  # the hull contains the origin
    f[inward] = f[inward][:, ::-1]
    centres = _BUMP_CENTRES / np.linalg.norm(_BUMP_CENTRES, axis=1, keepdims=True)
    angle = np.arccos(np.clip(p @ centres.T, -1.0, 1.0))
    r = 1.0 + 0.3 * (_BUMP_HEIGHTS * np.exp(-((angle / _BUMP_WIDTHS) ** 2))).sum(axis=1)
    return torchfmap.Mesh(p * r[:, None] * np.array([1.6, 1.0, 1.0]), f, name=mesh_name(n_vertices))


def mesh_name(n: int) -> str:
    """``'bench5K'`` for 5000 vertices, ``'bench1234'`` otherwise."""
    return f"bench{n // 1000}K" if n % 1000 == 0 else f"bench{n}"


# -- formatting --------------------------------------------------------------------------------
def fmt(x: Any, digits: int | None = None) -> str:
    """One cell: floats with ``digits`` decimals if given, else 3 significant-ish (``.2e`` if tiny
    or huge, ``.3f`` below 100, ``.0f`` above); ints with thousands separators; the rest ``str``."""
    if isinstance(x, (bool, np.bool_)):
        return str(bool(x))
    if isinstance(x, (float, np.floating)):
        x = float(x)
        if math.isnan(x):
            return "nan"
        if digits is not None:
            return f"{x:.{digits}f}" if abs(x) < 100 else f"{x:.0f}"
        if x == 0.0:
            return "0"
        if abs(x) < 1e-3 or abs(x) >= 1e6:
            return f"{x:.2e}"
        return f"{x:.3f}" if abs(x) < 100 else f"{x:.0f}"
    if isinstance(x, (int, np.integer)):
        return f"{int(x):,}"
    return str(x)


def markdown(rows: Iterable[Mapping[str, Any] | Sequence[Any]], columns: Sequence[str] | None = None) -> str:
    """A markdown table. Rows are dicts (missing keys: empty cells) or sequences in column order;
    ``columns`` defaults to the keys of the dict rows in order of appearance."""
    rows = list(rows)
    if columns is None:
        columns = list(dict.fromkeys(c for r in rows if isinstance(r, Mapping) for c in r))

    def line(cells: Iterable[Any]) -> str:
        return "| " + " | ".join(fmt(c).replace("|", "\\|") for c in cells) + " |"

    out = [line(columns), "|" + "|".join("---" for _ in columns) + "|"]
    for r in rows:
        out.append(line(r.get(c, "") for c in columns) if isinstance(r, Mapping) else line(r))
    return "\n".join(out)


def nanmean(values: Iterable[float]) -> float:
    """Mean of ``values``, NaN when there is none (no warning)."""
    values = list(values)
    return float(np.mean(values)) if values else float("nan")


# -- the results writer ------------------------------------------------------------------------
def _atomic_write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


class Report:
    """One case's results: sections printed to stdout as they come and written together to
    ``<folder>/<stem>.md`` (``stem``: ``<suite>_<case>``, ``_<name>`` appended when a run is
    named), its raw rows to ``<stem>.csv`` (rewritten by :meth:`rows_csv` as runs finish), a
    figure to ``<stem>.png`` (:meth:`figure`; skipped with a note without matplotlib)."""

    def __init__(self, stem: str, folder: Path | None = None, header: str = "") -> None:
        self.stem, self.folder = stem, Path(folder or RESULTS_DIR)
        self.parts: list[str] = []
        self.files: list[Path] = []
        if header:
            self.add(header)

    def path(self, suffix: str) -> Path:
        return self.folder / f"{self.stem}{suffix}"

    def add(self, *texts: str) -> None:
        """Print ``texts`` (one paragraph each) and keep them for :meth:`save`."""
        for text in texts:
            if text:
                print(text + "\n", flush=True)
                self.parts.append(text)

    def table(self, title: str, rows, columns: Sequence[str] | None = None, note: str = "") -> None:
        """``### title``, the table of ``rows`` and an optional note below it."""
        self.add(title if title.startswith("#") else f"### {title}", markdown(rows, columns), note)

    def rows_csv(self, rows: list[dict]) -> Path:
        """All ``rows`` (dicts; the union of their keys) to ``<stem>.csv``."""
        keys = list(dict.fromkeys(k for r in rows for k in r))
        path = self.path(".csv")
        with tempfile.SpooledTemporaryFile(mode="w+", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=keys)
            writer.writeheader()
            writer.writerows(rows)
            fh.seek(0)
            _atomic_write(path, fh.read())
        if path not in self.files:
            self.files.append(path)
        return path

    def figure(self, draw: Callable[[Any], Any], *args, **kwargs) -> Path | None:
        """``draw(plt, *args, **kwargs)`` returns a matplotlib figure, saved to ``<stem>.png``."""
        try:
            import matplotlib

            matplotlib.use("Agg", force=False)
            import matplotlib.pyplot as plt
        except ImportError:
            self.add("(matplotlib not installed: no figure)")
            return None
        fig = draw(plt, *args, **kwargs)
        path = self.path(".png")
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.tight_layout()
        fig.savefig(path, dpi=120)
        plt.close(fig)
        self.files.append(path)
        self.add(f"Figure: `{path.name}`")
        return path

    def save(self) -> Path:
        path = self.path(".md")
        _atomic_write(path, "\n\n".join(self.parts).rstrip("\n") + "\n")
        log("written: " + ", ".join(str(p) for p in [path, *self.files]))
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


class Failed(str):
    """A table cell for an operation that raised (the traceback goes to stderr)."""


def attempt(label: str, fn: Callable[[], Any]) -> Any:
    """``fn()``, or a :class:`Failed` cell with the traceback logged if it raises."""
    try:
        return fn()
    except Exception as exc:  # noqa: BLE001 - a benchmark reports failures and carries on
        log(f"  !! {label} raised {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
        return Failed(f"ERROR {type(exc).__name__}")


def run_timed(label: str, fn: Callable[[], Any], repeats: int, max_repeat_s: float) -> tuple[Any, Any]:
    """``(median time, last result)`` of :func:`timed`, or ``(Failed cell, None)`` if ``fn`` raises."""
    res = attempt(label, lambda: timed(fn, repeats, max_repeat_s=max_repeat_s))
    return (res, None) if isinstance(res, Failed) else (res[0], res[2])


def traced_peak_mib(fn: Callable[[], Any]) -> tuple[float, Any]:
    """tracemalloc peak (MiB) above the start during one call of ``fn``, and its result
    (Python/numpy allocations only, not memory inside C/C++/Fortran libraries)."""
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


def json_line(obj: Any) -> str:
    """Compact JSON of a configuration, for report headers."""
    return json.dumps(obj, separators=(", ", ": "), default=str)
