"""Benchmark: where the FAUST_r recipe converges: validation error against steps and wall time.

Run by hand from the repository root (one training job on the machine; it is the heavy one)::

    OMP_NUM_THREADS=1 python3 bench/learned_curve.py --minutes 45 --every 250
    python3 bench/learned_curve.py --minutes 2 --every 20 --val-pairs 2 --name curve_smoke

Trains the shipped model's recipe (``torchfmap models``: WKS 128 inputs, DiffusionNet width 128
with 256 features, K = 100, K_net = 128, gradient clipping 1, Adam 1e-3 with the cosine schedule
over ``--minutes``) on FAUST_r ``tr_reg_000..069`` through :class:`torchfmap.nn.Trainer`, and
every ``--every`` steps scores the network on the first ``--val-pairs`` of the 40 validation pairs
among ``tr_reg_070..079`` (``bench/learned.py``'s ``faust_val``): mean geodesic error / sqrt(area)
of the raw functional-map point maps (500 ground-truth points per pair), next to the
unsupervised validation loss that ``torchfmap train`` selects by. The ground truth is read only
to report; the weights are never selected by it. The curve is shorter than the shipped model's
95-minute run, so its schedule anneals sooner: it shows the shape of convergence, not the shipped
model's final error. Writes ``bench/results/<name>.md`` and ``<name>.png`` (error and loss
against steps and minutes).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from _common import RESULTS_DIR, Report, log, require_data
from learned import FAUST_VAL, PairErrors, faust_val_pairs

from torchfmap.eval import gt_from_vts
from torchfmap.io import read_vts
from torchfmap.nn.config import TrainConfig, build_solver
from torchfmap.nn.data import ShapeDataset, class_pairs
from torchfmap.nn.inference import predict_p2p
from torchfmap.nn.train import unsupervised_score
from torchfmap.nn.trainer import Trainer

RECIPE = dict(k=100, n_wks=128, k_net=128, width=128, c_out=256, clip_grad=1.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--minutes", type=float, default=45.0, help="training budget (cosine schedule over it)"
    )
    parser.add_argument("--every", type=int, default=250, help="steps between validations")
    parser.add_argument("--val-pairs", type=int, default=8, help="validation pairs scored by geodesic error")
    parser.add_argument("--cache", default=None, help="precompute cache folder (default: per-user cache)")
    parser.add_argument("--name", default="learned_curve")
    args = parser.parse_args()
    folder = require_data("faust_r_train")
    config = TrainConfig(minutes=args.minutes, epochs=None, **RECIPE)
    train_files = [folder / f"tr_reg_{i:03d}.off" for i in range(70)]
    shapes = ShapeDataset(train_files, args.cache, **config.dataset_kwargs(), progress=True)
    val = ShapeDataset([folder / f"{n}.off" for n in FAUST_VAL], args.cache, **config.dataset_kwargs())
    rows = faust_val_pairs()[: args.val_pairs]
    gts = [
        gt_from_vts(read_vts(folder / "corres" / f"{a}.vts"), read_vts(folder / "corres" / f"{b}.vts"))
        for a, b in rows
    ]
    index = {n: i for i, n in enumerate(val.names)}
    val_pairs = [(index[a], index[b]) for a, b in rows]
    scorers = [PairErrors(val, p, gt, 500) for p, gt in zip(val_pairs, gts, strict=True)]
    pairs = class_pairs(shapes.names)
    solver, loss_fn = build_solver(config)
    picked = pairs[:: max(1, len(pairs) // 6)][:6]
    unsupervised = unsupervised_score(shapes, picked, solver, loss_fn)
    curve: list[dict] = []
    t_start = time.perf_counter()
    eval_seconds = 0.0

    def validate(model) -> float:
        nonlocal eval_seconds
        t0 = time.perf_counter()
        score = unsupervised(model)
        errors = [
            s.mean(predict_p2p(model, solver, val[a], val[b]))
            for s, (a, b) in zip(scorers, val_pairs, strict=True)
        ]
        eval_seconds += time.perf_counter() - t0
        point = {
            "step": (len(curve) + 1) * args.every,  # every N steps (the last: fixed below)
            "minutes": (time.perf_counter() - t_start - eval_seconds) / 60,
            "val error": float(np.mean(errors)),
            "val loss": score,
        }
        curve.append(point)
        log(
            f"step {point['step']}: error {point['val error']:.4f}, loss {score:.4g}, "
            f"{point['minutes']:.1f} min"
        )
        model.train()
        return score

    trainer = Trainer.from_config(
        config, shapes, pairs, device="cpu", validate=validate, validate_every=args.every
    )
    state = trainer.fit()
    if curve:
        curve[-1]["step"] = state.step  # the validation at the end
    report = Report(args.name)
    report.add(
        f"`python3 bench/learned_curve.py --minutes {args.minutes:g} --every {args.every} --val-pairs "
        f"{args.val_pairs}` ({torch.get_num_threads()} torch threads): {state.step} steps in "
        f"{state.seconds:.0f} s of training ({state.seconds / max(state.step, 1):.2f} s / step, "
        f"{len(pairs)} ordered pairs per epoch: {len(pairs) * state.seconds / max(state.step, 1) / 60:.0f} "
        f"min / epoch), validations excluded from the minutes below."
    )
    report.table(
        "Validation against steps",
        [{k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in p.items()} for p in curve],
    )
    png = RESULTS_DIR / f"{args.name}.png"
    plot(curve, state.losses, png)
    print(f"results -> {report.save()}, {png}")


def plot(curve: list[dict], losses: list, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    steps = [p["step"] for p in curve]
    ax1.plot(steps, [100 * p["val error"] for p in curve], "C3-o", label="validation error x100")
    ax1.set_xlabel("step")
    ax1.set_ylabel("mean geodesic error x100 (validation pairs)")
    top = ax1.secondary_xaxis(
        "top", functions=(_interp(curve, "step", "minutes"), _interp(curve, "minutes", "step"))
    )
    top.set_xlabel("minutes of training")
    ax1.grid(alpha=0.3)
    total = np.array([t["total"] for t in losses])
    w = max(1, len(total) // 50)
    ax2.plot(np.convolve(total, np.ones(w) / w, mode="valid"), label=f"training loss (mean of {w})")
    ax2.plot(steps, [p["val loss"] for p in curve], "C1-o", label="validation loss")
    ax2.set_yscale("log")
    ax2.set_xlabel("step")
    ax2.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _interp(curve, a: str, b: str):
    xs = np.array([p[a] for p in curve], dtype=float)
    ys = np.array([p[b] for p in curve], dtype=float)
    return lambda v: np.interp(v, xs, ys)


if __name__ == "__main__":
    main()
