"""The training loop (:class:`Trainer`) and DDP runs of the reference recipe (:func:`spawn_ddp`)."""

from __future__ import annotations

import os
import socket
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path

import torch
from tqdm import tqdm

from ..errors import ParameterError
from .augment import augment_batch, augmentation
from .checkpoints import check_config_fits, read_checkpoint, save_checkpoint
from .config import CosineBudget, TrainConfig, build_model, build_solver
from .data import PairDataset, ShapeDataset, class_pairs, collate_pairs
from .devices import resolve_device
from .networks import check_network
from .parts import PartLoss, PartPairs
from .train import ExtraLoss, TrainState, pair_loss

#: Progress bar of a time budget: seconds of the budget, no rate (steps and epochs in the postfix).
TIME_BAR = "{l_bar}{bar}| {n_fmt}/{total_fmt} s [{elapsed}<{remaining}{postfix}]"


def _cosine_factors(scheduler) -> list[CosineBudget]:
    return [f for f in getattr(scheduler, "lr_lambdas", []) if isinstance(f, CosineBudget)]


def _check_solver_fits(solver, config: TrainConfig) -> None:
    """Refuse a solver whose ``w_lap`` is not the recipe's (recorded in the checkpoint, used by inference)."""
    w_lap = getattr(solver, "w_lap", None)
    if w_lap is not None and float(w_lap) != float(config.w_lap):
        raise ParameterError(
            f"the solver's w_lap={w_lap:g} is not config.w_lap={config.w_lap:g}, which the checkpoint "
            "records and inference solves with. Fix: RegularizedFMSolver(w_lap=config.w_lap), "
            f"or TrainConfig(w_lap={w_lap:g}), or solver=None (the config's)."
        )


class Trainer:
    """Unsupervised training of ``net`` (a :class:`~torchfmap.nn.networks.FeatureNetwork`) on the pairs of
    ``data`` (a :class:`~torchfmap.nn.data.PairDataset`).

    ``loss_fn(C_xy, C_yx, feat_x, feat_y, basis_x, basis_y, generator=...)`` returns terms with ``'total'``;
    ``extra_losses``: plug-ins (:class:`~torchfmap.nn.train.ExtraLoss`). ``config``
    (:class:`~torchfmap.nn.TrainConfig`, recorded in the checkpoint) sets budget, batch size, clipping,
    augmentation and seed; ``solver=None``: the config's. ``scheduler`` steps after each step. ``device``:
    where the network, solver and loss run. ``validate(net) -> score`` (lower is better) runs every
    ``validate_every`` steps and at the end, keeping the best weights. ``checkpoint``: the file :meth:`save`
    writes and :meth:`resume` reads. In a process group of several ranks the network is wrapped in
    DistributedDataParallel and only rank 0 writes. Generators seeded ``seed + epoch`` shuffle and draw, so a
    resumed run draws as the uninterrupted one would.

    Raises:
        ParameterError: a network that does not follow the protocol, a config without a budget, an unknown
            augmentation or device, or (with a checkpoint) a config that does not describe the recipe
            network or a solver whose ``w_lap`` is not the config's."""

    def __init__(
        self,
        net: torch.nn.Module,
        data: PairDataset,
        loss_fn,
        optimizer: torch.optim.Optimizer,
        *,
        config: TrainConfig | None = None,
        solver=None,
        scheduler=None,
        device: str | torch.device = "auto",
        extra_losses: Sequence[ExtraLoss] = (),
        validate: Callable[[torch.nn.Module], float] | None = None,
        validate_every: int = 0,
        checkpoint: str | os.PathLike | None = None,
    ) -> None:
        check_network(net)
        if loss_fn is None and not extra_losses:
            raise ParameterError(
                "nothing to train: no loss_fn and no extra_losses. Fix: UnsupervisedFMLoss() for whole "
                "shapes, or extra_losses=[PartLoss()] on PartPairs."
            )
        self.config = config if config is not None else TrainConfig()
        self.budget = self.config.budget
        self.shapes = getattr(data, "shapes", None)
        self.augment = augmentation(self.config.augment, getattr(self.shapes, "inputs", None))
        self.device = resolve_device(device)
        self.net = net.to(self.device)
        self.solver = solver if solver is not None else build_solver(self.config)[0]
        self.loss_fn, self.optimizer, self.scheduler = loss_fn, optimizer, scheduler
        self.extra_losses = list(extra_losses)
        self.validate_fn, self.validate_every = validate, validate_every
        self.checkpoint = None if checkpoint is None else Path(checkpoint)
        if self.checkpoint is not None:
            check_config_fits(net, self.config)  # now, not at the first save
            _check_solver_fits(self.solver, self.config)
        self.state, self.best_state = TrainState(), None
        ddp = torch.distributed.is_available() and torch.distributed.is_initialized()
        self.world_size = torch.distributed.get_world_size() if ddp else 1
        self.rank = torch.distributed.get_rank() if ddp else 0
        self.model, sampler = net, None
        if self.world_size > 1:
            ids = [self.device] if self.device.type == "cuda" else None
            self.model = torch.nn.parallel.DistributedDataParallel(net, device_ids=ids)
            sampler = torch.utils.data.distributed.DistributedSampler(
                data, num_replicas=self.world_size, rank=self.rank, shuffle=True, seed=self.config.seed
            )
        self.sampler, self.shuffle, self.draws = (
            sampler,
            torch.Generator(),
            torch.Generator(device=self.device),
        )
        self.loader = torch.utils.data.DataLoader(
            data, batch_size=self.config.batch_size, shuffle=sampler is None, sampler=sampler,
            collate_fn=getattr(data, "collate", collate_pairs), generator=self.shuffle,
        )  # fmt: skip
        self._t_start = time.perf_counter()

    @classmethod
    def from_config(
        cls, config: TrainConfig, shapes: ShapeDataset, pairs=None, *, init: dict | None = None, **kwargs
    ) -> Trainer:
        """The reference recipe of ``config`` (:func:`~torchfmap.nn.build_model`, Adam,
        :class:`~torchfmap.nn.config.CosineBudget`) on ``pairs`` of ``shapes`` (default
        :func:`~torchfmap.nn.data.class_pairs`), the network starting from ``init`` if given. ``pairs`` a
        :class:`~torchfmap.nn.parts.PartPairs`: supervised on its parts, :class:`~torchfmap.nn.parts.PartLoss`
        (at the recipe's ``tau``) in place of the unsupervised loss.

        Raises:
            ParameterError: weights ``init`` that do not fit the recipe's network, or as the constructor."""
        net, solver, loss_fn = build_model(config)
        if isinstance(pairs, PartPairs):
            data, loss_fn = pairs, None
            tau = config.loss_weights.get("tau", 0.07)
            kwargs["extra_losses"] = [PartLoss(tau=tau), *kwargs.get("extra_losses", ())]
        else:
            data = PairDataset(shapes, class_pairs(shapes.names) if pairs is None else list(pairs))
        if init is not None:
            try:
                net.load_state_dict(init)
            except RuntimeError as err:
                raise ParameterError(
                    f"the initial weights do not fit the recipe's network ({str(err).splitlines()[0]}). Fix: "
                    "keep the network settings of the checkpoint (--width, --c-out, --inputs, --n-wks)."
                ) from None
        opt = torch.optim.Adam(net.parameters(), lr=config.lr)
        trainer = cls(net, data, loss_fn, opt, config=config, solver=solver, **kwargs)
        factor = CosineBudget(config.budget, trainer.batches_per_epoch)
        trainer.scheduler = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return trainer

    @property
    def batches_per_epoch(self) -> int:
        """Batches of one epoch (of this rank's share under DDP)."""
        return len(self.loader)

    @property
    def main(self) -> bool:
        """Whether this process writes (rank 0)."""
        return self.rank == 0

    def seconds_spent(self) -> float:
        """Seconds of training of the whole run (under DDP with a time budget, the slowest rank's)."""
        elapsed = time.perf_counter() - self._t_start
        if self.world_size == 1 or not self.budget.minutes:
            return elapsed
        agreed = torch.tensor([elapsed], dtype=torch.float64, device=self.device)
        torch.distributed.all_reduce(agreed, op=torch.distributed.ReduceOp.MAX)
        return float(agreed.item())

    def out_of_budget(self) -> bool:
        """Whether the budget's time or step bound is reached."""
        over_time = self.budget.minutes > 0 and self.seconds_spent() >= 60 * self.budget.minutes
        return over_time or (self.budget.steps > 0 and self.state.step >= self.budget.steps)

    def resume(self) -> bool:
        """Continue the run saved in :attr:`checkpoint` if it exists; returns whether it did."""
        if self.checkpoint is None or not self.checkpoint.exists():
            return False
        ckpt = read_checkpoint(self.checkpoint, map_location=self.device)
        self.net.load_state_dict(ckpt["state_dict"])
        self.optimizer.load_state_dict(ckpt["optimizer"])
        if self.scheduler is not None and ckpt.get("scheduler") is not None:
            bounds = [(f, f.bounds) for f in _cosine_factors(self.scheduler)]
            self.scheduler.load_state_dict(ckpt["scheduler"])
            for f, b in bounds:
                f.bounds = b
        self.state, self.best_state = TrainState(**ckpt["train_state"]), ckpt.get("best_state_dict")
        return True

    def save(self, path: str | os.PathLike | None = None, **extra) -> Path | None:
        """Write the checkpoint (rank 0 only; ``path`` default :attr:`checkpoint`) with ``extra``; its path
        or None."""
        path = self.checkpoint if path is None else Path(path)
        if path is None or not self.main:
            return None
        self.state.draws = self.draws.get_state().cpu().tolist()
        return save_checkpoint(
            path, self.net, self.config,
            optimizer=self.optimizer.state_dict(),
            scheduler=None if self.scheduler is None else self.scheduler.state_dict(),
            train_state=asdict(self.state), best_state_dict=self.best_state, **extra,
        )  # fmt: skip

    def validate(self) -> float | None:
        """Run ``validate`` once (None without one), recording the score and keeping the best weights."""
        if self.validate_fn is None:
            return None
        score = float(self.validate_fn(self.net))
        self.net.train()
        self.state.scores.append((self.state.step, score))
        if score < self.state.best_score:
            self.state.best_score = score
            self.best_state = {k: v.detach().cpu().clone() for k, v in self.net.state_dict().items()}
        return score

    def step(self, batch: dict) -> dict[str, float]:
        """One optimiser step on a collated batch; returns the loss terms (floats), also recorded."""
        batch = {**batch, "x": batch["x"].to(self.device), "y": batch["y"].to(self.device)}
        batch = augment_batch(batch, self.augment, self.draws)
        terms = pair_loss(self.model, self.solver, self.loss_fn, batch, self.draws, self.extra_losses)
        self.optimizer.zero_grad(set_to_none=True)
        terms["total"].backward()
        if self.config.clip_grad > 0:
            torch.nn.utils.clip_grad_norm_(self.net.parameters(), self.config.clip_grad)
        self.optimizer.step()
        if self.scheduler is not None:
            if self.world_size > 1 and self.budget.minutes:
                for factor in _cosine_factors(self.scheduler):
                    factor.set_clock(self.seconds_spent())
            self.scheduler.step()
        self.state.step += 1
        values = torch.stack([v.detach() for v in terms.values()]).tolist()  # one host sync a step
        self.state.losses.append(dict(zip(terms, values, strict=True)))
        return self.state.losses[-1]

    def _bar(self, progress: bool):
        bound = self.budget.step_bound(self.batches_per_epoch)
        by_time = self.budget.minutes > 0 and bound is None
        total = round(60 * self.budget.minutes) if by_time else bound
        return by_time, tqdm(
            total=total,
            initial=min(round(self.state.seconds), total) if by_time else self.state.step,
            disable=not progress or not self.main,
            unit="s" if by_time else "step",
            bar_format=TIME_BAR if by_time else None,  # seconds: no "s/s" rate
        )

    def fit(self, progress: bool = True) -> TrainState:
        """Train until the whole run's budget is spent; returns :class:`~torchfmap.nn.train.TrainState`."""
        epochs, state = self.budget.epochs, self.state
        self._t_start = time.perf_counter() - state.seconds
        self.net.train()
        if state.step == 0 and not state.scores:
            self.validate()  # the untrained network's score: the reference a trained one is read against
        self.save()  # a whole, resumable checkpoint from the start, before the first step
        stop = self.out_of_budget()
        by_time, bar = self._bar(progress)
        last_tick = state.seconds
        while (epochs is None or state.epoch < epochs) and not stop:
            if self.sampler is not None:
                self.sampler.set_epoch(state.epoch)
            self.shuffle.manual_seed(self.config.seed + state.epoch)  # each epoch's order, resumable
            if state.batch and state.draws is not None:  # resumed mid-epoch: the draws where it stood
                self.draws.set_state(torch.tensor(state.draws, dtype=torch.uint8))
            else:
                self.draws.manual_seed(self.config.seed + state.epoch)
            t_epoch = time.perf_counter()
            for i, batch in enumerate(self.loader):
                if i < state.batch:  # done before the run was interrupted
                    continue
                loss = self.step(batch)["total"]
                state.batch += 1
                if by_time:
                    now = time.perf_counter() - self._t_start
                    bar.update(min(round(now), bar.total) - min(round(last_tick), bar.total))
                    last_tick = now
                else:
                    bar.update()
                bar.set_postfix(step=state.step, full_epochs=state.epoch, loss=f"{loss:.3f}")
                if self.validate_every and state.step % self.validate_every == 0:
                    self.validate()
                    self.save()
                if self.out_of_budget():
                    stop = True
                    break
            else:
                state.epoch, state.batch = state.epoch + 1, 0
                state.epoch_seconds.append(time.perf_counter() - t_epoch)
            state.seconds = time.perf_counter() - self._t_start
            self.save()
        bar.close()
        if self.validate_fn is not None and (not state.scores or state.scores[-1][0] != state.step):
            self.validate()
        state.seconds = time.perf_counter() - self._t_start
        self.save()
        return state


def ddp_worker(
    rank: int, world_size: int, port: int, files, cache_dir, config_dict: dict, out_path, weights_dir
) -> None:
    """One rank of :func:`spawn_ddp` (gloo on CPU, NCCL with a GPU per rank); rank 0 writes ``out_path``."""
    cuda = torch.cuda.is_available() and torch.cuda.device_count() >= world_size
    device = torch.device(f"cuda:{rank}") if cuda else torch.device("cpu")
    os.environ.setdefault("MASTER_ADDR", "127.0.0.1")
    os.environ["MASTER_PORT"] = str(port)
    torch.distributed.init_process_group("nccl" if cuda else "gloo", rank=rank, world_size=world_size)
    try:
        config = TrainConfig(**config_dict)
        shapes = ShapeDataset(
            files, cache_dir, **config.dataset_kwargs(), rank=rank, world_size=world_size, progress=False
        )
        trainer = Trainer.from_config(config, shapes, device=device, checkpoint=out_path)
        trainer.fit(progress=rank == 0)
        torch.save(trainer.net.state_dict(), Path(weights_dir) / f"rank{rank}.pt")
    finally:
        torch.distributed.destroy_process_group()


def spawn_ddp(config: TrainConfig, files, out, *, world_size: int = 2, cache_dir=None) -> list[dict]:
    """DDP training of ``config`` on ``files`` (``world_size`` ranks) into ``out``; returns rank weights."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with tempfile.TemporaryDirectory(prefix="torchfmap-ddp-") as weights:
        torch.multiprocessing.spawn(
            ddp_worker,
            args=(world_size, port, [str(f) for f in files], cache_dir, asdict(config), str(out), weights),
            nprocs=world_size,
        )
        return [torch.load(Path(weights) / f"rank{r}.pt", map_location="cpu") for r in range(world_size)]
