"""Benchmark: the landmark default of ``match`` (it chooses the basis) against each forced kind and pyFM.

Run by hand from the repository root (tables to stdout and ``bench/results/landmark_default.md``,
rows to ``landmark_default.csv``, the landmark sweep to ``landmark_default.png``)::

    python3 bench/landmark_default.py                       # every set, L = 3, 7, 15
    python3 bench/landmark_default.py --sets smal --L 7 --methods default,laplacian
    python3 bench/landmark_default.py --methods default,laplacian,hybrid,diffusion   # then pyFM:
    python3 bench/landmark_default.py --methods pyFM --add bench/results/landmark_default.csv

Protocol: k = 60, ``refine='zoomout'``; landmarks: L ground-truth rows spread over x by
farthest-point sampling (``landmarks_from_gt``; the first L of ``landmarks.txt`` on cat-lion);
errors: mean geodesic error on x at every ground-truth row / sqrt(area), x100.
Sets (real pairs only; no synthetic stretch):

- ``near-iso``: 6 TOSCA test pairs within a class (``tosca5k_dev``);
- ``smal``: 11 SMAL_r training animals paired across names (``smal_r_train``, sorted names,
  ``A = names[i]``, ``B = names[(i + 11) % 32]`` for ``i = 0, 3, ..., 30``; pairs sharing a
  name stem are skipped), real non-isometric pairs of different animals, mostly of different
  species;
- ``cat-lion``: pyFM's cat and lion (strongly non-isometric).

Methods, the same landmarks for all: ``default`` (``basis=None``: the choice among
``AUTO_KINDS`` by geodesic distortion), ``laplacian``, ``hybrid``, ``diffusion`` forced (raw =
unrefined map of the same call), and pyFM (raw / ZoomOut). The default's candidates are the
forced runs of their kinds (``tests/test_pipeline.py`` checks they agree).

"Choice right" is the share of pairs on which the default's refined error is within 2 % of the
best forced kind's refined error. Times: the default's wall time over the forced eigenbasis
ZoomOut's, both on freshly prepared shapes in this process.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import RESULTS_DIR, Report, fmt, int_list, log, str_list
from _pairs import Pair, _crash, mean_of, na_row, record, run_pyfm_rows, save_csv, values

from torchfmap.io import mesh_files, shape_name
from torchfmap.pipeline import AUTO_KINDS, AUTO_MARGIN, match

K = 60
ISO = "cat0-cat1,cat2-cat8,cat10-cat4,cat5-cat9,wolf0-wolf1,wolf1-wolf2"
FORCED = ("laplacian", "hybrid", "diffusion")


def smal_pairs() -> list[str]:
    from _common import require_data

    names = sorted(shape_name(f) for f in mesh_files(require_data("smal_r_train")))

    def stem(n: str) -> str:
        return n.rstrip("0123456789").rstrip("_-").split("_")[0].lower()

    out = []
    for i in range(0, len(names), 3):
        a, b = names[i], names[(i + 11) % len(names)]
        if stem(a) != stem(b):
            out.append(f"smal:{a}+{b}")
    return out


def landmarks(pair: Pair, n: int) -> np.ndarray:
    return pair.fixed[:n] if pair.fixed is not None else pair.landmarks(n, use_fixed=False)


def run_pair(pair: Pair, n: int, methods, rows: list[dict]) -> None:
    lmk = landmarks(pair, n)
    if "pyFM" in methods:
        run_pyfm_rows(pair, lmk, K, (None, "zoomout"), rows)
    if "default" in methods:
        run_default(pair, n, lmk, rows)
    for basis in FORCED:
        if basis in methods:
            run_forced(pair, n, lmk, basis, rows)


def run_default(pair: Pair, n: int, lmk, rows: list[dict]) -> None:
    try:
        t0 = time.perf_counter()
        res = match(pair.x, pair.y, landmarks=lmk, k=K, refine="zoomout")
        wall = time.perf_counter() - t0
    except Exception:
        _crash(f"{pair.name} default L={n}")
        rows.append(na_row(pair, "default", "zoomout", n, "error"))
        return
    chosen = {"chosen": res.kind, "refine_kept": res.refined, "distortion": res.distortion}
    chosen |= {f"g_{name}": c.distortion for name, c in res.candidates.items()}
    rows.append(record(pair, "default", None, n, K, res.p2p_yx_initial, np.nan, **chosen))
    rows.append(record(pair, "default", "zoomout", n, K, res.p2p_yx, wall, **chosen))


def run_forced(pair: Pair, n: int, lmk, basis: str, rows: list[dict]) -> None:
    try:
        t0 = time.perf_counter()
        r = match(pair.x, pair.y, landmarks=lmk, basis=basis, k=K, refine="zoomout")
        wall = time.perf_counter() - t0
    except Exception:
        _crash(f"{pair.name} {basis} L={n}")
        rows.append(na_row(pair, basis, "zoomout", n, "error"))
        return
    extra = {"refine_kept": r.refined, "distortion": r.distortion}
    rows.append(record(pair, basis, None, n, K, r.p2p_yx_initial, wall - r.timings["refine"], **extra))
    rows.append(record(pair, basis, "zoomout", n, K, r.p2p_yx, wall, **extra))


def read_rows(path) -> list[dict]:
    """Rows of an earlier run's CSV (numbers parsed), to add pyFM or ours to it."""
    import csv

    def parse(v: str):
        try:
            return float(v) if v not in ("True", "False") else v == "True"
        except ValueError:
            return v

    with open(path, newline="") as fh:
        rows = [{k: parse(v) for k, v in r.items() if v != ""} for r in csv.DictReader(fh)]
    for r in rows:
        r["L"], r["pair"] = int(r["L"]), str(r["pair"])
        if r.get("refine") in (None, "none"):
            r["refine"] = "none"
    return rows


def choice_right(rows, names, n) -> float:
    right = 0
    for name in names:
        d = values(rows, [name], "default", "zoomout", n)
        best = [v for b in FORCED for v in values(rows, [name], b, "zoomout", n)]
        if not d or len(best) < len(FORCED):
            return float("nan")
        right += d[0] <= 1.02 * min(best)
    return right / len(names)


def summary(rows, sets, Ls, use_pyfm) -> list[dict]:
    out = []
    for n in Ls:
        for set_name, names in sets.items():
            row: dict = {"L": n, "set": set_name}
            for method in ("default", *FORCED, *(("pyFM",) if use_pyfm else ())):
                raw, ref = (mean_of(rows, names, method, r, n) for r in ("none", "zoomout"))
                row[method] = f"{fmt(raw, 3)} / {fmt(ref, 3)}"
                if method == "default":
                    d_raw, d_ref = raw, ref
                if method == "laplacian":
                    row["default / lap"] = f"{fmt(d_raw / raw, 3)} / {fmt(d_ref / ref, 3)}"
                if method == "pyFM":
                    row["default / pyFM refined"] = fmt(d_ref / ref, 3)
            row["refined / raw (default)"] = fmt(d_ref / d_raw, 3)
            row["choice right"] = fmt(choice_right(rows, names, n), 2)
            chosen = [r["chosen"] for r in rows if r["pair"] in names and r["L"] == n and r.get("chosen")]
            counts = {b: chosen.count(b) // 2 for b in AUTO_KINDS}
            row[f"chosen ({'/'.join(b[:3] for b in AUTO_KINDS)})"] = "/".join(
                str(counts[b]) for b in AUTO_KINDS
            )
            t_d = mean_of(rows, names, "default", "zoomout", n, "time")
            row["t default / t lap ZO"] = fmt(
                t_d / mean_of(rows, names, "laplacian", "zoomout", n, "time"), 3
            )
            out.append(row)
    return out


def per_pair(rows, Ls) -> list[dict]:
    out = []
    for name in dict.fromkeys(r["pair"] for r in rows):
        entry = {"pair": name}
        for n in Ls:
            d = [r for r in rows if r["pair"] == name and r["L"] == n and r["method"] == "default"]
            cells = [
                f"{100 * v:.2f}" for b in ("default", *FORCED) for v in values(rows, [name], b, "zoomout", n)
            ]
            entry[f"L={n}"] = " / ".join(cells) + (
                f" ({d[-1]['chosen']})" if d and d[-1].get("chosen") else ""
            )
        out.append(entry)
    return out


def sweep_png(rows, sets, Ls, path) -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(sets), figsize=(5.5 * len(sets), 4.2), squeeze=False)
    curves = (
        ("default", "C1", 2.5),
        ("laplacian", "C0", 1.2),
        ("hybrid", "C4", 1.2),
        ("diffusion", "C3", 1.2),
        ("pyFM", "C2", 1.2),
    )
    for ax, (set_name, names) in zip(axes[0], sets.items(), strict=True):
        for method, color, width in curves:
            for refine, style in (("none", "--"), ("zoomout", "-")):
                ys = [mean_of(rows, names, method, refine, n) for n in Ls]
                if not np.all(np.isnan(ys)):
                    label = f"{method} {'raw' if refine == 'none' else 'refined'}"
                    ax.plot(Ls, ys, style, color=color, lw=width, marker="o", label=label)
        ax.set_title(f"{set_name} ({len(names)} pairs), k={K}")
        ax.set_xlabel("landmarks L")
        ax.set_ylabel("mean geodesic error x100")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sets", default="near-iso,smal,cat-lion", help="comma list of the sets")
    parser.add_argument("--L", default="3,7,15", help="numbers of landmarks")
    parser.add_argument(
        "--methods", default="default,laplacian,hybrid,diffusion,pyFM", help="comma list of what to run"
    )
    parser.add_argument("--add", metavar="CSV", help="rows of an earlier run to add to (e.g. its csv)")
    parser.add_argument(
        "--name", default="landmark_default", help="results: bench/results/NAME.md, .csv, .png"
    )
    args = parser.parse_args(argv)
    every = {"near-iso": str_list(ISO), "smal": smal_pairs(), "cat-lion": ["cat-lion"]}
    sets = {s: every[s] for s in str_list(args.sets)}
    Ls = int_list(args.L)
    rows: list[dict] = read_rows(args.add) if args.add else []
    redo = set(str_list(args.methods))
    rows = [r for r in rows if r["method"] not in redo]  # the methods run now replace theirs
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    for names in sets.values():
        for name in names:
            pair = Pair(name)
            for n in Ls:
                log(f"{name} L={n}")
                run_pair(pair, n, str_list(args.methods), rows)
                save_csv(rows, RESULTS_DIR / f"{args.name}.csv")
    report = Report(args.name)
    report.add(
        f"k={K}, refine='zoomout'; mean geodesic error x100, raw / refined; default = basis=None "
        f"(chooses among {', '.join(AUTO_KINDS)} by geodesic distortion, eigenbasis margin "
        f"{AUTO_MARGIN:g}); {time.perf_counter() - t0:.0f} s in all."
    )
    has_pyfm = any(r["method"] == "pyFM" for r in rows)
    report.table("Means per set and L", summary(rows, sets, Ls, has_pyfm))
    report.table(
        "Per pair, refined: default / laplacian / hybrid / diffusion (chosen kind)", per_pair(rows, Ls)
    )
    sweep_png(rows, sets, Ls, RESULTS_DIR / f"{args.name}.png")
    print(f"results -> {report.save()}, {RESULTS_DIR / f'{args.name}.png'}")


if __name__ == "__main__":
    main()
