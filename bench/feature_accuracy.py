"""Benchmark: feature-aware bases vs the eigenbasis and pyFM with few landmarks (issue protocol).

Run by hand from the repository root (tables to stdout and ``bench/results/feature_accuracy.md``,
rows to ``feature_accuracy.csv``, the landmark sweep to ``feature_accuracy.png``)::

    python3 bench/feature_accuracy.py                         # all pairs, L = 3, 7, 15
    python3 bench/feature_accuracy.py --iso cat0-cat1 --noniso cat0~cat1 --L 7 --no-pyfm

Protocol: k = 60; landmarks ``landmarks_from_gt`` (ground-truth rows spread over x by
farthest-point sampling; the first L of ``landmarks.txt`` on cat-lion); errors: mean normalised
geodesic error on x at every ground-truth row (``bench/_pairs.py``). Pairs: isometric TOSCA test
pairs of both classes, and non-isometric ones: cat-lion and ``A~B`` (``B`` deformed by
``torchfmap.data.stretch_deform``, ids kept). Methods, the same landmarks for all:

- ``laplacian``: ``match(basis='laplacian', k=60)`` raw / ICP / ZoomOut (60 -> 120);
- ``diffusion``: ``match(landmarks, basis='diffusion', k=60)`` (the feature-aware basis; the
  landmark default until the eigenbasis measured better), raw and ``refine='zoomout'`` (its
  refinement); ``--also hybrid`` adds other kinds the same way;
- ``pyFM``: raw / ICP / ZoomOut (``bench/_pyfm.py``).

Targets (the issue, for the feature-aware basis): at L = 7 and 15 <= 0.8x the eigenbasis at the
same stage (raw vs raw, refined vs eigenbasis ZoomOut) on iso and non-iso pairs separately; at
L = 3 no worse; below pyFM at every L; no slower. The summary prints the ratios.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import RESULTS_DIR, Report, fmt, int_list, log, str_list
from _pairs import Pair, _crash, mean_of, na_row, record, run_pyfm_rows, save_csv

from torchfmap.pipeline import match

ISO = "cat0-cat1,cat2-cat8,cat10-cat4,cat5-cat9,wolf0-wolf1,wolf1-wolf2"
NONISO = "cat-lion,cat0~cat1,cat5~cat9,cat2~cat8,wolf0~wolf1"
K = 60


def landmarks(pair: Pair, n: int) -> np.ndarray:
    return pair.fixed[:n] if pair.fixed is not None else pair.landmarks(n, use_fixed=False)


def run_pair(pair: Pair, n: int, use_pyfm: bool, rows: list[dict], also: tuple[str, ...] = ()) -> None:
    lmk = landmarks(pair, n)
    for method, basis, refines in (
        ("laplacian", "laplacian", ("icp", "zoomout")),
        ("diffusion", "diffusion", ("zoomout",)),
        *((b, b, ("zoomout",)) for b in also),
    ):
        for refine in refines:
            try:
                t0 = time.perf_counter()
                res = match(pair.x, pair.y, landmarks=lmk, basis=basis, k=K, refine=refine)
                wall = time.perf_counter() - t0
            except Exception:
                _crash(f"{pair.name} {method} {refine} L={n}")
                rows.append(na_row(pair, method, refine, n, "error"))
                continue
            if refine == refines[0]:
                raw_t = wall - res.timings.get("refine", 0.0)
                rows.append(record(pair, method, None, n, res.basis_x.k, res.p2p_yx_initial, raw_t))
            rows.append(record(pair, method, refine, n, res.basis_x.k, res.p2p_yx, wall))
    if use_pyfm:
        run_pyfm_rows(pair, lmk, K, (None, "icp", "zoomout"), rows)


def summary(rows, sets, Ls, use_pyfm, also=()) -> list[dict]:
    out = []
    for n in Ls:
        for set_name, names in sets.items():
            row = {"L": n, "set": set_name}
            for method, refine in (
                ("laplacian", "none"),
                ("laplacian", "icp"),
                ("laplacian", "zoomout"),
                ("diffusion", "none"),
                ("diffusion", "zoomout"),
                *((b, r) for b in also for r in ("none", "zoomout")),
            ):
                row[f"{method} {refine}"] = mean_of(rows, names, method, refine, n)
            if use_pyfm:
                for refine in ("none", "icp", "zoomout"):
                    row[f"pyFM {refine}"] = mean_of(rows, names, "pyFM", refine, n)
            row["raw / lap raw"] = row["diffusion none"] / row["laplacian none"]
            row["refined / lap ZO"] = row["diffusion zoomout"] / row["laplacian zoomout"]
            row["t diffusion / t lap ZO"] = mean_of(rows, names, "diffusion", "zoomout", n, "time") / mean_of(
                rows, names, "laplacian", "zoomout", n, "time"
            )
            out.append({k: fmt(v, 3) if isinstance(v, float) else v for k, v in row.items()})
    return out


def per_pair(rows, Ls) -> list[dict]:
    out = []
    for name in dict.fromkeys(r["pair"] for r in rows):
        entry = {"pair": name}
        for n in Ls:
            cells = []
            for method, refine in (
                ("laplacian", "none"),
                ("laplacian", "zoomout"),
                ("pyFM", "none"),
                ("pyFM", "zoomout"),
                ("diffusion", "none"),
                ("diffusion", "zoomout"),
            ):
                v = mean_of(rows, [name], method, refine, n)
                cells.append("-" if np.isnan(v) else f"{v:.2f}")
            entry[f"L={n}"] = " / ".join(cells)
        out.append(entry)
    return out


def sweep_png(rows, sets, Ls, path, also=()) -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(sets), figsize=(5.5 * len(sets), 4.2), squeeze=False)
    curves = (
        ("laplacian", "none", "eigenbasis raw", "C0--"),
        ("laplacian", "zoomout", "eigenbasis ZoomOut", "C0-"),
        ("diffusion", "none", "feature-aware raw", "C3--"),
        ("diffusion", "zoomout", "feature-aware refined", "C3-"),
        ("pyFM", "none", "pyFM raw", "C2--"),
        ("pyFM", "zoomout", "pyFM ZoomOut", "C2-"),
        *(
            (b, r, f"{b} {label}", f"C{4 + i}{style}")
            for i, b in enumerate(also)
            for r, label, style in (("none", "raw", "--"), ("zoomout", "refined", "-"))
        ),
    )
    for ax, (set_name, names) in zip(axes[0], sets.items(), strict=True):
        for method, refine, label, style in curves:
            ys = [mean_of(rows, names, method, refine, n) for n in Ls]
            if not np.all(np.isnan(ys)):
                ax.plot(Ls, ys, style, marker="o", label=label)
        ax.set_title(f"{set_name} pairs ({len(names)}), k={K}")
        ax.set_xlabel("landmarks L")
        ax.set_ylabel("mean geodesic error x100")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iso", default=ISO, help="comma-separated isometric pairs")
    parser.add_argument("--noniso", default=NONISO, help="comma-separated non-isometric pairs")
    parser.add_argument("--L", default="3,7,15", help="numbers of landmarks")
    parser.add_argument("--no-pyfm", action="store_true", help="skip pyFM")
    parser.add_argument("--also", default="", help="more bases to run, e.g. hybrid (raw and refined)")
    parser.add_argument(
        "--name", default="feature_accuracy", help="results: bench/results/NAME.md, .csv, .png"
    )
    args = parser.parse_args(argv)
    also = tuple(filter(None, (b.strip() for b in args.also.split(","))))
    sets = {"iso": str_list(args.iso), "non-iso": str_list(args.noniso)}
    Ls = int_list(args.L)
    rows: list[dict] = []
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    for names in sets.values():
        for name in names:
            pair = Pair(name)
            for n in Ls:
                log(f"{name} L={n}")
                run_pair(pair, n, not args.no_pyfm, rows, also)
                save_csv(rows, RESULTS_DIR / f"{args.name}.csv")
    report = Report(args.name)
    report.add(f"k={K}; mean geodesic error x100; {time.perf_counter() - t0:.0f} s in all.")
    report.table(
        "Means per set and L (ratios: the issue's targets)", summary(rows, sets, Ls, not args.no_pyfm, also)
    )
    report.table(
        "Per pair: lap raw / lap ZoomOut / pyFM raw / pyFM ZoomOut / diffusion raw / diffusion refined",
        per_pair(rows, Ls),
    )
    sweep_png(rows, sets, Ls, RESULTS_DIR / f"{args.name}.png", also)
    print(f"results -> {report.save()}, {RESULTS_DIR / f'{args.name}.png'}")


if __name__ == "__main__":
    main()
