"""The bodies of ``torchfmap models`` and ``torchfmap train``: the learned path's commands,
which import torch and :mod:`torchfmap.nn` on first use (``import torchfmap`` and the
classical commands stay without torch)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .errors import TorchFmapError


def cmd_models(args: argparse.Namespace) -> int:
    from .nn.checkpoints import read_checkpoint  # torch: only for this command
    from .nn.shipped import shipped_models

    models = shipped_models()
    if not models:
        print("no models shipped in this installation")
    for name, path in models.items():
        ckpt = read_checkpoint(path)
        cfg = ckpt.get("config", {})
        print(f"{name}  ({path.stat().st_size / 1e6:.1f} MB, {cfg.get('basis')} basis K={cfg.get('k')})")
        for key, value in ckpt.get("provenance", {}).items():
            print(f"  {key}: {value}")
    return 0


def cmd_train(args: argparse.Namespace) -> int:

    from .nn.checkpoints import load_checkpoint
    from .nn.config import TrainConfig, build_solver
    from .nn.data import ShapeDataset, class_pairs
    from .nn.stages import StageTwo
    from .nn.train import total_steps, train_recipe, unsupervised_score

    budget = {
        name: value
        for name, value in (("epochs", args.epochs), ("minutes", args.minutes), ("max_steps", args.max_steps))
        if value
    }
    recipe = {
        name: getattr(args, name)
        for name in (
            "k",
            "basis",
            "inputs",
            "augment",
            "stages",
            "n_wks",
            "k_net",
            "width",
            "c_out",
            "lr",
            "clip_grad",
        )
        if getattr(args, name, None) is not None
    }
    config = TrainConfig(seed=args.seed, **budget, **recipe)
    init = None
    if args.init:
        if args.resume:
            raise TorchFmapError("--init starts a new run and --resume continues one. Fix: drop one.")
        init_net, init_config, _ = load_checkpoint(args.init)
        config = TrainConfig(**{**vars(init_config), "seed": args.seed, **budget, **recipe})
        if not budget:
            config.epochs, config.minutes, config.max_steps = TrainConfig.epochs, 0.0, 0
        init = init_net.state_dict()
    if args.resume and Path(args.out).exists():
        _, saved_config, ckpt = load_checkpoint(args.out)
        saved = vars(saved_config)
        differ = {n: (v, saved[n]) for n, v in recipe.items() if saved.get(n) != v}
        if differ:
            said = ", ".join(
                f"--{n.replace('_', '-')} {v} (checkpoint: {old})" for n, (v, old) in differ.items()
            )
            raise TorchFmapError(
                f"--resume continues the recipe of {args.out}, which differs from {said}. Fix: drop "
                "those flags to continue it, or train a new checkpoint (another --out)."
            )
        if budget:  # a budget given now replaces the saved one (it is the whole run's)
            saved.update(epochs=None, minutes=0.0, max_steps=0)
        config = TrainConfig(**{**saved, **budget})
        _check_budget_left(config, ckpt.get("train_state") or {}, args.out)
    # the budget: what was given (epochs unbounded then unless given), else the recipe's epochs
    epochs = config.epochs if (args.epochs or not (config.minutes or config.max_steps)) else None
    config.epochs = epochs  # recorded as it runs (None: bounded by time or steps only)
    cache = False if args.no_cache else args.cache
    shapes = ShapeDataset(args.folder, cache, **config.dataset_kwargs(), progress=not args.quiet)
    pairs = class_pairs(shapes.names, within=args.pairs == "classes")
    steps = total_steps(-(-len(pairs) // config.batch_size), epochs, config.max_steps) or 0
    limits = [f"{epochs} epochs" if epochs else "", f"{steps} steps" if steps else ""]
    limits.append(f"{config.minutes:g} minutes" if config.minutes else "")
    say = (lambda *_: None) if args.quiet else print
    say(
        f"training on {len(shapes)} meshes, {len(pairs)} ordered pairs ({config.basis} basis, K={config.k}); "
        f"budget: {', '.join(x for x in limits if x)} (whichever comes first; cosine learning rate over it)"
    )
    # validation: the unsupervised loss (full soft maps) on a fixed spread of training pairs
    picked = pairs[:: max(1, len(pairs) // args.validate_pairs)][: args.validate_pairs]
    solver, loss_fn = build_solver(config)
    stage = StageTwo(n_seeds=config.stage_seeds) if config.stages == 2 else None
    validate = (
        unsupervised_score(shapes, picked, solver, loss_fn, stage=stage) if args.validate_every else None
    )
    result, interrupted = _train_or_interrupted(
        train_recipe,
        args.out,
        config,
        shapes,
        pairs,
        out=args.out,
        resume=args.resume,
        init=init,
        validate=validate,
        validate_every=args.validate_every,
        progress=not args.quiet,
    )
    state = result[0] if result else None
    if interrupted:
        print(interrupted, file=sys.stderr)
        return 130
    last = state.losses[-1]["total"] if state.losses else float("nan")
    best = f"; best validation score {state.best_score:.4g}" if state.scores else ""
    summary = f"{state.step} steps, {state.epoch} full epochs, {state.seconds:.0f} s; last loss {last:.4g}"
    say(f"{summary}{best} -> {args.out}")
    return 0


def _check_budget_left(config, state: dict, out) -> None:
    """Refuse a ``--resume`` whose budget (the whole run's) the saved run has already spent:
    it would train nothing."""
    step, seconds, epoch = state.get("step", 0), state.get("seconds", 0.0), state.get("epoch", 0)
    spent = [
        f"--max-steps {config.max_steps} (done: {step} steps)"
        if config.max_steps and step >= config.max_steps
        else "",
        f"--minutes {config.minutes:g} (done: {seconds / 60:.1f} min)"
        if config.minutes and seconds >= 60 * config.minutes
        else "",
        f"--epochs {config.epochs} (done: {epoch})" if config.epochs and epoch >= config.epochs else "",
    ]
    spent = [x for x in spent if x]
    if spent:
        raise TorchFmapError(
            f"--resume: the run in {out} has already spent its budget {', '.join(spent)}; a budget "
            "covers the whole run, across resumes, so this would train nothing. Fix: give a larger "
            "budget (e.g. twice as many minutes or steps), or start a new --out."
        )


def _train_or_interrupted(train, checkpoint, *args, **kwargs):
    """``(train(*args, **kwargs), None)``, or on Ctrl-C ``(None, message)`` saying which step the
    checkpoint at ``checkpoint`` holds (it is written atomically, so it is always a whole one)."""
    out = checkpoint
    try:
        return train(*args, **kwargs), None
    except KeyboardInterrupt:
        from .nn.checkpoints import read_checkpoint

        try:
            step = read_checkpoint(out)["train_state"]["step"]
        except (TorchFmapError, OSError, KeyError, TypeError):
            return None, "torchfmap: training interrupted before its first checkpoint; nothing saved."
        return None, (
            f"torchfmap: training interrupted; the checkpoint {out} holds step {step} (intact). "
            "Fix: run the same command with --resume to continue from it."
        )
