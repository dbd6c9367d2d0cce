"""Train the reference recipe on a folder of meshes with ``torchfmap.nn.Trainer``.

``Trainer.from_config`` reads everything from a ``TrainConfig`` (network, solver, losses, Adam,
the cosine schedule over the budget, augmentation): the same code path as ``torchfmap train``
and each DDP rank. Training is unsupervised (pairs within classes of names such as ``cat0``,
``cat1``, else every ordered pair); the weights with the best validation score (the mean
unsupervised loss on a few pairs, lower is better, no ground truth) are kept. The budget is
``--max-steps`` / ``--minutes`` / ``--epochs`` (as ``torchfmap train`` spells them), whichever
ends first, and it is the whole run's:
``--resume`` continues the checkpoint's run up to it. The checkpoint stays whole (weights, best
weights, optimiser, schedule, state, and the errors below), so it resumes and it loads in
``examples/03_learned_match.py --model PATH`` and ``torchfmap match --checkpoint PATH``.

With a ground truth (the demo pair's shipped map, or the folder's ``corres/*.vts`` with its
``test_pairs.txt``), it prints the mean geodesic error of those pairs before and after::

    python examples/04_train.py                                     # the demo pair, 5 steps
    python examples/04_train.py FOLDER --minutes 5 --out model.ckpt
    python examples/04_train.py FOLDER --minutes 10 --out model.ckpt --resume   # 5 more minutes
    python examples/04_train.py FOLDER --epochs 1 --world-size 2    # DDP (gloo on CPU, NCCL on GPUs)
    torchfmap models --recipe faust_r > recipe.json && python examples/04_train.py FOLDER --config recipe.json
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

from torchfmap.data import demo_pair_paths
from torchfmap.errors import ParameterError
from torchfmap.evaluate.scores import discover_pairs, gt_from_map
from torchfmap.io import mesh_files, read_map
from torchfmap.nn import (
    Budget,
    ShapeDataset,
    TrainConfig,
    Trainer,
    build_model,
    class_pairs,
    evaluate,
    load_checkpoint,
    resolve_device,
    unsupervised_score,
)
from torchfmap.nn.trainer import spawn_ddp


def ground_truth(folder: Path, names: list[str], limit: int) -> tuple[list, list]:
    """``(index pairs, ground truths)`` of at most ``limit`` pairs: the demo's shipped map, or
    the folder's (:func:`torchfmap.evaluate.scores.discover_pairs`); none when it has no ground truth."""
    demo_x, demo_y, demo_gt = demo_pair_paths()
    if folder.resolve() == demo_x.parent.resolve():
        pair = (names.index("blob_a"), names.index("blob_b"))
        return [pair], [gt_from_map(read_map(demo_gt))]
    try:
        found = list(itertools.islice(discover_pairs(folder), limit))
    except ParameterError as err:
        print(f"no errors reported: {err}")
        return [], []
    return [(names.index(a), names.index(b)) for a, b, *_ in found], [gt for *_, gt in found]


def main(argv: list[str] | None = None) -> dict:
    """Run the example; returns ``{'steps', 'error_before', 'error_after', 'score_untrained',
    'best_score', 'out'}`` (errors None without a ground truth; with ``--world-size`` > 1 only
    ``'out'``)."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folder", nargs="?", type=Path, help="folder of meshes (default: the demo pair's)")
    parser.add_argument("--out", type=Path, default=Path("model.ckpt"), help="the checkpoint")
    parser.add_argument("--max-steps", type=int, help="optimiser steps (default 5 when no bound is given)")
    parser.add_argument("--minutes", type=float, default=0.0, help="minutes of training (0: no limit)")
    parser.add_argument("--epochs", type=int, help="passes over the pairs")
    parser.add_argument("--resume", action="store_true", help="continue the run saved in --out")
    parser.add_argument("--config", type=Path, help="a recipe file (TrainConfig as JSON)")
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto")
    parser.add_argument("--cache", type=Path, help="precompute cache folder (default: none)")
    parser.add_argument("--eval-pairs", type=int, default=8, help="pairs scored and validated on")
    parser.add_argument("--validate-every", type=int, default=100, help="steps between validations")
    parser.add_argument("--world-size", type=int, default=1, help="> 1: DDP over that many processes")
    args = parser.parse_args(argv)

    folder = args.folder or demo_pair_paths()[0].parent
    recipe = TrainConfig.from_json(args.config) if args.config else TrainConfig()
    unbounded = args.max_steps is None and not args.minutes and args.epochs is None
    budget = Budget(epochs=args.epochs, minutes=args.minutes, steps=5 if unbounded else args.max_steps or 0)
    config = recipe.with_budget(budget)
    cache = args.cache if args.cache else False
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.world_size > 1:
        weights = spawn_ddp(config, mesh_files(folder), args.out, world_size=args.world_size, cache_dir=cache)
        print(f"DDP run over {len(weights)} ranks finished; checkpoint {args.out}")
        return {"out": args.out}

    device = resolve_device(args.device)
    shapes = ShapeDataset(folder, cache, **config.dataset_kwargs(), progress=False)  # each mesh once
    pairs, gts = ground_truth(folder, shapes.names, args.eval_pairs)
    val_pairs = pairs or class_pairs(shapes.names)[: args.eval_pairs]
    untrained, solver, loss_fn = build_model(config)  # the recipe's network before training (same seed)
    untrained = untrained.to(device)
    validate = unsupervised_score(shapes, val_pairs, solver, loss_fn, device=device, augment=config.augment)
    trainer = Trainer.from_config(
        config, shapes, device=device, validate=validate, validate_every=args.validate_every,
        checkpoint=args.out,
    )  # fmt: skip
    if args.resume:
        resumed = trainer.resume()
        print(f"resumed at step {trainer.state.step}" if resumed else f"no {args.out} yet: a new run")
    print(f"budget: {config.budget.describe(trainer.batches_per_epoch)}")
    state = trainer.fit(progress=False)

    best = load_checkpoint(args.out)[0].to(device)  # the weights of the best validation score
    before = evaluate(untrained, shapes, pairs, gts, solver, device=device) if pairs else None
    after = evaluate(best, shapes, pairs, gts, solver, device=device) if pairs else None
    trainer.save(error_before=before, error_after=after)  # the whole checkpoint again, with the errors
    score_untrained = validate(untrained)
    print(f"trained {state.step} steps ({state.epoch} full epochs) in {state.seconds:.1f} s -> {args.out}")
    print(f"validation score (mean unsupervised loss on {len(val_pairs)} pairs, lower is better): "
          f"untrained {score_untrained:.4f}, best {state.best_score:.4f}")  # fmt: skip
    if pairs:
        print(f"mean geodesic error on {len(pairs)} pairs: untrained {before:.4f} -> trained {after:.4f}")
    return {
        "steps": state.step, "error_before": before, "error_after": after,
        "score_untrained": score_untrained, "best_score": state.best_score, "out": args.out,
    }  # fmt: skip


if __name__ == "__main__":
    main()
