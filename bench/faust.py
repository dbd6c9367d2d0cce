"""Benchmark: classical matching on FAUST_r humans (dev pairs of the training split), ours vs pyFM.

Run by hand from the repository root (tables to stdout and ``bench/results/faust.md``, rows to
``faust.csv``, the landmark sweep to ``faust.png``)::

    python3 bench/faust.py                        # 40 dev pairs, L = 0 (none), 3, 7, 15
    python3 bench/faust.py --pairs 40 --L 0 --name faust_nolandmarks   # no landmarks, 40 pairs
    python3 bench/faust.py --no-pyfm --match w_orient=0.3   # ours with other match() settings

Pairs: 40 ordered pairs drawn (seed 0) among ``faust_r_train/tr_reg_060`` .. ``079`` (people 6
and 7, ten poses each; the held-out test split 080-099 is never read), the first ``--pairs`` of
them. Errors: mean geodesic error on x / sqrt(area) x100 at every ``--every``-th ground-truth row
of ``corres/*.vts`` (default 5: 1000 of the 5000 rows; ``--every 1`` for all), the same rows for
every method. Landmarks: ``L`` ground-truth rows spread by farthest-point sampling
(``landmarks_from_gt``), the same for every method.

Methods:

- ``ours``: ``match(x, y, k=K)`` (no landmarks) or ``match(x, y, landmarks, k=K)`` (its default
  basis with landmarks), raw and ``refine='zoomout'``; ``--match key=value,...`` adds settings;
- ``--also hybrid,diffusion`` (with landmarks) adds ``ours <basis>`` rows for other kinds, raw
  and their refinement. (``bench/results/faust.md`` and ``faust_landmarks.md`` were measured
  when the landmark default was ``diffusion``: their ``ours`` rows at L > 0 are that basis, and
  ``ours laplacian`` the eigenbasis, now the default.)
- ``pyFM``: ``bench/_pyfm.py`` with pyFM's quick-start settings (:data:`PYFM_SETTINGS`: 100 WKS
  energies on 128 eigenpairs, every second kept; ``w_descr=1, w_lap=0.1, w_dcomm=1,
  w_orient=1``), raw and after ``zoomout_refine`` (K -> 2K, step K // 10, like ours). (The
  weights of its README cat-lion example, ``PYFM_FIT`` without orientation, are far weaker on
  humans.)
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from _common import RESULTS_DIR, Report, int_list, log
from _pairs import Pair, save_csv
from _pyfm import run_pyfm

from torchfmap.bases import prepare_shape
from torchfmap.eval import Correspondence
from torchfmap.pipeline import match

K = 50
#: pyFM's quick-start pipeline (its README): 100 WKS energies on 128 eigenpairs, every 2nd kept,
#: descriptor, Laplacian (resolvent), descriptor-commutativity and orientation terms.
PYFM_SETTINGS = {
    "pyFM": dict(
        n_descr=100, k_descr=128, subsample_step=2, fit=dict(w_descr=1, w_lap=0.1, w_dcomm=1, w_orient=1)
    ),
}
IDS = [f"{i:03d}" for i in range(60, 80)]


def dev_pairs(n: int) -> list[tuple[str, str]]:
    """The first ``n`` of 40 ordered pairs drawn with seed 0 among :data:`IDS`."""
    every = [(a, b) for a in IDS for b in IDS if a != b]
    pick = np.random.default_rng(0).choice(len(every), 40, replace=False)
    return [every[i] for i in pick][:n]


def parse_settings(text: str) -> dict:
    """``'w_orient=0.3,k=40'`` -> ``{'w_orient': 0.3, 'k': 40}`` (values read as JSON)."""
    out = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        key, _, value = item.partition("=")
        out[key.strip()] = json.loads(value)
    return out


def run(
    pairs, Ls, with_pyfm: bool, settings: dict, every: int, name: str, also: tuple[str, ...] = ()
) -> list[dict]:
    rows: list[dict] = []
    shapes: dict[str, tuple] = {}  # each mesh prepared once for all its pairs and settings
    for a, b in pairs:
        pair = Pair(f"faust:{a}-{b}")
        pair.gt = Correspondence(pair.gt.idx_x[::every], pair.gt.idx_y[::every])
        for mesh, key in ((pair.x, a), (pair.y, b)):
            shapes.setdefault(key, (mesh, prepare_shape(mesh, 0)))
        (pair.x, sx), (pair.y, sy) = shapes[a], shapes[b]
        for n in Ls:
            lmk = pair.landmarks(n) if n else None
            log(f"{pair.name} L={n}")
            methods = [("ours", {})] + [(f"ours {b}", {"basis": b}) for b in (also if n else ())]
            for method, extra in methods:
                t0 = time.perf_counter()
                res = match(
                    pair.x, pair.y, landmarks=lmk, k=K, refine="zoomout", shapes=(sx, sy), **settings, **extra
                )
                wall = time.perf_counter() - t0
                for stage, p2p in (("raw", res.p2p_yx_initial), ("refined", res.p2p_yx)):
                    err = pair.errors(p2p)
                    rows.append(
                        {
                            "pair": pair.name,
                            "L": n,
                            "method": method,
                            "stage": stage,
                            "kind": res.kind,
                            "mean": float(err.mean()),
                            "time": wall,
                        }
                    )
            if with_pyfm:
                for method, settings_pyfm in PYFM_SETTINGS.items():
                    out = run_pyfm(pair.x, pair.y, k=K, landmarks=lmk, refine=("zoomout",), **settings_pyfm)
                    for stage, key in (("raw", None), ("refined", "zoomout")):
                        err = pair.errors(out.p2p[key])
                        rows.append(
                            {
                                "pair": pair.name,
                                "L": n,
                                "method": method,
                                "stage": stage,
                                "kind": "",
                                "mean": float(err.mean()),
                                "time": out.times[key],
                            }
                        )
        pair._rows = None  # the pair's distance rows: freed
        save_csv(rows, RESULTS_DIR / f"{name}.csv")
    return rows


def summary(rows: list[dict], Ls) -> list[dict]:
    out = []
    methods = list(dict.fromkeys(r["method"] for r in rows))
    for n in Ls:
        for m in methods:
            line = {"L": n, "method": m}
            for stage in ("raw", "refined"):
                errs = np.array(
                    [r["mean"] for r in rows if r["L"] == n and r["method"] == m and r["stage"] == stage]
                )
                if not len(errs):
                    continue
                line[f"{stage} mean"] = f"{100 * errs.mean():.2f}"
                line[f"{stage} median"] = f"{100 * np.median(errs):.2f}"
                line[f"{stage} > 10"] = f"{int((errs > 0.1).sum())}/{len(errs)}"
                base = [
                    r["mean"] for r in rows if r["L"] == n and r["method"] == "pyFM" and r["stage"] == stage
                ]
                if base and m != "pyFM":
                    line[f"{stage} / pyFM"] = f"{errs.mean() / np.mean(base):.2f}"
            if line.keys() - {"L", "method"}:
                out.append(line)
    return out


def sweep_png(rows: list[dict], Ls, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for m in dict.fromkeys(r["method"] for r in rows):
        for stage, style in (("raw", "--"), ("refined", "-")):
            xs = [
                n for n in Ls if any(r["L"] == n and r["method"] == m and r["stage"] == stage for r in rows)
            ]
            ys = [
                100
                * np.mean(
                    [r["mean"] for r in rows if r["L"] == n and r["method"] == m and r["stage"] == stage]
                )
                for n in xs
            ]
            if xs:
                ax.plot(xs, ys, style, marker="o", label=f"{m} {stage}")
    ax.set_xlabel("landmarks L (0: none)")
    ax.set_ylabel("mean geodesic error x100")
    ax.set_title("FAUST_r dev pairs (060-079)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=40, help="how many of the 40 dev pairs")
    parser.add_argument("--L", default="0,3,7,15", help="numbers of landmarks (0: none)")
    parser.add_argument("--every", type=int, default=5, help="score every n-th ground-truth row")
    parser.add_argument("--match", default="", help="extra match() settings, key=value,...")
    parser.add_argument("--no-pyfm", action="store_true", help="skip pyFM")
    parser.add_argument("--also", default="", help="more bases to run with landmarks, e.g. hybrid,diffusion")
    parser.add_argument("--name", default="faust", help="results: bench/results/NAME.md, .csv, .png")
    args = parser.parse_args(argv)
    Ls, settings = int_list(args.L), parse_settings(args.match)
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    also = tuple(filter(None, (b.strip() for b in args.also.split(","))))
    rows = run(dev_pairs(args.pairs), Ls, not args.no_pyfm, settings, args.every, args.name, also)
    report = Report(args.name)
    command = f"python3 bench/faust.py --pairs {args.pairs} --L {args.L} --every {args.every}"
    command += (f" --match {args.match}" if args.match else "") + (" --no-pyfm" if args.no_pyfm else "")
    command += f" --also {args.also}" if also else ""
    seconds = time.perf_counter() - t0
    report.add(f"`{command}`; k={K}; mean geodesic error x100 ({args.pairs} pairs, {seconds:.0f} s)")

    report.table("Means per L and method", summary(rows, Ls))
    sweep_png(rows, Ls, RESULTS_DIR / f"{args.name}.png")
    print(f"results -> {report.save()}, {RESULTS_DIR / f'{args.name}.png'}")


if __name__ == "__main__":
    main()
