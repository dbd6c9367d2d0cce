"""Benchmark: the learned path on the dev data: errors of trained checkpoints, before / after
training, with test-time adaptation and ZoomOut refinement, per-epoch time, loss curves.

Run by hand from the repository root, after ``torchfmap train`` (see README, "Learning")::

    torchfmap train ../shared/data/tosca5k_dev --out /tmp/learn/dev.ckpt --minutes 15
    python3 bench/learned.py --checkpoints dev=/tmp/learn/dev.ckpt --adapt 10 --adapt-pairs 12
    python3 bench/learned.py --checkpoints eigen=a.ckpt,stack=b.ckpt --pairs all --name bases

Every shipped model on every dev set, one table (``--checkpoints`` defaults to the shipped
models; the remeshed sets come from ``bench/make_remeshed.py``)::

    python3 bench/learned.py --sets faust_val,faust_a,scape_r,scape_a,tosca --name sets

Pairs: ``--sets`` (see :func:`dev_set`), or the older ``--pairs``:
``../shared/data/tosca5k_dev/test_pairs.txt`` (``--pairs all|cat|wolf``) or 40 FAUST_r
validation pairs among tr_reg_070..079 (``--pairs faust_val``). Errors: mean
normalised geodesic error (``geodesic_errors``, ``--max-points`` per pair), averaged over pairs.
Rows per checkpoint: the untrained network of the same recipe and seed (baseline, same
process), the trained network's map from the functional map (``fmap``: orthogonal point-map rule, and
with the pull-back rule for comparison) and from nearest
neighbours in feature space (``features``), ZoomOut (``LearnedMatcher(..., refine='zoomout')``:
from the model's k to 2k eigenfunctions, each mesh prepared once and reused by its pairs),
and, on the first ``--adapt-pairs`` pairs, ``--adapt`` steps of unsupervised test-time
adaptation (``adapt``, lr ``--adapt-lr``) with and without ZoomOut, next to the unadapted
errors on the same pairs. The loss curve of each checkpoint (total per step, moving mean) goes to
``bench/results/learned_<name>_loss.png``. No ground truth is used anywhere but in the errors.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from _common import RESULTS_DIR, Report, load_note, log, require_data

from torchfmap.bases import prepare_shape
from torchfmap.eval import Correspondence, gt_from_vts
from torchfmap.io import read_test_pairs, read_vts
from torchfmap.mesh import Mesh
from torchfmap.nn.checkpoints import load_checkpoint
from torchfmap.nn.config import build_model
from torchfmap.nn.data import ShapeDataset
from torchfmap.nn.inference import LearnedMatcher, adapt, predict_p2p
from torchfmap.operators import GeodesicSolver

#: FAUST_r validation meshes (never trained on by the shipped model: it trains on 000-069).
FAUST_VAL = [f"tr_reg_{i:03d}" for i in range(70, 80)]


def faust_val_pairs(n: int = 40) -> list[tuple[str, str]]:
    """``n`` ordered pairs drawn with seed 0 among :data:`FAUST_VAL`."""
    every = [(a, b) for a in FAUST_VAL for b in FAUST_VAL if a != b]
    pick = np.random.default_rng(0).choice(len(every), n, replace=False)
    return [every[i] for i in pick]


def val_pairs(names: list[str], n: int = 40, seed: int = 0) -> list[tuple[str, str]]:
    """``n`` ordered pairs drawn with ``seed`` among ``names`` (all of them if fewer)."""
    every = [(a, b) for a in names for b in names if a != b]
    pick = np.random.default_rng(seed).choice(len(every), min(n, len(every)), replace=False)
    return [every[i] for i in pick]


#: Dev sets of ``--sets``: (folder, where (shared data or bench/data), meshes, pairs).
SCAPE_VAL = [f"mesh{i:03d}" for i in range(41, 51)]


def dev_set(name: str):
    """``(files, names, pairs (index pairs), ground truths)`` of a dev set of ``--sets``:
    ``faust_val`` (FAUST_r tr_reg_070..079), ``faust_a`` (the same shapes anisotropically
    remeshed, ``bench/make_remeshed.py``), ``scape_r`` / ``scape_a`` (SCAPE poses 041..050 remeshed
    isotropically / anisotropically; the F+S recipe trains on 000..040), each 40 ordered pairs
    drawn with seed 0; ``tosca`` (``tosca5k_dev/test_pairs.txt``); ``smal_val`` (the SMAL_r
    validation animals of the ``smal_r`` recipe, all ordered pairs)."""
    from _common import BENCH_DIR, smal_split

    local = BENCH_DIR / "data"
    if name == "tosca":
        folder = require_data("tosca5k_dev")
        rows = read_test_pairs(folder / "test_pairs.txt")
        names = sorted({n for r in rows for n in r})
        suffix = ".off"
    else:
        folder, names, suffix = {
            "faust_val": (require_data("faust_r_train"), FAUST_VAL, ".off"),
            "faust_a": (local / "faust_a", FAUST_VAL, ".off"),
            "scape_r": (local / "scape_r", SCAPE_VAL, ".off"),
            "scape_a": (local / "scape_a", SCAPE_VAL, ".off"),
            "smal_val": (require_data("smal_r_train"), smal_split()[1], ".off.gz"),
        }[name]
        if not folder.exists():
            raise SystemExit(f"skipped: {folder} not found (python3 bench/make_remeshed.py makes it)")
        rows = val_pairs(names, 40 if name != "smal_val" else 10**6)
    files = [folder / f"{n}{suffix}" for n in names]
    pairs = [(names.index(a), names.index(b)) for a, b in rows]
    gts = [
        gt_from_vts(read_vts(folder / "corres" / f"{a}.vts"), read_vts(folder / "corres" / f"{b}.vts"))
        for a, b in rows
    ]
    return files, names, pairs, gts


def test_pairs(folder, names, which: str):
    if which == "faust_val":
        rows = faust_val_pairs()
    else:
        rows = read_test_pairs(folder / "test_pairs.txt")
    rows = [r for r in rows if which in ("all", "faust_val") or r[0].startswith(which)]
    pairs = [(names.index(a), names.index(b)) for a, b in rows]
    gts = [
        gt_from_vts(read_vts(folder / "corres" / f"{a}.vts"), read_vts(folder / "corres" / f"{b}.vts"))
        for a, b in rows
    ]
    return pairs, gts


class PairErrors:
    """Geodesic errors of many maps of one pair from one set of distance rows (the ground-truth
    sample of ``max_points`` pairs; :func:`geodesic_errors` with a shared solver)."""

    def __init__(self, shapes, pair, gt, max_points: int) -> None:
        x = shapes[pair[0]]
        self.mesh_x = Mesh(x["vertices"].numpy(), x["faces"].numpy(), validate=False)
        idx_x, idx_y = gt
        if len(idx_y) > max_points:
            pick = np.sort(np.random.default_rng(0).choice(len(idx_y), max_points, replace=False))
            idx_x, idx_y = idx_x[pick], idx_y[pick]
        self.gt = Correspondence(idx_x, idx_y)
        uniq, inverse = np.unique(idx_x, return_inverse=True)
        self.rows, self.inverse = GeodesicSolver(self.mesh_x).distances(uniq), inverse

    def mean(self, p2p) -> float:
        pred = np.asarray(p2p)[self.gt.idx_y]
        errors = np.maximum(self.rows[self.inverse, pred], 0.0)
        errors[pred == self.gt.idx_x] = 0.0
        return float(errors.mean() / np.sqrt(self.mesh_x.area))


def loss_png(curves: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, losses in curves.items():
        total = np.array([t["total"] for t in losses])
        if not len(total):  # a shipped model keeps no loss history
            continue
        w = max(1, len(total) // 50)
        ax.plot(np.convolve(total, np.ones(w) / w, mode="valid"), label=f"{label} (mean of {w})")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("unsupervised loss")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run_checkpoint(
    spec: str, args, data, report: Report, rows: list, curves: dict, set_name: str = ""
) -> None:
    """Rows of one checkpoint on one set: ``data`` is ``(files, pairs, gts)``, or a folder of the
    old ``--pairs`` choices."""
    label, path = spec.split("=")
    net, config, ckpt = load_checkpoint(path)
    state = ckpt.get("train_state", {})
    curves[label] = state.get("losses", [])
    if isinstance(data, tuple):
        files, pairs, gts = data
        shapes = ShapeDataset(files, args.cache, **config.dataset_kwargs(), progress=False)
    else:
        folder = data
        files = [folder / f"{n}.off" for n in FAUST_VAL] if args.pairs == "faust_val" else folder
        shapes = ShapeDataset(files, args.cache, **config.dataset_kwargs(), progress=False)
        pairs, gts = test_pairs(folder, shapes.names, args.pairs)
    solver, loss_fn = build_model(config)[1:]
    untrained = build_model(config)[0].eval()
    errors: dict[str, list[float]] = {}
    seconds: dict[str, float] = {}

    def add(method: str, fn, pe: PairErrors):
        t0 = time.perf_counter()
        p2p = fn()
        seconds[method] = seconds.get(method, 0.0) + time.perf_counter() - t0
        errors.setdefault(method, []).append(pe.mean(p2p))
        return p2p

    eigen: dict[int, object] = {}  # ZoomOut's eigenbases, once per shape (not per pair)

    def prepared(i: int, mesh: Mesh):
        if i not in eigen:
            eigen[i] = prepare_shape(mesh, 0)  # grown by the matcher
        return eigen[i]

    def zoomout(network, shapes):  # the prepared shapes' own meshes: the meshes they were prepared for
        matcher = LearnedMatcher(network, config, device="cpu")
        return matcher(shapes[0].mesh, shapes[1].mesh, refine="zoomout", shapes=shapes).p2p_yx

    for i, ((a, b), gt) in enumerate(zip(pairs, gts, strict=True)):
        x, y = shapes[a], shapes[b]
        pe = PairErrors(shapes, (a, b), gt, args.max_points)
        mx = pe.mesh_x
        my = Mesh(y["vertices"].numpy(), y["faces"].numpy(), validate=False)
        if not args.quick:
            add("untrained, fmap", lambda: predict_p2p(untrained, solver, x, y), pe)  # noqa: B023
        base = add("trained, fmap", lambda: predict_p2p(net, solver, x, y), pe)  # noqa: B023
        if not args.quick:
            add("trained, fmap, pull-back", lambda: predict_p2p(net, solver, x, y, p2p_mode="pullback"), pe)  # noqa: B023
            add("trained, features", lambda: predict_p2p(net, solver, x, y, mode="features"), pe)  # noqa: B023
        if not args.no_refine:
            bases = (prepared(a, mx), prepared(b, my))
            add("trained, fmap + zoomout", lambda: zoomout(net, bases), pe)  # noqa: B023
        if args.adapt and i < args.adapt_pairs:
            add("trained, fmap (adapt subset)", lambda: base, pe)  # noqa: B023
            tuned = adapt(net, solver, loss_fn, x, y, steps=args.adapt, lr=args.adapt_lr)
            add(f"adapt {args.adapt}, fmap", lambda: predict_p2p(tuned, solver, x, y), pe)  # noqa: B023
            if not args.no_refine:
                add(f"adapt {args.adapt} + zoomout", lambda: zoomout(tuned, bases), pe)  # noqa: B023
        log(
            f"{label} pair {i + 1}/{len(pairs)}: "
            + ", ".join(f"{m} {np.mean(e):.4f}" for m, e in errors.items())
        )
    for method, errs in errors.items():
        rows.append(
            {
                "model": label,
                **({"set": set_name} if set_name else {}),
                "method": method,
                "pairs": len(errs),
                "mean error x100": 100 * float(np.mean(errs)),
                "s / pair": seconds[method] / len(errs),
            }
        )
    secs = state.get("epoch_seconds", [])
    if set_name and set_name != args.sets.split(",")[0]:
        return  # the training summary once per checkpoint
    report.add(
        f"**{label}** (`{path}`): {config.basis} basis K={config.k}, inputs {config.inputs}, "
        f"{state.get('step', '?')} steps, {state.get('epoch', '?')} full epochs, "
        f"{state.get('seconds', float('nan')):.0f} s training; seconds per full epoch: "
        + (", ".join(f"{s:.0f}" for s in secs) if secs else "n/a")
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--checkpoints", default=None, help="label=path,label=path (default: every shipped model)"
    )
    parser.add_argument(
        "--sets",
        default=None,
        help="comma list of dev sets (faust_val, faust_a, scape_r, scape_a, tosca, smal_val): one "
        "table of every checkpoint on every set (replaces --pairs)",
    )
    parser.add_argument(
        "--pairs",
        default="all",
        choices=["all", "cat", "wolf", "faust_val"],
        help="tosca5k_dev test pairs, or faust_val: 40 pairs among FAUST_r tr_reg_070..079",
    )
    parser.add_argument("--name", default="dev")
    parser.add_argument("--adapt", type=int, default=0)
    parser.add_argument("--adapt-lr", type=float, default=1e-4)
    parser.add_argument("--adapt-pairs", type=int, default=12)
    parser.add_argument("--max-points", type=int, default=500)
    parser.add_argument("--no-refine", action="store_true")
    parser.add_argument("--max-pairs", type=int, default=0, help="the first N pairs of each set (0: all)")
    parser.add_argument(
        "--quick", action="store_true", help="only the trained fmap and ZoomOut rows (no untrained, features)"
    )
    parser.add_argument("--cache", default=None)
    args = parser.parse_args()
    if args.checkpoints is None:
        from torchfmap.nn.shipped import shipped_models

        args.checkpoints = ",".join(f"{name}={path}" for name, path in shipped_models().items())
    report = Report(f"learned_{args.name}")
    rows, curves = [], {}
    if args.sets:
        report.add(f"# Learned path on the dev sets {args.sets} ({load_note()} at start)")
        for set_name in args.sets.split(","):
            files, _, pairs, gts = dev_set(set_name)
            pairs, gts = pairs[: args.max_pairs or None], gts[: args.max_pairs or None]
            for spec in args.checkpoints.split(","):
                run_checkpoint(spec, args, (files, pairs, gts), report, rows, curves, set_name)
    else:
        data = "faust_r_train" if args.pairs == "faust_val" else "tosca5k_dev"
        report.add(f"# Learned path on {data} ({args.pairs} pairs; {load_note()} at start)")
        for spec in args.checkpoints.split(","):
            run_checkpoint(spec, args, require_data(data), report, rows, curves)
    report.table("Mean geodesic error / sqrt(area), x100; seconds per pair (precompute excluded)", rows)
    png = RESULTS_DIR / f"learned_{args.name}_loss.png"
    loss_png(curves, png)
    report.add(f"Loss curves: `{png.relative_to(RESULTS_DIR.parent.parent)}`. {load_note()} at end.")
    report.save()


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
