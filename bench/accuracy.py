"""Benchmark: matching accuracy on real pairs, ours (4 bases x 3 refinements) vs pyFM, same landmarks and k.

Run by hand from the repository root (prints markdown tables to stdout, progress to stderr; writes
``bench/results/accuracy.md`` and ``accuracy.csv``, and the sweep's files, see below)::

    python3 bench/accuracy.py                                  # 6 TOSCA pairs + cat-lion, sweep on 2
    python3 bench/accuracy.py --pairs cat0-cat1,cat-lion --no-sweep
    python3 bench/accuracy.py --pairs cat0-cat1 --no-sweep     # quick check (one pair, ~1 min)
    python3 bench/landmark_sweep.py --pairs cat0-cat1 --L 5,10,20   # the sweep alone (was --no-main)

Pairs, landmarks (``--L`` rows on TOSCA pairs, the 20 given pairs on cat-lion) and errors
(normalised geodesic error, AUC on [0, 0.25], checked against ``evaluate_map``):
``bench/_pairs.py``.

Methods (all maps are ``p2p_yx``):

- ours: ``match(x, y, landmarks=pairs, basis=b, k=k, refine=r)`` for b in laplacian, harmonic,
  diffusion, stack and r in None, icp, zoomout (``'n/a'`` where match raises ParameterError);
  descriptors and energy weights are ``match``'s defaults (printed with the table). The
  unrefined map is ``p2p_yx_initial`` of the ``refine='icp'`` call; its time is that call's wall
  time minus ``timings['refine']``. ``K`` is the basis size ``match`` used (``basis_x.k``):
  feature-aware bases do not honour ``k`` (harmonic: L columns; diffusion: 4L minus dependent
  ones; stack: 5L + max(0, k - 5L) eigenfunctions).
- pyFM (the baseline, ``bench/_pyfm.py``): ``TriMesh`` from our arrays, ``preprocess(n_descr=50,
  k_descr=50, descr_type='WKS', landmarks=pairs, subsample_step=5, k_process=2k)``,
  ``fit(K=(k, k))`` with the weights of pyFM's README example, ``get_p2p()``, then
  ``icp_refine(nit=10)`` and ``zoomout_refine(nit=10, step=k//10)`` (k -> 2k, like ours), each
  from the fitted map. One preprocess serves all three, so its None / icp times include the 2k
  eigenpairs ZoomOut needs.

Times are wall-clock seconds of single runs, all in one process; the 1-minute load average is
recorded with every run (another job may share the CPUs). The summary gives ``t / pyFM``, the
ratio of the median times to pyFM's. Unless ``--no-sweep``, ``bench/landmark_sweep.py`` then runs
on ``--sweep-pairs`` with ``--sweep-L``, reusing the main-table runs with the same pair and L.
The CSVs are rewritten as runs finish; Ctrl-C or SIGTERM stops the runs and prints the tables of
what finished.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from _common import RESULTS_DIR, Report, fmt, int_list, log, markdown, str_list
from _pairs import (
    BASES,
    METHODS,
    PairCache,
    errors_section,
    interruptible,
    lookup,
    ours_settings,
    rname,
    run_header,
    run_ours,
    run_pyfm_rows,
    save_csv,
)
from landmark_sweep import DEFAULT_L, replot, run_sweep, sweep_sections

REFINES: tuple[str | None, ...] = (None, "icp", "zoomout")
DEFAULT_PAIRS = "cat0-cat1,cat2-cat8,cat10-cat4,cat5-cat9,wolf0-wolf1,wolf1-wolf2,cat-lion"
DEFAULT_SWEEP_PAIRS = "cat0-cat1,wolf0-wolf1"


def cell(r: dict | None, key: str, digits: int = 4) -> str:
    if r is None:
        return "-"
    if "mean" not in r:
        return r.get("note", "n/a")
    return fmt(r[key], digits)


def main_table(rows: list[dict], pairs: list[str]) -> str:
    """Per pair and method: error, AUC and time for every refinement."""
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


def summary_cells(rows: list[dict], pairs: list[str], m: str, r: str | None) -> list[str]:
    """Mean over pairs of the mean error and AUC, median time and its ratio to pyFM's."""
    got = [x for x in (lookup(rows, p, m, r) for p in pairs) if x is not None]
    ok = [x for x in got if "mean" in x]
    if not ok:
        return ["/".join(sorted({x.get("note", "n/a") for x in got})) or "-"] * 4
    partial = "" if len(ok) == len(pairs) else f" ({len(ok)}/{len(pairs)} pairs)"
    t = float(np.median([x["time"] for x in ok]))
    base = [x["time"] for x in (lookup(rows, p, "pyFM", r) for p in pairs) if x is not None and "time" in x]
    ratio = fmt(t / float(np.median(base)), 2) if base else "-"
    return [
        fmt(float(np.mean([x["mean"] for x in ok])), 4) + partial,
        fmt(float(np.mean([x["auc"] for x in ok])), 3),
        fmt(t, 2),
        ratio,
    ]


def summary_table(rows: list[dict], pairs: list[str]) -> str:
    """Per method and refinement: mean over pairs of mean error and AUC, median of the times."""
    cols = ["method"]
    for r in REFINES:
        cols += [f"{rname(r)} err", f"{rname(r)} AUC", f"{rname(r)} median t [s]", f"{rname(r)} t / pyFM"]
    out = [[m, *(c for r in REFINES for c in summary_cells(rows, pairs, m, r))] for m in METHODS]
    return markdown(out, cols)


def run_main(args, pairs: list[str], rows: list[dict], cache: PairCache, keep: set[str]) -> None:
    """The main table's runs, appended to ``rows``; ``accuracy.csv`` rewritten after every pair."""
    for spec in pairs:
        pair = cache.get(spec)
        lmk = pair.landmarks(args.L)
        nx, ny = pair.x.n_vertices, pair.y.n_vertices
        log(f"{spec}: V_x={nx}, V_y={ny}, {len(pair.gt.idx_x)} gt rows, L={len(lmk)}")
        for basis in BASES:
            run_ours(pair, basis, lmk, args.k, REFINES, rows)
        if not args.no_pyfm:
            run_pyfm_rows(pair, lmk, args.k, REFINES, rows)
        save_csv(rows, args.out / "accuracy.csv")
        if spec not in keep:
            cache.drop(spec)  # frees its geodesic distance rows


def main_sections(rows: list[dict], pairs: list[str], args) -> list[str]:
    parts = [
        "### Per pair: mean normalised geodesic error, AUC (PCK on [0, 0.25]), wall time",
        main_table(rows, pairs),
        f"### Mean over the {len(pairs)} pairs (times: median, robust to load spikes)",
        summary_table(rows, pairs),
    ]
    pyfm_row = next((r for r in rows if r["method"] == "pyFM" and "n_descr" in r), None)
    if pyfm_row is not None:
        parts.append(
            f"K: basis size used. ours: {ours_settings()}; pyFM: {pyfm_row['n_descr']} descriptors (WKS + "
            f"landmark WKS, every 5th), k_process={pyfm_row['k_process']}. t / pyFM: median time over "
            f"pyFM's median time, same refinement. Per-phase times: {args.out / 'accuracy.csv'}."
        )
    return parts


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", default=DEFAULT_PAIRS, help="A-B (tosca5k_dev) or cat-lion, comma sep.")
    parser.add_argument("--L", type=int, default=20, help="landmarks on TOSCA pairs (cat-lion: its 20)")
    parser.add_argument("--k", type=int, default=50, help="basis / functional map size")
    parser.add_argument("--sweep-pairs", default=DEFAULT_SWEEP_PAIRS)
    parser.add_argument("--sweep-L", default=DEFAULT_L)
    parser.add_argument("--no-main", action="store_true", help="skip the main table")
    parser.add_argument("--no-sweep", action="store_true", help="skip the landmark sweep")
    parser.add_argument("--no-pyfm", action="store_true")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR, help="folder of the CSVs, PNG and .md")
    parser.add_argument("--replot", action="store_true", help="only redraw the PNG from landmark_sweep.csv")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.replot:
        replot(args.out)
        return
    pairs = [] if args.no_main else str_list(args.pairs)
    sweep_pairs = [] if args.no_sweep else str_list(args.sweep_pairs)
    sizes = int_list(args.sweep_L)
    t_start, load_start = time.perf_counter(), os.getloadavg()
    rows: list[dict] = []
    sweep_rows: list[dict] = []
    cache = PairCache()

    def run_all() -> None:
        run_main(args, pairs, rows, cache, set(sweep_pairs))
        run_sweep(sweep_pairs, sizes, args.k, args.no_pyfm, args.out, sweep_rows, reuse=rows, cache=cache)

    stopped = interruptible(run_all)
    title = f"Matching accuracy, k={args.k}: ours (match) vs pyFM, same landmarks"
    report = Report("accuracy", args.out)
    report.add(run_header(title, t_start, load_start, rows + sweep_rows, stopped))
    if rows:
        report.add(*main_sections(rows, pairs, args))
    if sweep_rows:
        sweep = sweep_sections(sweep_rows, sweep_pairs, sizes, args.k, args.out)
        report.add(*sweep)
        sweep_report = Report("landmark_sweep", args.out)
        sweep_report.parts += [report.parts[0], *sweep]  # also on its own, as landmark_sweep.py writes it
        sweep_report.save()
    if errors_section():
        report.add(errors_section())
    report.save()


if __name__ == "__main__":
    main()
