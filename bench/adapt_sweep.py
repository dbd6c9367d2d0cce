"""Benchmark: unsupervised test-time adaptation (``adapt``): steps x learning rate on dev pairs.

Run by hand from the repository root (needs the remeshed sets, ``bench/make_remeshed.py``)::

    python3 bench/adapt_sweep.py --checkpoint faust_r --set scape_r --pairs 6
    python3 bench/adapt_sweep.py --checkpoint faust_r --set scape_r --steps 0,10,25,50 --lrs 1e-4,1e-3

For each pair (the first ``--pairs`` of the set's 40, ``learned.dev_set``) and each (steps, lr),
a copy of the network is adapted on the pair by the unsupervised loss (``adapt``: both
directions, no ground truth), then the pair is predicted (functional map, orthogonal rule) and
refined by ZoomOut (``LearnedMatcher``: the model's k -> 2k eigenfunctions). Rows: mean
geodesic error x100 raw / refined and the seconds per pair that the adaptation adds (wall time
of ``adapt``, this process, 1 thread).
Writes ``bench/results/adapt_<name>.md``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from _common import Report, load_note, log
from learned import PairErrors, dev_set

from torchfmap.bases import prepare_shape
from torchfmap.mesh import Mesh
from torchfmap.nn.checkpoints import load_checkpoint
from torchfmap.nn.config import build_model
from torchfmap.nn.data import ShapeDataset
from torchfmap.nn.inference import LearnedMatcher, adapt, predict_p2p


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="faust_r", help="a checkpoint path or shipped name")
    p.add_argument("--set", default="scape_r", help="a dev set of bench/learned.py --sets")
    p.add_argument("--pairs", type=int, default=6)
    p.add_argument("--steps", default="0,10,25,50")
    p.add_argument("--lrs", default="1e-4,1e-3")
    p.add_argument("--name", default=None)
    args = p.parse_args()
    steps = [int(s) for s in args.steps.split(",")]
    lrs = [float(s) for s in args.lrs.split(",")]
    net, config, _ = load_checkpoint(args.checkpoint)
    _, solver, loss_fn = build_model(config)
    files, _, pairs, gts = dev_set(args.set)
    shapes = ShapeDataset(files, None, **config.dataset_kwargs(), progress=False)
    eig = {}
    results: dict[tuple[int, float], list[tuple[float, float, float]]] = {}
    for i, ((a, b), gt) in enumerate(list(zip(pairs, gts, strict=True))[: args.pairs]):
        x, y = shapes[a], shapes[b]
        pe = PairErrors(shapes, (a, b), gt, 500)
        my = Mesh(y["vertices"].numpy(), y["faces"].numpy(), validate=False)
        for j, m in ((a, pe.mesh_x), (b, my)):
            if j not in eig:
                eig[j] = prepare_shape(m, 0)  # grown by the matcher
        for n in steps:
            for lr in lrs if n else lrs[:1]:
                t0 = time.perf_counter()
                tuned = adapt(net, solver, loss_fn, x, y, steps=n, lr=lr) if n else net
                seconds = time.perf_counter() - t0
                raw = predict_p2p(tuned, solver, x, y)
                matcher = LearnedMatcher(tuned, config, device="cpu")
                ref = matcher(eig[a].mesh, eig[b].mesh, refine="zoomout", shapes=(eig[a], eig[b])).p2p_yx
                results.setdefault((n, lr), []).append((pe.mean(raw), pe.mean(ref), seconds))
        log(
            f"pair {i + 1}: "
            + ", ".join(
                f"{n}@{lr:g} {100 * r[-1][0]:.2f}/{100 * r[-1][1]:.2f}" for (n, lr), r in results.items()
            )
        )
    rows = [
        {
            "steps": n,
            "lr": f"{lr:g}" if n else "-",
            "raw x100": 100 * float(np.mean([r[0] for r in res])),
            "ZoomOut x100": 100 * float(np.mean([r[1] for r in res])),
            "adapt s / pair": float(np.mean([r[2] for r in res])),
        }
        for (n, lr), res in results.items()
    ]
    report = Report(f"adapt_{args.name or args.set}")
    report.add(
        f"# Test-time adaptation: `{args.checkpoint}` on {args.set} ({args.pairs} pairs; {load_note()})",
    )
    report.table("Mean geodesic error x100 and the adaptation's cost", rows)
    report.save()


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
