"""Benchmark: the self-seeded second stage of the learned path (``torchfmap.experimental.stages``) against
stage 1, raw and after ZoomOut, on validation pairs, with the time per pair.

Run by hand from the repository root::

    python3 bench/stage_two.py --sets faust_val --checkpoints humans
    python3 bench/stage_two.py --sets smal_val --checkpoints smal=/work/ckpt/smal_xyz.ckpt
    python3 bench/stage_two.py --sets faust_val,smal_val --checkpoints humans,smal=... --max-pairs 12

Pairs: :func:`learned.dev_set` (40 FAUST_r validation pairs among tr_reg_070..079; every
ordered pair of the SMAL_r validation animals). Errors: mean normalised geodesic error x100
over ``--max-points`` ground-truth points per pair, averaged over pairs. ``stage 1``: the
checkpoint's eigenbasis map; ``stage 2``: the same features solved in diffusion bases at the
consistent seeds of stage 1 (the network was trained for stage 1 only unless the checkpoint
says otherwise); ``+ZO``: ZoomOut 50 -> 200 from each (``refine_p2p``). ``seeds``: the mean
count of consistent seed pairs. Time: seconds per pair of each map (network, solves, seeding,
kernels; shapes prepared once per mesh are not counted); ``s_per_step``: one training step
(forward, both losses, backward) of stage 1 alone and of both stages on ``--step-pairs`` pairs.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from _common import Report, log
from learned import PairErrors, dev_set

from torchfmap.bases import prepare_shape
from torchfmap.experimental.stages import StageTwo, StageTwoLoss, two_stage_p2p
from torchfmap.mesh import Mesh
from torchfmap.nn.checkpoints import load_checkpoint
from torchfmap.nn.config import build_solver
from torchfmap.nn.data import ShapeDataset, collate_pairs
from torchfmap.nn.inference import REFINE_K_FINAL, predict_p2p, refine_p2p
from torchfmap.nn.train import pair_loss


def step_times(net, config, shapes, pairs) -> tuple[float, float]:
    """Seconds per training step (forward, loss, backward; no optimiser) of stage 1 alone and of
    both stages, on the same ``pairs``, after one untimed warm-up pass of each (shapes of the
    second stage prepared then, as in training after the first epoch)."""
    solver, loss_fn = build_solver(config)
    stage = StageTwoLoss(shapes.mesh)
    batches = [collate_pairs([(shapes[a], shapes[b])]) for a, b in pairs]
    generator = torch.Generator().manual_seed(0)
    net.train()
    out = []
    for extra in ((), (stage,)):
        for timed in (False, True):
            t0 = time.perf_counter()
            for batch in batches:
                net.zero_grad()
                terms = pair_loss(net, solver, loss_fn, batch, generator, extra)
                terms["total"].backward()
            if timed:
                out.append((time.perf_counter() - t0) / len(batches))
    net.eval()
    return out[0], out[1]


def run(set_name: str, spec: str, args) -> dict:
    label, path = spec.split("=") if "=" in spec else (spec, spec)
    net, config, _ = load_checkpoint(path)
    files, names, pairs, gts = dev_set(set_name)
    pairs, gts = pairs[: args.max_pairs], gts[: args.max_pairs]
    shapes = ShapeDataset(files, args.cache, **config.dataset_kwargs(), progress=False)
    solver, _ = build_solver(config)
    stage = StageTwo(n_seeds=args.seeds)
    prepared: dict[int, object] = {}

    def shape(i: int):
        if i not in prepared:
            item = shapes[i]
            mesh = Mesh(item["vertices"].numpy(), item["faces"].numpy(), validate=False)
            prepared[i] = prepare_shape(mesh, min(REFINE_K_FINAL, mesh.n_vertices - 1))
        return prepared[i]

    errors: dict[str, list[float]] = {}
    seconds = {"stage 1": 0.0, "stage 2": 0.0}
    counts = []
    for n, ((a, b), gt) in enumerate(zip(pairs, gts, strict=True)):
        sx, sy = shape(a), shape(b)
        pe = PairErrors(shapes, (a, b), gt, args.max_points)
        t0 = time.perf_counter()
        first, second, used = two_stage_p2p(net, solver, shapes[a], shapes[b], sx, sy, stage)
        total = time.perf_counter() - t0
        t0 = time.perf_counter()
        predict_p2p(net, solver, shapes[a], shapes[b])
        seconds["stage 1"] += time.perf_counter() - t0  # stage 1 alone
        seconds["stage 2"] += total
        counts.append(used)
        for method, p2p in (("stage 1", first), ("stage 2", second)):
            errors.setdefault(method, []).append(pe.mean(p2p))
            if args.zoomout:
                refined = refine_p2p(sx.mesh, sy.mesh, p2p, shapes=(sx, sy))
                errors.setdefault(method + " +ZO", []).append(pe.mean(refined))
        log(
            f"{set_name} {label} pair {n + 1}/{len(pairs)}: "
            + ", ".join(f"{m} {100 * v[-1]:.2f}" for m, v in errors.items())
        )
    step = step_times(net, config, shapes, pairs[: args.step_pairs]) if args.step_pairs else (np.nan, np.nan)
    mean = {m: 100 * float(np.mean(v)) for m, v in errors.items()}
    return dict(
        set=set_name, model=label, pairs=len(pairs), **{m: f"{v:.3f}" for m, v in mean.items()},
        ratio_raw=f"{mean['stage 2'] / mean['stage 1']:.3f}",
        ratio_zo=f"{mean['stage 2 +ZO'] / mean['stage 1 +ZO']:.3f}" if args.zoomout else "",
        seeds=f"{np.mean(counts):.1f}", s_per_pair_1=f"{seconds['stage 1'] / len(pairs):.3f}",
        s_per_pair_2=f"{seconds['stage 2'] / len(pairs):.3f}",
        time_ratio=f"{seconds['stage 2'] / max(seconds['stage 1'], 1e-12):.2f}",
        s_per_step_1=f"{step[0]:.3f}", s_per_step_2=f"{step[1]:.3f}", step_ratio=f"{step[1] / step[0]:.2f}",
    )  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sets", default="faust_val")
    p.add_argument(
        "--checkpoints", default="humans", help="one per set, comma-separated (label=path or a name)"
    )
    p.add_argument("--max-pairs", type=int, default=40)
    p.add_argument("--max-points", type=int, default=1000)
    p.add_argument("--seeds", type=int, default=StageTwo.n_seeds)
    p.add_argument("--no-zoomout", dest="zoomout", action="store_false")
    p.add_argument("--step-pairs", type=int, default=4, help="pairs timed for the training step (0: none)")
    p.add_argument("--cache", default=None)
    p.add_argument("--name", default="stage_two")
    args = p.parse_args()
    sets, specs = args.sets.split(","), args.checkpoints.split(",")
    if len(specs) == 1:
        specs = specs * len(sets)
    report = Report(args.name)
    rows = [run(set_name, spec, args) for set_name, spec in zip(sets, specs, strict=True)]
    report.table("Second stage of the learned path: stage 1 vs stage 2 (x100 mean geodesic error)", rows)
    report.save()


if __name__ == "__main__":
    main()
