"""Benchmark: the learned path on the dev data: errors of trained checkpoints, before / after
training, with test-time adaptation and ZoomOut refinement, per-epoch time, loss curves.

Run by hand from the repository root, after ``torchfmap train`` (see README, "Learning")::

    torchfmap train ../shared/data/tosca5k_dev --out /tmp/learn/dev.ckpt --minutes 15
    python3 bench/learned.py --checkpoints dev=/tmp/learn/dev.ckpt --adapt 10 --adapt-pairs 12
    python3 bench/learned.py --checkpoints eigen=a.ckpt,stack=b.ckpt --pairs all --name bases

Pairs: ``../shared/data/tosca5k_dev/test_pairs.txt`` (``--pairs all|cat|wolf``). Errors: mean
normalised geodesic error (``geodesic_errors``, ``--max-points`` per pair), averaged over pairs.
Rows per checkpoint: the untrained network of the same recipe and seed (baseline, same
process), the trained network's map from the functional map (``fmap``) and from nearest
neighbours in feature space (``features``), ZoomOut (``refine_p2p``: 30 -> 120 eigenfunctions),
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

from torchfmap.eval import geodesic_errors, gt_from_vts, read_vts
from torchfmap.mesh import Mesh
from torchfmap.nn.data import ShapeDataset
from torchfmap.nn.train import adapt, build_model, load_checkpoint, predict_p2p, refine_p2p


def test_pairs(folder, names, which: str):
    rows = [ln.split()[:2] for ln in (folder / "test_pairs.txt").read_text().splitlines() if ln.strip()]
    rows = [r for r in rows if which == "all" or r[0].startswith(which)]
    pairs = [(names.index(a), names.index(b)) for a, b in rows]
    gts = [
        gt_from_vts(read_vts(folder / "corres" / f"{a}.vts"), read_vts(folder / "corres" / f"{b}.vts"))
        for a, b in rows
    ]
    return pairs, gts


def errors_of(maps, shapes, pairs, gts, max_points) -> float:
    out = []
    for p2p, (a, _), gt in zip(maps, pairs, gts, strict=True):
        x = shapes[a]
        mesh_x = Mesh(x["vertices"].numpy(), x["faces"].numpy(), validate=False)
        out.append(geodesic_errors(mesh_x, p2p, gt, max_points=max_points).mean())
    return float(np.mean(out))


def loss_png(curves: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for label, losses in curves.items():
        total = np.array([t["total"] for t in losses])
        w = max(1, len(total) // 50)
        ax.plot(np.convolve(total, np.ones(w) / w, mode="valid"), label=f"{label} (mean of {w})")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("unsupervised loss")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run_checkpoint(spec: str, args, folder, report: Report, rows: list, curves: dict) -> None:
    label, path = spec.split("=")
    net, config, ckpt = load_checkpoint(path)
    state = ckpt.get("train_state", {})
    curves[label] = state.get("losses", [])
    shapes = ShapeDataset(folder, args.cache, **config.dataset_kwargs(), progress=False)
    pairs, gts = test_pairs(folder, shapes.names, args.pairs)
    solver, loss_fn = build_model(config)[1:]
    untrained = build_model(config)[0].eval()
    secs = state.get("epoch_seconds", [])

    def row(method, maps, n, t0, label=label):
        e = errors_of(maps, shapes, pairs[:n], gts[:n], args.max_points)
        rows.append(
            {
                "model": label,
                "method": method,
                "pairs": n,
                "mean error": e,
                "s / pair": (time.perf_counter() - t0) / n,
            }
        )
        log(f"{label} {method}: {e:.4f}")

    n_all = len(pairs)
    t0 = time.perf_counter()
    row(
        "untrained, fmap",
        [predict_p2p(untrained, solver, shapes[a], shapes[b]) for a, b in pairs],
        n_all,
        t0,
    )
    t0 = time.perf_counter()
    base = [predict_p2p(net, solver, shapes[a], shapes[b]) for a, b in pairs]
    row("trained, fmap", base, n_all, t0)
    t0 = time.perf_counter()
    row(
        "trained, features",
        [predict_p2p(net, solver, shapes[a], shapes[b], mode="features") for a, b in pairs],
        n_all,
        t0,
    )

    def meshes(a, b):
        return [
            Mesh(shapes[i]["vertices"].numpy(), shapes[i]["faces"].numpy(), validate=False) for i in (a, b)
        ]

    if not args.no_refine:
        t0 = time.perf_counter()
        row(
            "trained, fmap + zoomout",
            [refine_p2p(*meshes(a, b), p) for (a, b), p in zip(pairs, base, strict=True)],
            n_all,
            t0,
        )
    if args.adapt:
        n = min(args.adapt_pairs, n_all)
        row("trained, fmap (adapt subset)", base[:n], n, time.perf_counter())
        t0 = time.perf_counter()
        adapted = []
        for a, b in pairs[:n]:
            tuned = adapt(net, solver, loss_fn, shapes[a], shapes[b], steps=args.adapt, lr=args.adapt_lr)
            adapted.append(predict_p2p(tuned, solver, shapes[a], shapes[b]))
        row(f"adapt {args.adapt} steps, fmap", adapted, n, t0)
        if not args.no_refine:
            t0 = time.perf_counter()
            row(
                f"adapt {args.adapt} + zoomout",
                [refine_p2p(*meshes(a, b), p) for (a, b), p in zip(pairs[:n], adapted, strict=True)],
                n,
                t0,
            )
    report.add(
        f"**{label}** (`{path}`): {config.basis} basis K={config.k}, inputs {config.inputs}, "
        f"{state.get('step', '?')} steps, {state.get('epoch', '?')} full epochs, "
        f"{state.get('seconds', float('nan')):.0f} s training; seconds per full epoch: "
        + (", ".join(f"{s:.0f}" for s in secs) if secs else "n/a (budget ended inside the first epoch)")
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoints", required=True, help="label=path,label=path")
    parser.add_argument("--pairs", default="all", choices=["all", "cat", "wolf"])
    parser.add_argument("--name", default="dev")
    parser.add_argument("--adapt", type=int, default=0)
    parser.add_argument("--adapt-lr", type=float, default=1e-3)
    parser.add_argument("--adapt-pairs", type=int, default=12)
    parser.add_argument("--max-points", type=int, default=1000)
    parser.add_argument("--no-refine", action="store_true")
    parser.add_argument("--cache", default=None)
    args = parser.parse_args()
    folder = require_data("tosca5k_dev")
    report = Report(f"learned_{args.name}")
    report.add(f"# Learned path on tosca5k_dev ({args.pairs} test pairs; {load_note()} at start)")
    rows, curves = [], {}
    for spec in args.checkpoints.split(","):
        run_checkpoint(spec, args, folder, report, rows, curves)
    report.table("Mean geodesic error (normalised by sqrt(area))", rows)
    png = RESULTS_DIR / f"learned_{args.name}_loss.png"
    loss_png(curves, png)
    report.add(f"Loss curves: `{png.relative_to(RESULTS_DIR.parent.parent)}`. {load_note()} at end.")
    report.save()


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
