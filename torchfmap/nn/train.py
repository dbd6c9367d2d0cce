"""The training loop: unsupervised training of any feature network with resumable checkpoints
and the best validation score, validation by the unsupervised loss, and DistributedDataParallel
training (gloo on CPU, NCCL on GPU; each rank on its own device).

:func:`train` takes the user's network (any :class:`~torchfmap.nn.networks.FeatureNetwork`),
loss, optimiser, scheduler and device; :mod:`torchfmap.nn.config` holds the reference recipe
used by ``torchfmap train``, :mod:`torchfmap.nn.checkpoints` the checkpoint files and
:mod:`torchfmap.nn.inference` prediction, adaptation and evaluation.
"""

from __future__ import annotations

import copy
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NamedTuple

import torch
from tqdm import tqdm

from ..errors import ParameterError
from .augment import augmentation, random_rigid, recipe_augmentation
from .checkpoints import read_checkpoint, save_checkpoint
from .config import CosineBudget, TrainConfig, build_model, build_solver
from .data import PairDataset, ShapeDataset, class_pairs, collate_pairs
from .modules import UnsupervisedFMLoss
from .networks import check_network, features
from .stages import StageTwo, stage_two_loss

#: Progress bar of a time budget: seconds of the budget, no rate (steps and epochs in the postfix).
TIME_BAR = "{l_bar}{bar}| {n_fmt}/{total_fmt} s [{elapsed}<{remaining}{postfix}]"

#: The recipe whose settings are the defaults of :func:`train` (one set of defaults).
_RECIPE = TrainConfig()


class PairForward(NamedTuple):
    """Result of :func:`forward_pair`: features ``(B, V_x, D)``, ``(B, V_y, D)`` and both maps."""

    feat_x: torch.Tensor
    feat_y: torch.Tensor
    C_xy: torch.Tensor
    C_yx: torch.Tensor | None


def forward_pair(net, solver, batch: dict) -> PairForward:
    """Features and both maps of a collated batch (:func:`~torchfmap.nn.data.collate_pairs`)."""
    x, y = batch["x"], batch["y"]
    feat_x, feat_y = features(net, x), features(net, y)
    C_xy, C_yx = solver(feat_x, feat_y, x.basis, y.basis)
    return PairForward(feat_x, feat_y, C_xy, C_yx)


def pair_loss(
    net, solver, loss_fn, batch: dict, generator: torch.Generator | None = None, *, stage=None, mesh_of=None
) -> dict[str, torch.Tensor]:
    """The loss terms of a collated batch:
    ``loss_fn(C_xy, C_yx, feat_x, feat_y, basis_x, basis_y, generator=generator)``. With a
    second stage (``stage``, :class:`~torchfmap.nn.stages.StageTwo`; ``mesh_of(index) -> Mesh``
    of the dataset's shapes) its terms are added as ``stage2_<term>`` and its total to
    ``total`` (:func:`~torchfmap.nn.stages.stage_two_loss`)."""
    out = forward_pair(net, solver, batch)
    terms = loss_fn(
        out.C_xy, out.C_yx, out.feat_x, out.feat_y, batch["x"].basis, batch["y"].basis, generator=generator
    )
    if stage is None:
        return terms
    second = stage_two_loss(stage, solver, loss_fn, out, batch, mesh_of, generator)
    if second is None:  # too few consistent seeds: this step trains stage 1 only
        second = {name: torch.zeros_like(value) for name, value in terms.items()}
    both = {**terms, **{f"stage2_{n}": v for n, v in second.items()}}
    return {**both, "total": terms["total"] + second["total"]}


def unsupervised_score(
    shapes: ShapeDataset, pairs, solver, loss_fn: UnsupervisedFMLoss, device="cpu", stage=None
):
    """``score(net) -> float``: the mean unsupervised loss on ``pairs`` with full (not sampled)
    soft maps, in eval mode, for :func:`train`'s ``validate`` (no ground truth)."""
    full = copy.deepcopy(loss_fn)
    full.n_samples = 0
    batches = [collate_pairs([(shapes[a], shapes[b])]) for a, b in pairs]

    @torch.no_grad()
    def score(net) -> float:
        net.eval()
        total = 0.0
        for batch in batches:
            batch = {**batch, "x": batch["x"].to(device), "y": batch["y"].to(device)}
            total += float(pair_loss(net, solver, full, batch, stage=stage, mesh_of=shapes.mesh)["total"])
        return total / max(len(batches), 1)

    return score


@dataclass
class TrainState:
    """What :func:`train` returns and checkpoints: per-step losses, epochs, times, best score."""

    step: int = 0
    epoch: int = 0
    seconds: float = 0.0
    losses: list = field(default_factory=list)
    epoch_seconds: list = field(default_factory=list)
    scores: list = field(default_factory=list)  # (step, validation score)
    best_score: float = math.inf


def _set_schedule_clock(scheduler, seconds: float) -> None:
    """The time-based schedules of ``scheduler`` (:class:`~torchfmap.nn.config.CosineBudget`
    factors of a ``LambdaLR``) set to ``seconds`` of training."""
    for factor in getattr(scheduler, "lr_lambdas", []):
        if isinstance(factor, CosineBudget):
            factor.set_clock(seconds)


def train(
    net: torch.nn.Module,
    data: PairDataset,
    loss_fn: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    *,
    solver: torch.nn.Module | None = None,
    scheduler=None,
    device: str | torch.device = "cpu",
    epochs: int | None = _RECIPE.epochs,
    minutes: float = _RECIPE.minutes,
    max_steps: int = _RECIPE.max_steps,
    batch_size: int = _RECIPE.batch_size,
    clip_grad: float = _RECIPE.clip_grad,
    augment: bool | str | None = None,
    validate=None,
    validate_every: int = 0,
    checkpoint: str | os.PathLike | None = None,
    config: TrainConfig | dict | None = None,
    resume: bool = False,
    seed: int = _RECIPE.seed,
    progress: bool = True,
    rank: int = 0,
    world_size: int = 1,
    stage: StageTwo | None = None,
) -> TrainState:
    """Unsupervised training of ``net`` on the pairs of ``data``; returns the :class:`TrainState`.

    ``net`` follows the :class:`~torchfmap.nn.networks.FeatureNetwork` protocol (checked by
    :func:`~torchfmap.nn.networks.check_network`); ``loss_fn`` is called as
    ``loss_fn(C_xy, C_yx, feat_x, feat_y, basis_x, basis_y, generator=...)`` and returns a
    dict of terms with ``'total'`` (as :class:`~torchfmap.nn.UnsupervisedFMLoss`). The
    defaults are the recipe's (:class:`~torchfmap.nn.TrainConfig`: budget, batch size, clipping,
    augmentation, seed; ``solver=None``: the recipe's solver, :func:`~torchfmap.nn.build_solver`).

    Stops after ``epochs`` epochs (None: not bounded by epochs), ``minutes`` of training (0: no
    limit) or ``max_steps`` steps (0: no limit), whichever comes first; the budget is the whole
    run's, so a resumed run counts the steps and time of the earlier ones. The progress bar
    counts steps up to the step bound (``min(max_steps, epochs x batches)``), or, with a time
    budget and no step bound, seconds up to ``60 minutes``. :func:`total_steps` gives the step
    bound for a schedule (:class:`~torchfmap.nn.config.CosineBudget`).
    ``net`` is moved to ``device`` and every batch with it.
    ``clip_grad > 0``: the gradient norm is clipped to it before each step (0: no clipping).
    With ``world_size > 1`` the ranks agree on the time budget (one all-reduce a step), so all
    stop at the same step. ``stage``: a self-seeded second stage
    (:class:`~torchfmap.nn.stages.StageTwo`) whose loss is added to stage 1's (:func:`pair_loss`;
    batches of one pair).
    ``augment``: XYZ inputs moved at random each step (:func:`random_rigid`): ``"rigid"`` (or
    True) a rotation and a scaling, ``"scale"`` a scaling only (shapes aligned alike, e.g.
    SMAL_r), ``"none"`` (or False) nothing; None: the recipe's for XYZ inputs, nothing for
    others (a rigid motion of WKS inputs is meaningless and refused). ``validate(net) -> score``
    (lower is better) runs every ``validate_every`` steps and at the end; the best weights are
    kept in the checkpoint as ``best_state_dict``. ``checkpoint`` is written atomically at each
    epoch end, each validation and the end (by rank 0), with the network's record
    (:func:`~torchfmap.nn.checkpoints.save_checkpoint`; ``config`` is recorded there as it is,
    it does not set this loop's arguments: :func:`train_recipe` trains by a config);
    ``resume=True`` continues from it
    (weights, optimiser, scheduler, step and the time already spent). With ``world_size > 1``
    (inside an initialised process group) the network is wrapped in DistributedDataParallel
    and each rank trains on its share of the same pairs.

    Randomness comes from generators the loop owns, seeded ``seed + epoch`` at the start (so a
    resumed run re-seeds from its epoch; the generators are not checkpointed): a CPU one
    shuffles the pairs, one on ``device`` draws the loss's vertex samples and the augmentation.
    Nothing is drawn from the global RNG by torchfmap (torch's own ``nn.Dropout`` and weight
    initialisation still use it).
    """
    check_network(net)
    augment = augmentation(augment, getattr(getattr(data, "shapes", None), "inputs", None))
    if epochs is None and not minutes and not max_steps:
        raise ParameterError("training needs a budget. Fix: epochs, minutes and/or max_steps.")
    if not (math.isfinite(minutes) and minutes >= 0):
        raise ParameterError(f"minutes must be finite and >= 0, got {minutes}.")
    device = torch.device(device)
    solver = solver if solver is not None else build_solver(_RECIPE)[0]
    net.to(device)
    state = TrainState()
    best_state = None
    if resume and checkpoint is not None and Path(checkpoint).exists():
        ckpt = read_checkpoint(checkpoint, map_location=device)
        net.load_state_dict(ckpt["state_dict"])
        optimizer.load_state_dict(ckpt["optimizer"])
        if scheduler is not None and ckpt.get("scheduler") is not None:
            # the clock and step continue; the budget is this run's (LambdaLR restores both)
            budgets = [
                (f, f.budget) for f in getattr(scheduler, "lr_lambdas", []) if isinstance(f, CosineBudget)
            ]
            scheduler.load_state_dict(ckpt["scheduler"])
            for f, budget in budgets:
                f.budget = budget
        state = TrainState(**ckpt["train_state"])
        best_state = ckpt.get("best_state_dict")
    model = net
    sampler = None
    if world_size > 1:
        model = torch.nn.parallel.DistributedDataParallel(
            net, device_ids=[device] if device.type == "cuda" else None
        )
        sampler = torch.utils.data.distributed.DistributedSampler(
            data, num_replicas=world_size, rank=rank, shuffle=True, seed=seed
        )
    generator = torch.Generator().manual_seed(seed + state.epoch)
    draws = torch.Generator(device=device).manual_seed(seed + state.epoch)
    loader = torch.utils.data.DataLoader(
        data,
        batch_size=batch_size,
        shuffle=sampler is None,
        sampler=sampler,
        collate_fn=collate_pairs,
        generator=generator,
    )
    t_start = time.perf_counter() - state.seconds
    main = rank == 0

    # each rank has its own clock: the ranks of a time-budgeted DDP run follow one, the slowest
    # rank's, so all stop at the same step and their schedules (hence weights) agree
    shared_clock = world_size > 1 and minutes > 0

    def seconds_spent() -> float:
        elapsed = time.perf_counter() - t_start
        if not shared_clock:
            return elapsed
        agreed = torch.tensor([elapsed], dtype=torch.float64, device=device)
        torch.distributed.all_reduce(agreed, op=torch.distributed.ReduceOp.MAX)
        return float(agreed.item())

    def out_of_budget() -> bool:
        over_time = minutes > 0 and seconds_spent() >= 60 * minutes
        return over_time or (max_steps > 0 and state.step >= max_steps)

    def save() -> None:
        if checkpoint is None or not main:
            return
        extra = {
            "optimizer": optimizer.state_dict(),
            "scheduler": None if scheduler is None else scheduler.state_dict(),
            "train_state": asdict(state),
            "best_state_dict": best_state,
        }
        save_checkpoint(checkpoint, net, config if config is not None else {}, **extra)

    def run_validation() -> None:
        nonlocal best_state
        if validate is None:
            return
        score = float(validate(net))
        net.train()
        state.scores.append((state.step, score))
        if score < state.best_score:
            state.best_score = score
            best_state = {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}

    net.train()
    stop = out_of_budget()
    step_bound = total_steps(len(loader), epochs, max_steps)
    by_time = minutes > 0 and step_bound is None
    bar = tqdm(
        total=round(60 * minutes) if by_time else step_bound,
        initial=min(round(state.seconds), round(60 * minutes)) if by_time else state.step,
        disable=not progress or not main,
        unit="s" if by_time else "step",
        # a time budget counts seconds: no "s/s" rate, the steps and epochs are in the postfix
        bar_format=TIME_BAR if by_time else None,
    )
    last_tick = state.seconds
    while (epochs is None or state.epoch < epochs) and not stop:
        if sampler is not None:
            sampler.set_epoch(state.epoch)
        t_epoch = time.perf_counter()
        for batch in loader:
            batch = {**batch, "x": batch["x"].to(device), "y": batch["y"].to(device)}
            if augment != "none":
                for side in ("x", "y"):
                    s = batch[side]
                    moved = random_rigid(s.inputs, draws, rotate=augment == "rigid")
                    batch[side] = s._replace(inputs=moved)
            terms = pair_loss(model, solver, loss_fn, batch, draws, stage=stage, mesh_of=data.shapes.mesh)
            optimizer.zero_grad(set_to_none=True)
            terms["total"].backward()
            if clip_grad > 0:
                torch.nn.utils.clip_grad_norm_(net.parameters(), clip_grad)
            optimizer.step()
            if scheduler is not None:
                if shared_clock:
                    _set_schedule_clock(scheduler, seconds_spent())
                scheduler.step()
            state.step += 1
            values = torch.stack([v.detach() for v in terms.values()]).tolist()  # one host sync a step
            state.losses.append(dict(zip(terms, values, strict=True)))
            if by_time:
                now = time.perf_counter() - t_start
                bar.update(min(round(now), bar.total) - min(round(last_tick), bar.total))
                last_tick = now
            else:
                bar.update()
            # full epochs, as the end-of-run summary counts them
            bar.set_postfix(step=state.step, full_epochs=state.epoch, loss=f"{state.losses[-1]['total']:.3f}")
            if validate_every and state.step % validate_every == 0:
                run_validation()
                save()
            if out_of_budget():
                stop = True
                break
        else:
            state.epoch += 1
            state.epoch_seconds.append(time.perf_counter() - t_epoch)
        state.seconds = time.perf_counter() - t_start
        save()
    bar.close()
    if validate is not None and (not state.scores or state.scores[-1][0] != state.step):
        run_validation()
    state.seconds = time.perf_counter() - t_start
    save()
    return state


def total_steps(batches_per_epoch: int, epochs: int | None, max_steps: int = 0) -> int | None:
    """The step bound of a budget: ``min(max_steps, epochs x batches_per_epoch)`` over the bounds
    that are set (``max_steps=0`` and ``epochs=None`` are unset); None when neither is."""
    bounds = [b for b in (max_steps or None, None if epochs is None else epochs * batches_per_epoch) if b]
    return min(bounds) if bounds else None


def train_recipe(
    config: TrainConfig,
    shapes: ShapeDataset,
    pairs=None,
    *,
    out=None,
    resume: bool = False,
    validate=None,
    validate_every: int = 0,
    device: str | torch.device = "cpu",
    progress: bool = True,
    rank: int = 0,
    world_size: int = 1,
    init: dict | None = None,
) -> tuple[TrainState, torch.nn.Module]:
    """The reference recipe, all of it read from ``config``: the network, solver and loss of
    :func:`~torchfmap.nn.config.build_model`, Adam at ``config.lr``, the cosine schedule over
    the budget (``config.epochs`` / ``minutes`` / ``max_steps``, whichever ends first:
    :class:`~torchfmap.nn.config.CosineBudget`), ``config.clip_grad``, and the augmentation
    ``config.augment`` of XYZ inputs; trained by :func:`train` on ``pairs`` of ``shapes`` (default
    :func:`~torchfmap.nn.data.class_pairs`). ``torchfmap train``, DDP ranks
    (:func:`ddp_worker`) and ``examples/train.py`` all call it, so one process and a DDP run
    follow the same schedule. ``init``: a state dict the network starts from (fine-tuning).
    Returns ``(state, net)``.

    Raises:
        ParameterError: a config without a budget, or as :func:`train`.
    """
    pairs = class_pairs(shapes.names) if pairs is None else list(pairs)
    net, solver, loss_fn = build_model(config)
    if init is not None:  # fine-tuning: the recipe's network, started from these weights
        try:
            net.load_state_dict(init)
        except RuntimeError as err:
            raise ParameterError(
                f"the initial weights do not fit the recipe's network ({str(err).splitlines()[0]}). Fix: "
                "keep the network settings of the checkpoint (--width, --c-out, --inputs, --n-wks)."
            ) from None
    opt = torch.optim.Adam(net.parameters(), lr=config.lr)
    per_rank = -(-len(pairs) // (config.batch_size * world_size))  # batches of one rank per epoch
    steps = total_steps(per_rank, config.epochs, config.max_steps) or 0
    scheduler = torch.optim.lr_scheduler.LambdaLR(opt, CosineBudget(minutes=config.minutes, steps=steps))
    state = train(
        net,
        PairDataset(shapes, pairs),
        loss_fn,
        opt,
        solver=solver,
        scheduler=scheduler,
        device=device,
        epochs=config.epochs,
        minutes=config.minutes,
        max_steps=config.max_steps,
        batch_size=config.batch_size,
        clip_grad=config.clip_grad,
        augment=recipe_augmentation(config),
        validate=validate,
        validate_every=validate_every,
        checkpoint=out,
        config=config,
        resume=resume,
        seed=config.seed,
        progress=progress,
        rank=rank,
        world_size=world_size,
        stage=StageTwo(n_seeds=config.stage_seeds) if config.stages == 2 else None,
    )
    return state, net


def ddp_worker(rank: int, world_size: int, port: int, files, cache_dir, config_dict: dict, out_path) -> None:
    """One rank of a DDP run of the reference recipe (gloo on CPU, NCCL with one GPU per rank):
    :func:`train_recipe` with the whole budget, schedule, clipping and augmentation of
    ``config_dict``.

    The same pairs as one process (:func:`~torchfmap.nn.data.class_pairs`); rank 0 shows
    progress and writes the checkpoint ``out_path``; every rank writes its final weights to
    ``<out_path folder>/rank{r}.pt`` so they can be compared.
    """
    cuda = torch.cuda.is_available() and torch.cuda.device_count() >= world_size
    backend = "nccl" if cuda else "gloo"
    device = torch.device(f"cuda:{rank}") if cuda else torch.device("cpu")
    os.environ.setdefault("MASTER_ADDR", "127.0.0.1")
    os.environ["MASTER_PORT"] = str(port)
    torch.distributed.init_process_group(backend, rank=rank, world_size=world_size)
    try:
        config = TrainConfig(**config_dict)
        shapes = ShapeDataset(
            files, cache_dir, **config.dataset_kwargs(), rank=rank, world_size=world_size, progress=False
        )
        _, net = train_recipe(
            config, shapes, out=out_path, device=device, progress=rank == 0, rank=rank, world_size=world_size
        )
        torch.save(net.state_dict(), Path(out_path).parent / f"rank{rank}.pt")
    finally:
        torch.distributed.destroy_process_group()
