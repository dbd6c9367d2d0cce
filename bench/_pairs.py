"""Real pairs, landmarks, errors and result rows shared by ``accuracy.py``, ``landmark_sweep.py``
and ``weight_sweep.py``.

Pairs: ``smal:A+B`` is ``smal_r_train/A.off.gz`` (x) and ``B.off.gz`` (y) with their
``corres/*.vts`` rows (SMAL template vertices); ``faust:A-B`` is ``faust_r_train/tr_reg_A.off``
(x) and ``tr_reg_B.off`` (y) with their ``corres/*.vts`` rows; ``A-B`` is
``tosca5k_dev/A.off`` (source x) and ``B.off`` (target y), ground truth the rows of
``corres/A.vts`` and ``corres/B.vts``; ``A~B`` is the same with ``B`` deformed
non-isometrically by ``torchfmap.data.stretch_deform(B, seed=crc32(name of B), strength=1)``
(vertex ids kept, so the same ground truth); ``cat-lion`` is ``pyfm_cat_lion`` with x = cat-00,
y = lion-00 and ground truth ``lion2cat`` (line i: the cat vertex of lion vertex i).

Landmarks, the same for every method of a pair: on TOSCA pairs, L ground-truth rows spread over x
by Euclidean farthest-point sampling (``torchfmap.eval.landmarks_from_gt``: deterministic), i.e.
pairs ``(vts_x[r], vts_y[r])``; on cat-lion the 20 pairs of ``landmarks.txt`` (column 0 on the
cat, column 1 on the lion; they agree exactly with ``lion2cat``), whatever L.

Errors: normalised geodesic error on x (heat method, ``GeodesicSolver``; divided by
``sqrt(area_x)``) at every ground-truth row, AUC of the PCK curve on [0, 0.25]
(``torchfmap.eval.auc``). The distance rows of a pair are computed once and reused for all its
maps; the first map of each pair is also scored by ``torchfmap.eval.evaluate_map`` and the
difference is logged (it must be ~0). All maps are ``p2p_yx``, evaluated against
``gt = Correspondence(idx_x, idx_y)``.
"""

from __future__ import annotations

import csv
import inspect
import os
import signal
import subprocess
import time
import traceback
import zlib
from pathlib import Path
from typing import Any

import numpy as np
from _common import REPO_ROOT, load1, log, require_data, versions
from _pyfm import run_pyfm

import torchfmap
from torchfmap.data import stretch_deform
from torchfmap.errors import ParameterError
from torchfmap.eval import auc, evaluate_map, gt_from_map, gt_from_vts, landmarks_from_gt
from torchfmap.io import read_landmark_pairs, read_map, read_vts
from torchfmap.pipeline import match

BASES = ("laplacian", "harmonic", "diffusion", "stack")
METHODS = (*BASES, "pyFM")
ERRORS: list[str] = []  # tracebacks of unexpected exceptions, printed at the end


def rname(refine: str | None) -> str:
    return refine or "none"


class Pair:
    """Source ``x``, target ``y``, ground truth (a ``Correspondence``) and fixed landmarks (or None)."""

    def __init__(self, spec: str) -> None:
        self.name = spec
        if spec.startswith("faust:"):  # faust:A-B: FAUST_r training meshes tr_reg_A (x), tr_reg_B (y)
            a, b = (f"tr_reg_{n}" for n in spec.split(":", 1)[1].split("-"))
            self._load_vts_pair(require_data("faust_r_train"), a, b, ".off")
        elif spec.startswith("smal:"):  # smal:A+B: SMAL_r training animals A (x), B (y)
            a, b = spec.split(":", 1)[1].split("+")
            self._load_vts_pair(require_data("smal_r_train"), a, b, ".off.gz")
        elif spec == "cat-lion":
            folder = require_data("pyfm_cat_lion")
            self.x = torchfmap.load_mesh(folder / "cat-00.off")
            self.y = torchfmap.load_mesh(folder / "lion-00.off")
            self.gt = gt_from_map(read_map(folder / "lion2cat"))
            self.fixed = read_landmark_pairs(folder / "landmarks.txt")  # (cat, lion)
        else:
            stretched = "~" in spec  # A~B: y = B deformed non-isometrically (ids kept)
            a, b = spec.replace("~", "-").split("-")
            folder = require_data("tosca5k_dev")
            self.x = torchfmap.load_mesh(folder / f"{a}.off")
            self.y = torchfmap.load_mesh(folder / f"{b}.off")
            if stretched:
                self.y = stretch_deform(self.y, seed=zlib.crc32(b.encode()), strength=1.0)
            corres = folder / "corres"
            self.gt = gt_from_vts(read_vts(corres / f"{a}.vts"), read_vts(corres / f"{b}.vts"))
            self.fixed = None
        self._rows: np.ndarray | None = None
        self._inverse: np.ndarray | None = None
        self.checked = False

    def _load_vts_pair(self, folder: Path, a: str, b: str, suffix: str) -> None:
        """Meshes ``folder/a``, ``folder/b`` and the ground truth of their ``corres/*.vts`` rows."""
        self.x = torchfmap.load_mesh(folder / f"{a}{suffix}")
        self.y = torchfmap.load_mesh(folder / f"{b}{suffix}")
        corres = folder / "corres"
        self.gt = gt_from_vts(read_vts(corres / f"{a}.vts"), read_vts(corres / f"{b}.vts"))
        self.fixed = None

    def landmarks(self, n: int, use_fixed: bool = True) -> np.ndarray:
        if use_fixed and self.fixed is not None:
            return self.fixed
        return landmarks_from_gt(self.x, self.gt, n)

    def _distance_rows(self) -> None:
        t0 = time.perf_counter()
        uniq, self._inverse = np.unique(self.gt.idx_x, return_inverse=True)
        solver = torchfmap.GeodesicSolver(self.x)
        self._rows = np.vstack([solver.distances(uniq[s : s + 256]) for s in range(0, len(uniq), 256)])
        log(f"  {self.name}: {len(uniq)} geodesic distance rows in {time.perf_counter() - t0:.1f} s")

    def errors(self, p2p_yx: np.ndarray) -> np.ndarray:
        """Normalised geodesic errors at every ground-truth row (distance rows computed once)."""
        idx_x, idx_y = self.gt
        if self._rows is None:
            self._distance_rows()
        p2p_yx = np.asarray(p2p_yx, dtype=np.int64)
        if p2p_yx.shape != (self.y.n_vertices,):
            raise RuntimeError(f"map of shape {p2p_yx.shape} is not p2p_yx ({self.y.n_vertices},)")
        pred = p2p_yx[idx_y]
        err = np.maximum(self._rows[self._inverse, pred], 0.0)
        err[pred == idx_x] = 0.0
        err /= np.sqrt(self.x.area)
        if not self.checked:  # the package's evaluation must agree
            report, ref = evaluate_map(self.x, self.y, p2p_yx, self.gt)
            diff = np.abs(ref - err).max()
            means = f"mean {report.mean_error:.5f} vs {err.mean():.5f}"
            log(f"  {self.name}: evaluate_map check: {means}, max |diff| {diff:.2e}")
            self.checked = True
        return err


def record(pair: Pair, method: str, refine: str | None, n_lmk: int, k: int, p2p, seconds: float, **extra):
    """A result row: errors of ``p2p`` (mean, median, AUC), time and the load average."""
    err = pair.errors(p2p)
    row = {"pair": pair.name, "method": method, "refine": rname(refine), "L": n_lmk, "K": k}
    row |= {"mean": float(err.mean()), "median": float(np.median(err)), "auc": auc(err)}
    row |= {"time": seconds, "load": load1(), **extra}
    log(
        f"    {method:9s} {rname(refine):7s} K={k:3d}  mean {row['mean']:.4f}  AUC {row['auc']:.3f}  "
        f"{seconds:6.2f} s  (load {row['load']:.1f})"
    )
    return row


def na_row(pair: Pair, method: str, refine: str | None, n_lmk: int, why: str) -> dict[str, Any]:
    return {"pair": pair.name, "method": method, "refine": rname(refine), "L": n_lmk, "K": "", "note": why}


def _crash(label: str) -> None:
    tb = traceback.format_exc()
    ERRORS.append(f"{label}:\n{tb}")
    log(tb)


def run_ours(pair: Pair, basis: str, lmk: np.ndarray, k: int, refines, rows: list[dict]) -> None:
    """Append the rows of ``match`` for one basis; ``None`` comes from the icp call's initial map.

    The unrefined map is ``p2p_yx_initial`` of the ``refine='icp'`` call (the same computation);
    its time is that call's wall time minus ``timings['refine']``. ``K`` is the basis size that
    ``match`` actually used (``basis_x.k``). ``'n/a'`` where ``match`` raises ParameterError.
    """
    calls = ["icp" if (None in refines or "icp" in refines) else None]
    if "zoomout" in refines:
        calls.append("zoomout")
    for refine in calls:
        try:
            t0 = time.perf_counter()
            res = match(pair.x, pair.y, landmarks=lmk, basis=basis, k=k, refine=refine)
            wall = time.perf_counter() - t0
        except ParameterError as exc:
            log(f"    {basis:9s} {rname(refine):7s} n/a: {exc}")
            rows.append(na_row(pair, basis, refine, len(lmk), "n/a"))
            continue
        except Exception:  # a crash: report it, keep benchmarking
            _crash(f"{pair.name} {basis} refine={refine} L={len(lmk)}")
            rows.append(na_row(pair, basis, refine, len(lmk), "error"))
            continue
        phases = {f"t_{key}": val for key, val in res.timings.items()}
        if refine == "icp" and None in refines:
            t_none = wall - res.timings.get("refine", 0.0)
            rows.append(record(pair, basis, None, len(lmk), res.basis_x.k, res.p2p_yx_initial, t_none))
        if refine in refines:
            rows.append(record(pair, basis, refine, len(lmk), res.basis_x.k, res.p2p_yx, wall, **phases))


def run_pyfm_rows(pair: Pair, lmk: np.ndarray, k: int, refines, rows: list[dict]) -> None:
    """Append the rows of one pyFM pipeline (preprocess + fit, then each refinement)."""
    extra = tuple(r for r in refines if r is not None)
    try:
        run = run_pyfm(pair.x, pair.y, k=k, landmarks=lmk, refine=extra, subsample_step=5)
    except Exception:
        _crash(f"{pair.name} pyFM L={len(lmk)}")
        rows += [na_row(pair, "pyFM", r, len(lmk), "error") for r in refines]
        return
    info = {"n_descr": run.n_descr, "k_process": run.k_process}
    info.update({f"t_{key}": val for key, val in run.phases.items()})
    rows += [record(pair, "pyFM", r, len(lmk), k, run.p2p[r], run.times[r], **info) for r in refines]


def lookup(rows, pair: str, method: str, refine: str | None, n_lmk: int | None = None):
    """The first row of ``pair`` / ``method`` / ``refine`` (and ``L == n_lmk`` if given), or None."""
    for r in rows:
        if r["pair"] == pair and r["method"] == method and r["refine"] == rname(refine):
            if n_lmk is None or r["L"] == n_lmk:
                return r
    return None


def values(rows, names, method: str, refine: str, n_lmk: int, key: str = "mean") -> list[float]:
    """``key`` of the rows of ``pairs`` in ``names`` for one method, refinement and ``L``."""
    return [
        r[key]
        for r in rows
        if r["pair"] in names
        and r["method"] == method
        and r["refine"] == refine
        and r["L"] == n_lmk
        and key in r
    ]


def mean_of(rows, names, method: str, refine: str, n_lmk: int, key: str = "mean") -> float:
    """Mean of :func:`values` (x100 for errors), NaN unless every pair of ``names`` has a row."""
    v = values(rows, names, method, refine, n_lmk, key)
    return float(np.mean(v)) * (100 if key == "mean" else 1) if len(v) == len(names) else float("nan")


def save_csv(rows: list[dict], path: Path) -> None:
    keys: list[str] = []
    for r in rows:
        keys += [key for key in r if key not in keys]
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)


def code_state() -> str:
    """``git describe`` and the newest ``torchfmap`` source file (which code the figures are of)."""
    try:
        cmd = ["git", "describe", "--always", "--dirty"]
        desc = subprocess.run(cmd, cwd=REPO_ROOT, capture_output=True, text=True, check=False).stdout.strip()
    except OSError:
        desc = "?"
    newest = max((p.stat().st_mtime, p) for p in (REPO_ROOT / "torchfmap").rglob("*.py"))
    stamp = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(newest[0]))
    return f"git {desc}, newest torchfmap file {newest[1].relative_to(REPO_ROOT)} at {stamp}"


def ours_settings() -> str:
    """``match``'s descriptor and weight defaults, as used here."""
    d = {n: p.default for n, p in inspect.signature(match).parameters.items()}
    from torchfmap.kinds import KINDS

    kinds = KINDS.items()
    d["w_lap"] = "/".join(f"{k.w_lap:g} ({n})" for n, k in kinds) if d["w_lap"] is None else d["w_lap"]
    weights = ", ".join(
        f"{n}={d[n]:g}" if not isinstance(d[n], str) else f"{n}={d[n]}" for n in d if n.startswith("w_")
    )
    return (
        f"{d['n_descriptors']} WKS from {d['k_descriptors']} eigenpairs + 2 heat descriptors per "
        f"landmark, {weights} (match defaults)"
    )


class PairCache:
    """Pairs loaded once; :meth:`drop` frees one (and its geodesic distance rows)."""

    def __init__(self) -> None:
        self.pairs: dict[str, Pair] = {}

    def get(self, spec: str) -> Pair:
        if spec not in self.pairs:
            log(f"loading {spec}")
            self.pairs[spec] = Pair(spec)
        return self.pairs[spec]

    def drop(self, spec: str) -> None:
        self.pairs.pop(spec, None)


def run_header(title: str, t_start: float, load_start, rows: list[dict], interrupted: bool) -> str:
    """Title line and the run's context: versions, code state, load averages, total time."""
    loads = [r["load"] for r in rows if "load" in r]
    note = "**Interrupted**: the tables below hold the runs that finished. " if interrupted else ""
    return (
        f"## {title}\n\n{note}{versions('scipy', 'pyfmaps')}; {code_state()}. Load average "
        f"(1/5/15 min) at start {'/'.join(f'{x:.1f}' for x in load_start)}, at end "
        f"{'/'.join(f'{x:.1f}' for x in os.getloadavg())}; 1-min load during runs "
        f"{min(loads, default=0):.1f}..{max(loads, default=0):.1f}. Total "
        f"{time.perf_counter() - t_start:.0f} s."
    )


def errors_section() -> str:
    """The tracebacks of unexpected exceptions, or ''."""
    if not ERRORS:
        return ""
    return "### Unexpected exceptions\n\n" + "\n".join("```\n" + e + "```" for e in ERRORS)


def interruptible(fn) -> bool:
    """Run ``fn()``; Ctrl-C or SIGTERM stops it. Returns True if it was interrupted."""
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        fn()
    except KeyboardInterrupt:
        log("interrupted: printing what finished")
        return True
    return False
