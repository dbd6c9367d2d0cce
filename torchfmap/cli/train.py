"""``torchfmap models`` and ``torchfmap train``, which import torch and :mod:`torchfmap.nn` when run."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .._util.files import output_lock
from .._util.threads import thread_limit
from ..errors import TorchFmapError

#: ``TrainConfig`` fields that ``torchfmap train`` takes as flags (``--k``, ``--n-wks``, ...).
RECIPE_FLAGS = (
    "k", "basis", "inputs", "augment", "parts", "n_wks", "k_net", "width", "c_out", "lr", "clip_grad", "seed",
)  # fmt: skip


def cmd_models(args: argparse.Namespace) -> int:
    from ..nn.checkpoints import read_checkpoint, read_recipe
    from ..nn.shipped import shipped_models

    if args.recipe:
        print(read_recipe(args.recipe).to_json(), end="")
        return 0
    models = shipped_models()
    if not models:
        print("no models shipped in this installation")
    for name, path in models.items():
        ckpt = read_checkpoint(path)
        cfg = ckpt.get("config", {})
        print(f"{name}  ({path.stat().st_size / 1e6:.1f} MB, {cfg.get('basis')} basis K={cfg.get('k')})")
        for key, value in ckpt.get("provenance", {}).items():
            print(f"  {key}: {value}")
        print(f"  recipe: torchfmap models --recipe {name} > r.json; torchfmap train FOLDER --config r.json")
    return 0


def _recipe(args: argparse.Namespace):
    """The run's :class:`~torchfmap.nn.TrainConfig`: the defaults (or ``--init``'s recipe), then
    ``--config``, then the flags; with ``--resume``, the checkpoint's recipe, which they must not
    contradict. A budget given replaces the whole budget."""
    from ..nn.checkpoints import read_checkpoint, read_recipe
    from ..nn.config import BUDGET_FIELDS, TrainConfig

    given = {n: getattr(args, n) for n in RECIPE_FLAGS if getattr(args, n, None) is not None}
    bounds = {"epochs": args.epochs, "minutes": args.minutes, "max_steps": args.max_steps}
    if any(bounds.values()):
        unbounded = {"epochs": None, "minutes": 0.0, "max_steps": 0}
        given.update(unbounded | {k: v for k, v in bounds.items() if v})
    asked = {**(TrainConfig.read_json(args.config) if args.config else {}), **given}
    if args.init:
        if args.resume:
            raise TorchFmapError("--init starts a new run and --resume continues one. Fix: drop one.")
        base = read_recipe(args.init).with_budget(TrainConfig().budget)
        return base.updated(asked, "the recipe")
    if not (args.resume and Path(args.out).exists()):
        return TrainConfig().updated(asked, "the recipe")
    saved = read_recipe(args.out)
    recipe = {n: v for n, v in asked.items() if n not in BUDGET_FIELDS}
    differ = {n: (v, getattr(saved, n)) for n, v in recipe.items() if getattr(saved, n) != v}
    if differ:
        said = ", ".join(f"--{n.replace('_', '-')} {v} (checkpoint: {old})" for n, (v, old) in differ.items())
        raise TorchFmapError(
            f"--resume continues the recipe of {args.out}, which differs from {said}. Fix: drop "
            "those settings to continue it, or train a new checkpoint (another --out)."
        )
    config = saved.updated({n: v for n, v in asked.items() if n in BUDGET_FIELDS}, "the recipe")
    state = read_checkpoint(args.out).get("train_state") or {}
    spent = config.budget.spent(state.get("step", 0), state.get("seconds", 0.0), state.get("epoch", 0))
    if spent:
        raise TorchFmapError(
            f"--resume: the run in {args.out} has already spent its budget {', '.join(spent)}; a budget "
            "covers the whole run, across resumes, so this would train nothing. Fix: give a larger "
            "budget (e.g. twice as many minutes or steps), or start a new --out."
        )
    return config


def cmd_train(args: argparse.Namespace) -> int:
    """``torchfmap train``, under :func:`~torchfmap._util.files.output_lock`."""
    with output_lock(args.out, "--out"), thread_limit(args.threads):
        return _train(args)


def _train(args: argparse.Namespace) -> int:
    from ..nn.checkpoints import load_checkpoint
    from ..nn.config import build_solver
    from ..nn.data import ShapeDataset, class_pairs
    from ..nn.devices import resolve_device
    from ..nn.train import unsupervised_score
    from ..nn.trainer import Trainer

    device = resolve_device(args.device)
    config = _recipe(args)
    init = load_checkpoint(args.init)[0].state_dict() if args.init else None
    cache = False if args.no_cache else args.cache
    shapes = ShapeDataset(args.folder, cache, **config.dataset_kwargs(), progress=not args.quiet)
    if config.parts:  # supervised on cuts of the shapes, matched to every shape
        from ..nn.parts import PartLoss, PartPairs, part_score

        corres = Path(args.folder) / "corres"
        pairs = PartPairs(shapes, corres, config.parts, seed=config.seed, progress=not args.quiet)
    else:
        pairs = class_pairs(shapes.names, within=args.pairs == "classes")
    validate, picked = None, []
    if args.validate_every:  # the training loss on a fixed spread of training pairs
        picked = list(range(len(pairs)))[:: max(1, len(pairs) // args.validate_pairs)][: args.validate_pairs]
        solver, loss_fn = build_solver(config)
        if config.parts:
            tau = config.loss_weights.get("tau", 0.07)
            validate = part_score(pairs, picked, PartLoss(tau), solver, device=device)
        else:
            chosen = [pairs[i] for i in picked]
            validate = unsupervised_score(
                shapes, chosen, solver, loss_fn, device=device, augment=config.augment
            )
    trainer = Trainer.from_config(
        config, shapes, pairs, init=init, device=device, validate=validate,
        validate_every=args.validate_every, checkpoint=args.out,
    )  # fmt: skip
    if args.resume:
        trainer.resume()
    say = (lambda *_: None) if args.quiet else print
    kind = "(part, whole)" if config.parts else "ordered"
    say(
        f"training on {len(shapes)} meshes, {len(pairs)} {kind} pairs "
        f"({config.basis} basis, K={config.k}) "
        f"on {device}; budget: {config.budget.describe(trainer.batches_per_epoch)} (whichever comes first; "
        "cosine learning rate over it)"
    )
    state, interrupted = _fit_or_interrupted(trainer, progress=not args.quiet)
    if interrupted:
        print(interrupted, file=sys.stderr)
        return 130
    last = state.losses[-1]["total"] if state.losses else float("nan")
    summary = f"{state.step} steps, {state.epoch} full epochs, {state.seconds:.0f} s; last loss {last:.4g}"
    scored = "the part error" if config.parts else "the unsupervised loss"
    say(f"{summary}{_validation_summary(state, len(picked), bool(args.init), scored)} -> {args.out}")
    return 0


#: ``train`` warns when the best validation loss is above this fraction of the untrained one.
UNMOVED = 0.9


def _validation_summary(
    state, n_pairs: int, fine_tune: bool = False, scored: str = "the unsupervised loss"
) -> str:
    """The validation score (``scored``: what it is) against the step-0 one, in words; warns on stderr
    when training from scratch barely moved it."""
    if not state.scores:
        return ""
    text = (
        f"; best validation loss {state.best_score:.4g} ({scored} on {n_pairs} fixed training pairs, "
        "lower is better"
    )
    first = state.scores[0][1] if state.scores[0][0] == 0 else None
    if first is None or not first > 0:
        return text + ")"
    started = "the --init weights" if fine_tune else "untrained"
    if not fine_tune and state.best_score > UNMOVED * first:
        print(
            f"torchfmap: warning: training lowered the validation loss only from {first:.4g} "
            f"(untrained) to {state.best_score:.4g}: the network is close to untrained and its maps "
            "will be too. Fix: train longer (--minutes / --epochs), or check the meshes and --pairs.",
            file=sys.stderr,
        )
    return text + f"; {started} {first:.4g}, {100 * (1 - state.best_score / first):.0f} % lower)"


def _fit_or_interrupted(trainer, progress: bool):
    """``(trainer.fit(progress), None)``, or on Ctrl-C ``(None, message)`` naming the checkpoint's step."""
    from ..nn.checkpoints import read_checkpoint

    out = trainer.checkpoint
    try:
        return trainer.fit(progress=progress), None
    except KeyboardInterrupt:
        try:
            step = read_checkpoint(out)["train_state"]["step"]
        except (TorchFmapError, OSError, KeyError, TypeError):
            return None, "torchfmap: training interrupted before its first checkpoint; nothing saved."
        return None, (
            f"torchfmap: training interrupted; the checkpoint {out} holds step {step} (intact). "
            "Fix: run the same command with --resume to continue from it."
        )
