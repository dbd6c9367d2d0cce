"""Benchmark: mean geodesic error vs number of landmarks, every basis and pyFM ("Fig. 9-style").

Run by hand from the repository root (prints markdown tables to stdout, progress to stderr; writes
``bench/results/landmark_sweep.md``, ``.csv`` and ``.png``)::

    python3 bench/landmark_sweep.py                        # cat0-cat1, wolf0-wolf1; L = 5,10,20,40
    python3 bench/landmark_sweep.py --pairs cat0-cat1 --L 5,10,20
    python3 bench/landmark_sweep.py --replot               # redraw the PNG from the CSV, no runs
    python3 bench/landmark_sweep.py --pairs cat0-cat1 --L 5 --no-pyfm   # quick check

``bench/accuracy.py`` runs the same sweep after its main table (``--sweep-pairs``, ``--sweep-L``)
and reuses its runs with the same pair and L. Pairs, landmarks (here always ``L`` ground-truth
rows spread by FPS, also on cat-lion) and errors: ``bench/_pairs.py``. For every L of ``--L``
(outer loop: an interrupted run loses the largest, slowest L first) and pair: ``match`` for every
basis with no refinement and ICP (the unrefined map is that of the ICP call), and pyFM with no
refinement and ICP (``k_process=k``); methods as in ``bench/accuracy.py``. The CSV is rewritten
as runs finish; Ctrl-C or SIGTERM stops the runs and prints the tables of what finished.
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from pathlib import Path

import numpy as np
from _common import RESULTS_DIR, Report, fmt, int_list, log, markdown, str_list
from _pairs import (
    METHODS,
    PairCache,
    errors_section,
    interruptible,
    lookup,
    rname,
    run_header,
    run_ours,
    run_pyfm_rows,
    save_csv,
)

DEFAULT_PAIRS = "cat0-cat1,wolf0-wolf1"
DEFAULT_L = "5,10,20,40"
COLORS = {"laplacian": "tab:blue", "harmonic": "tab:orange", "diffusion": "tab:green"}
COLORS |= {"stack": "tab:red", "pyFM": "black"}


def run_sweep(pairs, sizes, k: int, no_pyfm: bool, out: Path, rows: list[dict], reuse=(), cache=None) -> None:
    """Append the sweep rows to ``rows``; rows of ``reuse`` with the same pair and L are reused."""
    cache = cache or PairCache()
    for n in sizes:  # L outer: an interrupted run loses the largest (slowest) L first
        for spec in pairs:
            pair = cache.get(spec)
            lmk = pair.landmarks(n, use_fixed=False)
            log(f"sweep {spec}: L={n}")
            for m in METHODS:
                if m == "pyFM" and no_pyfm:
                    continue
                reused = [lookup(reuse, spec, m, r, n) for r in (None, "icp")]
                if all(r is not None for r in reused) and pair.fixed is None:
                    rows += reused
                elif m == "pyFM":
                    run_pyfm_rows(pair, lmk, k, (None, "icp"), rows)
                else:
                    run_ours(pair, m, lmk, k, (None, "icp"), rows)
            save_csv(rows, out / "landmark_sweep.csv")


def sweep_table(rows: list[dict], pairs: list[str], sizes: list[int], key: str = "mean") -> str:
    """Per method and refinement, the mean over ``pairs`` of ``key`` at every L (and the sizes K)."""
    cols = ["method", "refine", *[f"L={n}" for n in sizes], *[f"K (L={n})" for n in sizes]]
    out = []
    for m in METHODS:
        for r in (None, "icp"):
            vals, ks = [], []
            for n in sizes:
                ok = [x for x in (lookup(rows, p, m, r, n) for p in pairs) if x is not None and "mean" in x]
                mean = fmt(float(np.mean([x[key] for x in ok])), 4 if key == "mean" else 1) if ok else "n/a"
                vals.append(mean if len(ok) == len(pairs) else "n/a")
                ks.append("/".join(sorted({str(x["K"]) for x in ok})) or "-")
            out.append([m, rname(r), *vals, *ks])
    return markdown(out, cols)


def _panel_curve(rows, sel: list[str], m: str, refine, sizes: list[int]) -> list[float]:
    ys = []
    for n in sizes:
        ok = [
            x["mean"] for x in (lookup(rows, p, m, refine, n) for p in sel) if x is not None and "mean" in x
        ]
        ys.append(np.mean(ok) if len(ok) == len(sel) else np.nan)
    return ys


def plot_sweep(rows: list[dict], pairs: list[str], sizes: list[int], path: Path) -> None:
    """One row of panels per pair and one for the mean; columns: no refinement, ICP."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [*pairs, "mean over pairs"]
    size = (11, 3.4 * len(panels))
    fig, axes = plt.subplots(len(panels), 2, figsize=size, squeeze=False, sharey="row")
    for i, panel in enumerate(panels):
        sel = pairs if panel == "mean over pairs" else [panel]
        for j, refine in enumerate((None, "icp")):
            ax = axes[i, j]
            for m in METHODS:
                ys = _panel_curve(rows, sel, m, refine, sizes)
                ax.plot(sizes, ys, "--" if m == "pyFM" else "-", marker="o", color=COLORS[m], label=m, lw=2)
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
    plot_sweep(rows, pairs, sorted({r["L"] for r in rows}), folder / "landmark_sweep.png")
    print(f"Plot: {folder / 'landmark_sweep.png'}")


def sweep_sections(rows, pairs, sizes, k: int, out: Path) -> list[str]:
    """The two sweep tables (error, time) and the plot's path; draws the plot."""
    png = out / "landmark_sweep.png"
    plot_sweep(rows, pairs, sizes, png)
    return [
        f"### Landmark sweep: mean error over {', '.join(pairs)} (k={k})",
        sweep_table(rows, pairs, sizes),
        f"### Landmark sweep: mean wall time [s] over {', '.join(pairs)}",
        sweep_table(rows, pairs, sizes, key="time"),
        f"Plot: {png}; data: {out / 'landmark_sweep.csv'}",
    ]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", default=DEFAULT_PAIRS, help="A-B (tosca5k_dev) or cat-lion, comma sep.")
    parser.add_argument("--L", default=DEFAULT_L, help="numbers of landmarks, comma-separated")
    parser.add_argument("--k", type=int, default=50, help="basis / functional map size")
    parser.add_argument("--no-pyfm", action="store_true")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR, help="folder of the CSV, PNG and .md")
    parser.add_argument("--replot", action="store_true", help="only redraw the PNG from landmark_sweep.csv")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.replot:
        replot(args.out)
        return
    pairs, sizes = str_list(args.pairs), int_list(args.L)
    t_start, load_start = time.perf_counter(), os.getloadavg()
    rows: list[dict] = []
    stopped = interruptible(lambda: run_sweep(pairs, sizes, args.k, args.no_pyfm, args.out, rows))
    report = Report("landmark_sweep", args.out)
    report.add(
        run_header(f"Landmark sweep, k={args.k}: ours (match) vs pyFM", t_start, load_start, rows, stopped)
    )
    if rows:
        report.add(*sweep_sections(rows, pairs, sizes, args.k, args.out))
    if errors_section():
        report.add(errors_section())
    report.save()


if __name__ == "__main__":
    main()
