"""Benchmark: matching accuracy on real pairs, ours (4 bases x 3 refinements) vs pyFM, same landmarks and k.

Run by hand from the repository root (prints markdown tables to stdout, progress to stderr; writes
CSVs and a PNG under ``bench/results/``)::

    python bench/accuracy.py                                   # 6 TOSCA pairs + cat-lion, sweep on 2
    python bench/accuracy.py --pairs cat0-cat1,cat-lion --no-sweep
    python bench/accuracy.py --no-main --sweep-pairs cat0-cat1 --sweep-L 5,10,20

Pairs: ``A-B`` is ``tosca5k_dev/A.off`` (source x) and ``B.off`` (target y), ground truth the
rows of ``corres/A.vts`` and ``corres/B.vts``; ``cat-lion`` is ``pyfm_cat_lion`` with x = cat-00,
y = lion-00 and ground truth ``lion2cat`` (line i: the cat vertex of lion vertex i).

Landmarks, the same for every method of a pair: on TOSCA pairs, ``--L`` ground-truth rows spread
over x by Euclidean farthest-point sampling (``torchfmap.eval.landmarks_from_gt``: deterministic),
i.e. pairs ``(vts_x[r], vts_y[r])``; on cat-lion the 20 pairs of ``landmarks.txt`` (column 0 on
the cat, column 1 on the lion; they agree exactly with ``lion2cat``), whatever ``--L``.

Methods (all maps are ``p2p_yx``, evaluated against ``gt = (idx_y, idx_x)``):

- ours: ``match(x, y, landmarks=pairs, basis=b, k=k, refine=r)`` for b in laplacian, harmonic,
  diffusion, stack and r in None, icp, zoomout (``'n/a'`` where match raises ParameterError);
  descriptors and energy weights are ``match``'s defaults (printed with the table).
  The unrefined map is ``p2p_yx_initial`` of the ``refine='icp'`` call (the same computation);
  its time is that call's wall time minus ``timings['refine']``. ``K`` is the basis size that
  ``match`` actually used (``basis_x.k``): feature-aware bases do not honour ``k`` (harmonic: L
  columns; diffusion: 4L minus dependent ones; stack: 5L + max(0, k - 5L) eigenfunctions).
- pyFM (``bench/_pyfm.py``): ``TriMesh`` from our arrays, ``preprocess(n_descr=50, k_descr=50,
  descr_type='WKS', landmarks=pairs, subsample_step=5, k_process=2k)``, ``fit(K=(k, k))`` with
  the weights of pyFM's README example, ``get_p2p()``, then ``icp_refine(nit=10)`` and
  ``zoomout_refine(nit=10, step=k//10)`` (k -> 2k, like ours), each from the fitted map. One
  preprocess serves all three, so its None / icp times include the 2k eigenpairs ZoomOut needs.

Errors: normalised geodesic error on x (heat method, ``GeodesicSolver``; divided by
``sqrt(area_x)``) at every ground-truth row, AUC of the PCK curve on [0, 0.25]
(``torchfmap.eval.auc``). The distance rows of a pair are computed once and reused for all its
maps; the first map of each pair is also scored by ``torchfmap.eval.evaluate_map`` and the
difference is printed (it must be ~0). Times are wall-clock seconds of single runs, all in one
process; the 1-minute load average is recorded with every run (another job may share the CPUs).

Sweep ("Fig. 9-style"): mean error vs number of landmarks ``--sweep-L`` for every basis (no
refinement and ICP) and pyFM (no refinement and ICP, ``k_process=k``) on ``--sweep-pairs``; runs
of the main table with the same pair and L are reused; L is the outer loop. Saved as
``bench/results/landmark_sweep.png`` and ``.csv``; the main table goes to ``bench/results/accuracy.csv``
(both CSVs are rewritten as runs finish). Ctrl-C or SIGTERM stops the runs and prints the tables
of what finished.
"""

from __future__ import annotations

import argparse
import csv
import inspect
import os
import signal
import subprocess
import sys
import time
import traceback
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import load1, log  # noqa: E402
from _meshes import DATA_DIR  # noqa: E402
from _pyfm import run_pyfm  # noqa: E402

import torchfmap  # noqa: E402
from torchfmap.errors import ParameterError  # noqa: E402
from torchfmap.eval import (  # noqa: E402
    auc,
    evaluate_map,
    gt_from_map,
    gt_from_vts,
    landmarks_from_gt,
    read_map,
    read_vts,
)
from torchfmap.pipeline import match  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
BASES = ("laplacian", "harmonic", "diffusion", "stack")
METHODS = (*BASES, "pyFM")
REFINES: tuple[str | None, ...] = (None, "icp", "zoomout")
DEFAULT_PAIRS = "cat0-cat1,cat2-cat8,cat10-cat4,cat5-cat9,wolf0-wolf1,wolf1-wolf2,cat-lion"
DEFAULT_SWEEP_PAIRS = "cat0-cat1,wolf0-wolf1"
ERRORS: list[str] = []  # tracebacks of unexpected exceptions, printed at the end


def rname(refine: str | None) -> str:
    return refine or "none"


class Pair:
    """Source ``x``, target ``y``, ground truth ``(idx_y, idx_x)`` and fixed landmarks (or None)."""

    def __init__(self, spec: str) -> None:
        self.name = spec
        if spec == "cat-lion":
            folder = DATA_DIR / "pyfm_cat_lion"
            self.x = torchfmap.load_mesh(folder / "cat-00.off")
            self.y = torchfmap.load_mesh(folder / "lion-00.off")
            self.gt = gt_from_map(read_map(folder / "lion2cat"))
            self.fixed = np.loadtxt(folder / "landmarks.txt", dtype=np.int64)  # (cat, lion)
        else:
            a, b = spec.split("-")
            folder = DATA_DIR / "tosca5k_dev"
            self.x = torchfmap.load_mesh(folder / f"{a}.off")
            self.y = torchfmap.load_mesh(folder / f"{b}.off")
            corres = folder / "corres"
            self.gt = gt_from_vts(read_vts(corres / f"{a}.vts"), read_vts(corres / f"{b}.vts"))
            self.fixed = None
        self._rows: np.ndarray | None = None
        self._inverse: np.ndarray | None = None
        self.checked = False

    def landmarks(self, n: int, use_fixed: bool = True) -> np.ndarray:
        if use_fixed and self.fixed is not None:
            return self.fixed
        return landmarks_from_gt(self.x, self.gt, n)

    def errors(self, p2p_yx: np.ndarray) -> np.ndarray:
        """Normalised geodesic errors at every ground-truth row (distance rows computed once)."""
        idx_y, idx_x = self.gt
        if self._rows is None:
            t0 = time.perf_counter()
            uniq, self._inverse = np.unique(idx_x, return_inverse=True)
            solver = torchfmap.GeodesicSolver(self.x)
            self._rows = np.vstack([solver.distances(uniq[s : s + 256]) for s in range(0, len(uniq), 256)])
            log(f"  {self.name}: {len(uniq)} geodesic distance rows in {time.perf_counter() - t0:.1f} s")
        p2p_yx = np.asarray(p2p_yx, dtype=np.int64)
        if p2p_yx.shape != (self.y.n_vertices,):
            raise RuntimeError(f"map of shape {p2p_yx.shape} is not p2p_yx ({self.y.n_vertices},)")
        pred = p2p_yx[idx_y]
        err = np.maximum(self._rows[self._inverse, pred], 0.0)
        err[pred == idx_x] = 0.0
        err /= np.sqrt(self.x.area)
        if not self.checked:  # the package's evaluation must agree
            report, ref = evaluate_map(self.x, self.y, p2p_yx, self.gt)
            log(
                f"  {self.name}: evaluate_map check: mean {report.mean_error:.5f} vs {err.mean():.5f}, "
                f"max |diff| {np.abs(ref - err).max():.2e}"
            )
            self.checked = True
        return err


def record(pair: Pair, method: str, refine: str | None, n_lmk: int, k: int, p2p, seconds: float, **extra):
    err = pair.errors(p2p)
    row = {
        "pair": pair.name,
        "method": method,
        "refine": rname(refine),
        "L": n_lmk,
        "K": k,
        "mean": float(err.mean()),
        "median": float(np.median(err)),
        "auc": auc(err),
        "time": seconds,
        "load": load1(),
        **extra,
    }
    log(
        f"    {method:9s} {rname(refine):7s} K={k:3d}  mean {row['mean']:.4f}  AUC {row['auc']:.3f}  "
        f"{seconds:6.2f} s  (load {row['load']:.1f})"
    )
    return row


def na_row(pair: Pair, method: str, refine: str | None, n_lmk: int, why: str) -> dict[str, Any]:
    return {"pair": pair.name, "method": method, "refine": rname(refine), "L": n_lmk, "K": "", "note": why}


def run_ours(pair: Pair, basis: str, lmk: np.ndarray, k: int, refines, rows: list[dict]) -> None:
    """Append the rows of ``match`` for one basis; ``None`` comes from the icp call's initial map."""
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
            tb = traceback.format_exc()
            ERRORS.append(f"{pair.name} {basis} refine={refine} L={len(lmk)}:\n{tb}")
            log(tb)
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
        tb = traceback.format_exc()
        ERRORS.append(f"{pair.name} pyFM L={len(lmk)}:\n{tb}")
        log(tb)
        rows += [na_row(pair, "pyFM", r, len(lmk), "error") for r in refines]
        return
    info = {"n_descr": run.n_descr, "k_process": run.k_process}
    info.update({f"t_{key}": val for key, val in run.phases.items()})
    rows += [record(pair, "pyFM", r, len(lmk), k, run.p2p[r], run.times[r], **info) for r in refines]


def fmt(x: Any, digits: int = 4) -> str:
    if isinstance(x, float):
        return f"{x:.{digits}f}" if abs(x) < 100 else f"{x:.0f}"
    return str(x)


def markdown(rows: list[list[Any]], columns: list[str]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def lookup(rows, pair: str, method: str, refine: str | None, n_lmk: int | None = None):
    for r in rows:
        if r["pair"] == pair and r["method"] == method and r["refine"] == rname(refine):
            if n_lmk is None or r["L"] == n_lmk:
                return r
    return None


def cell(r: dict | None, key: str, digits: int = 4) -> str:
    if r is None:
        return "-"
    if "mean" not in r:
        return r.get("note", "n/a")
    return fmt(r[key], digits)


def main_table(rows: list[dict], pairs: list[str], k: int) -> str:
    cols = ["pair", "L", "method", "K"]
    for r in REFINES:
        cols += [f"{rname(r)} err", f"{rname(r)} AUC", f"{rname(r)} t [s]"]
    out = []
    for p in pairs:
        for m in METHODS:
            rs = [lookup(rows, p, m, r) for r in REFINES]
            first = next((r for r in rs if r is not None), None)
            if first is None:
                continue
            k_used = next((r["K"] for r in rs if r is not None and r.get("K") != ""), "")
            line = [p, first["L"], m, k_used]
            for r in rs:
                line += [cell(r, "mean"), cell(r, "auc", 3), cell(r, "time", 2)]
            out.append(line)
    return markdown(out, cols)


def summary_table(rows: list[dict], pairs: list[str]) -> str:
    """Per method and refinement: mean over pairs of mean error and AUC, median of the times."""
    cols = ["method"]
    for r in REFINES:
        cols += [f"{rname(r)} err", f"{rname(r)} AUC", f"{rname(r)} median t [s]"]
    out = []
    for m in METHODS:
        line = [m]
        for r in REFINES:
            got = [x for x in (lookup(rows, p, m, r) for p in pairs) if x is not None]
            ok = [x for x in got if "mean" in x]
            if not ok:
                line += ["/".join(sorted({x.get("note", "n/a") for x in got})) or "-"] * 3
                continue
            partial = "" if len(ok) == len(pairs) else f" ({len(ok)}/{len(pairs)} pairs)"
            line += [
                fmt(float(np.mean([x["mean"] for x in ok]))) + partial,
                fmt(float(np.mean([x["auc"] for x in ok])), 3),
                fmt(float(np.median([x["time"] for x in ok])), 2),
            ]
        out.append(line)
    return markdown(out, cols)


def save_csv(rows: list[dict], path: Path) -> None:
    keys: list[str] = []
    for r in rows:
        keys += [key for key in r if key not in keys]
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)


def sweep_table(rows: list[dict], pairs: list[str], sizes: list[int], key: str = "mean") -> str:
    """Per method and refinement, the mean over ``pairs`` of ``key`` at every L (and the sizes K)."""
    cols = ["method", "refine", *[f"L={n}" for n in sizes], *[f"K (L={n})" for n in sizes]]
    out = []
    for m in METHODS:
        for r in (None, "icp"):
            vals, ks = [], []
            for n in sizes:
                got = [lookup(rows, p, m, r, n) for p in pairs]
                ok = [x for x in got if x is not None and "mean" in x]
                mean = fmt(float(np.mean([x[key] for x in ok])), 4 if key == "mean" else 1)
                vals.append(mean if len(ok) == len(pairs) else "n/a")
                ks.append("/".join(sorted({str(x["K"]) for x in ok})) or "-")
            out.append([m, rname(r), *vals, *ks])
    return markdown(out, cols)


def plot_sweep(rows: list[dict], pairs: list[str], sizes: list[int], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"laplacian": "tab:blue", "harmonic": "tab:orange", "diffusion": "tab:green"}
    colors |= {"stack": "tab:red", "pyFM": "black"}
    panels = [*pairs, "mean over pairs"]
    size = (11, 3.4 * len(panels))
    fig, axes = plt.subplots(len(panels), 2, figsize=size, squeeze=False, sharey="row")
    for i, panel in enumerate(panels):
        for j, refine in enumerate((None, "icp")):
            ax = axes[i, j]
            for m in METHODS:
                ys = []
                for n in sizes:
                    sel = pairs if panel == "mean over pairs" else [panel]
                    got = [lookup(rows, p, m, refine, n) for p in sel]
                    ok = [x["mean"] for x in got if x is not None and "mean" in x]
                    ys.append(np.mean(ok) if len(ok) == len(sel) else np.nan)
                style = "--" if m == "pyFM" else "-"
                ax.plot(sizes, ys, style, marker="o", color=colors[m], label=m, lw=2)
            ax.set_xscale("log", base=2)
            ax.set_xticks(sizes, [str(n) for n in sizes])
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
            ax.set_title(f"{panel}: {'no refinement' if refine is None else 'ICP'}", fontsize=11)
            ax.set_ylabel("mean geodesic error / sqrt(area)" if j == 0 else "")
            ax.set_xlabel("number of landmarks L")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    top = 1 - 0.75 / size[1]  # room for the title and the legend (inches -> figure fraction)
    fig.suptitle("Mean geodesic error vs number of landmarks, same landmarks for all", y=0.998, fontsize=12)
    fig.legend(
        handles, labels, loc="upper center", bbox_to_anchor=(0.5, 1 - 0.3 / size[1]), ncol=len(METHODS),
        fontsize=11, frameon=False,
    )  # fmt: skip
    fig.tight_layout(rect=(0, 0, 1, top))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def ours_settings() -> str:
    """``match``'s descriptor and weight defaults, as used here."""
    d = {n: p.default for n, p in inspect.signature(match).parameters.items()}
    from torchfmap.pipeline import W_LAP

    d["w_lap"] = "/".join(f"{W_LAP[b]:g} ({b})" for b in W_LAP) if d["w_lap"] is None else d["w_lap"]
    weights = ", ".join(
        f"{n}={d[n]:g}" if not isinstance(d[n], str) else f"{n}={d[n]}" for n in d if n.startswith("w_")
    )
    return (
        f"{d['n_descriptors']} WKS from {d['k_descriptors']} eigenpairs + 2 heat descriptors per "
        f"landmark, {weights} (match defaults)"
    )


def replot(folder: Path) -> None:
    """Redraw ``landmark_sweep.png`` from ``landmark_sweep.csv`` (no runs)."""
    with (folder / "landmark_sweep.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        r["L"] = int(r["L"])
        if r.get("mean"):
            r["mean"] = float(r["mean"])
        else:
            r.pop("mean", None)
    pairs = list(dict.fromkeys(r["pair"] for r in rows))
    sizes = sorted({r["L"] for r in rows})
    plot_sweep(rows, pairs, sizes, folder / "landmark_sweep.png")
    print(f"Plot: {folder / 'landmark_sweep.png'}")


def code_state() -> str:
    root = Path(__file__).resolve().parents[1]
    try:
        desc = subprocess.run(
            ["git", "describe", "--always", "--dirty"], cwd=root, capture_output=True, text=True, check=False
        ).stdout.strip()
    except OSError:
        desc = "?"
    newest = max((p.stat().st_mtime, p) for p in (root / "torchfmap").rglob("*.py"))
    stamp = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(newest[0]))
    return f"git {desc}, newest torchfmap file {newest[1].relative_to(root)} at {stamp}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", default=DEFAULT_PAIRS, help="A-B (tosca5k_dev) or cat-lion, comma sep.")
    parser.add_argument("--L", type=int, default=20, help="landmarks on TOSCA pairs (cat-lion: its 20)")
    parser.add_argument("--k", type=int, default=50, help="basis / functional map size")
    parser.add_argument("--sweep-pairs", default=DEFAULT_SWEEP_PAIRS)
    parser.add_argument("--sweep-L", default="5,10,20,40")
    parser.add_argument("--no-main", action="store_true", help="skip the main table")
    parser.add_argument("--no-sweep", action="store_true", help="skip the landmark sweep")
    parser.add_argument("--no-pyfm", action="store_true")
    parser.add_argument("--out", type=Path, default=RESULTS, help="folder of the CSVs and the PNG")
    parser.add_argument("--replot", action="store_true", help="only redraw the PNG from landmark_sweep.csv")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.replot:
        replot(args.out)
        return
    pairs = [] if args.no_main else [p for p in args.pairs.split(",") if p]
    sweep_pairs = [] if args.no_sweep else [p for p in args.sweep_pairs.split(",") if p]
    sizes = [int(n) for n in args.sweep_L.split(",") if n]
    t_start, load_start, state = time.perf_counter(), os.getloadavg(), code_state()
    # SIGTERM (e.g. a time limit) ends the runs like Ctrl-C: the tables of what finished still print.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    rows: list[dict] = []
    sweep_rows: list[dict] = []
    interrupted = ""
    try:
        run_all(args, pairs, sweep_pairs, sizes, rows, sweep_rows)
    except KeyboardInterrupt:
        interrupted = "**Interrupted**: the tables below hold the runs that finished. "
        log("interrupted: printing what finished")

    load_end = os.getloadavg()
    all_loads = [r["load"] for r in rows + sweep_rows if "load" in r]
    print(
        f"## Matching accuracy, k={args.k}: ours (match) vs pyFM {version('pyfmaps')}, same landmarks\n\n"
        f"{interrupted}{os.cpu_count()} CPUs; numpy {np.__version__}, scipy {version('scipy')}; {state}. "
        f"Load average (1/5/15 min) at start {'/'.join(f'{x:.1f}' for x in load_start)}, at end "
        f"{'/'.join(f'{x:.1f}' for x in load_end)}; 1-min load during runs "
        f"{min(all_loads, default=0):.1f}..{max(all_loads, default=0):.1f}. Total "
        f"{time.perf_counter() - t_start:.0f} s.\n"
    )
    if rows:
        print("### Per pair: mean normalised geodesic error, AUC (PCK on [0, 0.25]), wall time\n")
        print(main_table(rows, pairs, args.k))
        print(f"\n### Mean over the {len(pairs)} pairs (times: median, robust to load spikes)\n")
        print(summary_table(rows, pairs))
        pyfm_row = next((r for r in rows if r["method"] == "pyFM" and "n_descr" in r), None)
        if pyfm_row is not None:
            print(
                f"\nK: basis size used. ours: {ours_settings()}; pyFM: "
                f"{pyfm_row['n_descr']} descriptors (WKS + landmark WKS, every 5th), "
                f"k_process={pyfm_row['k_process']}. Per-phase times: {args.out / 'accuracy.csv'}."
            )
    if sweep_rows:
        print(f"\n### Landmark sweep: mean error over {', '.join(sweep_pairs)} (k={args.k})\n")
        print(sweep_table(sweep_rows, sweep_pairs, sizes))
        print(f"\n### Landmark sweep: mean wall time [s] over {', '.join(sweep_pairs)}\n")
        print(sweep_table(sweep_rows, sweep_pairs, sizes, key="time"))
        png = args.out / "landmark_sweep.png"
        plot_sweep(sweep_rows, sweep_pairs, sizes, png)
        print(f"\nPlot: {png}; data: {args.out / 'landmark_sweep.csv'}")
    if ERRORS:
        print("\n### Unexpected exceptions\n")
        for e in ERRORS:
            print("```\n" + e + "```")


def run_all(args, pairs, sweep_pairs, sizes, rows: list[dict], sweep_rows: list[dict]) -> None:
    """Main table then sweep, appending to ``rows`` / ``sweep_rows``; CSVs rewritten as they grow."""
    cache: dict[str, Pair] = {}

    def get(spec: str) -> Pair:
        if spec not in cache:
            log(f"loading {spec}")
            cache[spec] = Pair(spec)
        return cache[spec]

    for spec in pairs:
        pair = get(spec)
        lmk = pair.landmarks(args.L)
        nx, ny = pair.x.n_vertices, pair.y.n_vertices
        log(f"{spec}: V_x={nx}, V_y={ny}, {len(pair.gt[0])} gt rows, L={len(lmk)}")
        for basis in BASES:
            run_ours(pair, basis, lmk, args.k, REFINES, rows)
        if not args.no_pyfm:
            run_pyfm_rows(pair, lmk, args.k, REFINES, rows)
        save_csv(rows, args.out / "accuracy.csv")
        if spec not in sweep_pairs:
            cache.pop(spec)  # frees its geodesic distance rows

    for n in sizes:  # L outer: an interrupted run loses the largest (slowest) L first
        for spec in sweep_pairs:
            pair = get(spec)
            lmk = pair.landmarks(n, use_fixed=False)
            log(f"sweep {spec}: L={n}")
            for m in METHODS:
                if m == "pyFM" and args.no_pyfm:
                    continue
                reused = [lookup(rows, spec, m, r, n) for r in (None, "icp")]
                if all(r is not None for r in reused) and pair.fixed is None:
                    sweep_rows += reused
                elif m == "pyFM":
                    run_pyfm_rows(pair, lmk, args.k, (None, "icp"), sweep_rows)
                else:
                    run_ours(pair, m, lmk, args.k, (None, "icp"), sweep_rows)
            save_csv(sweep_rows, args.out / "landmark_sweep.csv")


if __name__ == "__main__":
    main()
