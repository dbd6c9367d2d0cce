"""The reference training recipe (:class:`TrainConfig`), its :class:`Budget`, model and schedule."""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..errors import ParameterError
from ..fmap.defaults import DEFAULT_K
from .inputs import input_channels
from .modules import RegularizedFMSolver, UnsupervisedFMLoss
from .networks import DiffusionNet

#: Augmentations of XYZ inputs (:attr:`TrainConfig.augment`).
AUGMENTS = ("rigid", "up", "scale", "none")
#: The :class:`TrainConfig` fields that make up its :class:`Budget`.
BUDGET_FIELDS = ("epochs", "minutes", "max_steps")


@dataclass(frozen=True)
class Budget:
    """A run's bounds (across resumes; the first reached ends it): ``epochs`` or None, ``minutes``, ``steps``.

    Raises:
        ParameterError: no bound at all, or a negative or non-finite one."""

    epochs: int | None = None
    minutes: float = 0.0
    steps: int = 0

    def __post_init__(self) -> None:
        if self.epochs is not None and (isinstance(self.epochs, bool) or not isinstance(self.epochs, int)
                                        or self.epochs < 1):  # fmt: skip
            raise ParameterError(f"epochs must be an integer >= 1 or None, got {self.epochs!r}.")
        if isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 0:
            raise ParameterError(f"steps must be an integer >= 0, got {self.steps!r}.")
        if not (isinstance(self.minutes, (int, float)) and math.isfinite(self.minutes) and self.minutes >= 0):
            raise ParameterError(f"minutes must be finite and >= 0, got {self.minutes!r}.")
        if self.epochs is None and not self.minutes and not self.steps:
            raise ParameterError("training needs a budget. Fix: epochs, minutes and/or steps (max_steps).")

    def step_bound(self, batches_per_epoch: int) -> int | None:
        """``min(steps, epochs x batches_per_epoch)`` over the bounds set; None for a time budget."""
        bounds = [b for b in (self.steps, (self.epochs or 0) * batches_per_epoch) if b]
        return min(bounds) if bounds else None

    def spent(self, step: int = 0, seconds: float = 0.0, epoch: int = 0) -> list[str]:
        """The bounds reached at ``step``, ``seconds`` and ``epoch``, in command-line terms."""
        minutes = f"--minutes {self.minutes:g} (done: {seconds / 60:.1f} min)"
        bounds = [
            (f"--max-steps {self.steps} (done: {step} steps)", self.steps and step >= self.steps),
            (minutes, self.minutes and seconds >= 60 * self.minutes),
            (f"--epochs {self.epochs} (done: {epoch})", self.epochs and epoch >= self.epochs),
        ]
        return [text for text, done in bounds if done]

    def describe(self, batches_per_epoch: int) -> str:
        """``'2 epochs, 4 steps, 1.5 minutes'``: the bounds set, the step bound included."""
        steps = self.step_bound(batches_per_epoch)
        parts = [f"{self.epochs} epochs" if self.epochs else "", f"{steps} steps" if steps else ""]
        parts.append(f"{self.minutes:g} minutes" if self.minutes else "")
        return ", ".join(p for p in parts if p)


@dataclass
class TrainConfig:
    """The reference recipe (saved in checkpoints): data, network, solver, loss, optimiser, budget
    (:attr:`budget`) and loop settings. ``augment`` (XYZ inputs only): ``"rigid"`` (rotation and scaling),
    ``"up"`` (rotation about ``y``, scaling), ``"scale"`` or ``"none"``. ``parts``: 0 trains unsupervised on
    whole shapes; ``n > 0`` supervised on ``n`` cuts of every whole matched to every whole
    (:class:`~torchfmap.nn.parts.PartPairs`, ground truth from the folder's ``corres/``)."""

    k: int = DEFAULT_K
    k_net: int = 96
    n_wks: int = 32
    basis: str = "laplacian"
    inputs: str = "wks"
    width: int = 48
    c_out: int = 64
    n_blocks: int = 4
    dropout: float = 0.0
    gradients: bool = True
    lr: float = 1e-3
    clip_grad: float = 0.0
    epochs: int | None = 5
    minutes: float = 0.0
    max_steps: int = 0
    batch_size: int = 1
    w_lap: float = 1e-3
    seed: int = 0
    augment: str = "rigid"
    parts: int = 0
    loss_weights: dict = field(
        default_factory=lambda: {"w_bij": 1.0, "w_orth": 1.0, "w_couple": 1.0, "n_samples": 1000, "tau": 0.07}
    )

    @property
    def budget(self) -> Budget:
        """The run's :class:`Budget` (``max_steps`` is its ``steps``)."""
        return Budget(self.epochs, self.minutes, self.max_steps)

    def with_budget(self, budget: Budget) -> TrainConfig:
        """A copy whose whole budget is ``budget`` (bounds it leaves unset are unbounded)."""
        return dataclasses.replace(self, epochs=budget.epochs, minutes=budget.minutes, max_steps=budget.steps)

    def dataset_kwargs(self) -> dict:
        """Keyword arguments of :class:`~torchfmap.nn.data.ShapeDataset` for this recipe."""
        return dict(k=self.k, n_wks=self.n_wks, k_net=self.k_net, basis=self.basis, inputs=self.inputs)

    @classmethod
    def from_dict(cls, values: dict, where: str = "the recipe") -> TrainConfig:
        """``TrainConfig().updated(values)``: the recipe of ``values`` (field -> value)."""
        return cls().updated(values, where)

    def updated(self, values: dict, where: str = "the recipe") -> TrainConfig:
        """A copy with ``values`` (field -> value) replacing its own; a budget key replaces all the budget.

        Raises:
            ParameterError: an unknown key (nearest field named), a value of a wrong type, or no budget."""
        if not isinstance(values, dict):
            raise ParameterError(
                f"{where} must be a JSON object of TrainConfig fields, got {type(values).__name__}. Fix: "
                '{"k": 50, ...}, as TrainConfig.to_json writes.'
            )
        names = {f.name: f for f in dataclasses.fields(self)}
        unknown = sorted(set(values) - set(names))
        if unknown:
            near = {k: difflib.get_close_matches(k, names, 1) for k in unknown}
            hints = [f"{k!r} (did you mean {m[0]!r}?)" if m else repr(k) for k, m in near.items()]
            raise ParameterError(
                f"{where} has keys {', '.join(hints)} that TrainConfig does not know. Fix: use its "
                f"fields only: {', '.join(names)}."
            )
        default = type(self)()
        for key, value in values.items():
            _check_type(key, value, getattr(default, key), where)
            _check_range(key, value, where)
        if any(k in values for k in BUDGET_FIELDS):
            values = {"epochs": None, "minutes": 0.0, "max_steps": 0, **values}
        config = dataclasses.replace(self, **values)
        config.budget  # noqa: B018 -- refuses a budget without bounds now, not at the first step
        return config

    @classmethod
    def from_json(cls, path: str | os.PathLike) -> TrainConfig:
        """The recipe in the JSON file ``path``, defaults elsewhere."""
        return cls.from_dict(cls.read_json(path), where=f"the recipe file {path}")

    @classmethod
    def read_json(cls, path: str | os.PathLike) -> dict:
        """The values of the recipe file ``path`` (as :meth:`to_json` writes), checked as :meth:`updated`.

        Raises:
            ParameterError: a file that is not JSON, or as :meth:`updated`."""
        try:
            values = json.loads(Path(path).read_text(encoding="utf-8"))
        except json.JSONDecodeError as err:
            raise ParameterError(
                f"the recipe file {path} is not JSON ({err}). Fix: write it as TrainConfig.to_json does "
                "(`torchfmap models --recipe CKPT` prints a checkpoint's)."
            ) from None
        except OSError as err:
            raise ParameterError(
                f"cannot read the recipe file {path} ({err.strerror}). Fix: check the path."
            ) from None
        cls().updated(values, where=f"the recipe file {path}")
        return values

    def to_json(self, path: str | os.PathLike | None = None) -> str:
        """The recipe as JSON text (every field), written to ``path`` too when given."""
        text = json.dumps(dataclasses.asdict(self), indent=2) + "\n"
        if path is not None:
            Path(path).write_text(text, encoding="utf-8")
        return text


def _check_type(key: str, value, default, where: str) -> None:
    """Refuse a recipe value not of the field's type (an int for a float is fine; epochs may be None)."""
    if key == "epochs" and value is None:
        return
    kind = type(default)
    ok = isinstance(value, kind) and not (kind is int and isinstance(value, bool))
    ok = ok or (kind is float and isinstance(value, int) and not isinstance(value, bool))
    if not ok:
        raise ParameterError(
            f"{where}: {key} must be {kind.__name__}, got {value!r}. Fix: e.g. {json.dumps({key: default})}."
        )


#: Recipe fields that must be integers >= 1, and the allowed ranges of the float fields.
_POSITIVE_FIELDS = ("k", "k_net", "n_wks", "width", "c_out", "n_blocks", "batch_size")
_FLOAT_RANGES = {"lr": (0.0, math.inf, False), "clip_grad": (0.0, math.inf, True),
                 "w_lap": (0.0, math.inf, True), "dropout": (0.0, 1.0, True)}  # fmt: skip


def _check_range(key: str, value, where: str) -> None:
    """Refuse a recipe value outside its field's range (finite; sizes >= 1; ``lr`` > 0; ``dropout`` < 1)."""
    if key == "parts" and value < 0:
        raise ParameterError(f"{where}: parts must be >= 0, got {value!r}. Fix: 0 (whole shapes) or e.g. 4.")
    if key in _POSITIVE_FIELDS and value < 1:
        raise ParameterError(f"{where}: {key} must be >= 1, got {value!r}. Fix: a positive size.")
    if key in _FLOAT_RANGES:
        low, high, closed = _FLOAT_RANGES[key]
        if not (math.isfinite(value) and (value >= low if closed else value > low) and value < high):
            bound = f"{'>=' if closed else '>'} {low}" + (f" and < {high}" if math.isfinite(high) else "")
            raise ParameterError(f"{where}: {key} must be finite and {bound}, got {value!r}.")


def network_kwargs(config: TrainConfig) -> dict:
    """The :class:`~torchfmap.nn.networks.DiffusionNet` arguments of the recipe ``config``."""
    c_in = input_channels(config.inputs, config.n_wks)
    return dict(
        c_in=c_in, c_out=config.c_out, width=config.width, n_blocks=config.n_blocks,
        dropout=config.dropout, gradients=config.gradients,
    )  # fmt: skip


def build_model(config: TrainConfig) -> tuple[DiffusionNet, RegularizedFMSolver, UnsupervisedFMLoss]:
    """``(network, solver, loss)`` of the recipe, the network drawn from CPU RNG seeded ``config.seed``."""
    with torch.random.fork_rng(devices=[]):
        torch.default_generator.manual_seed(config.seed)
        net = DiffusionNet(**network_kwargs(config))
    return (net, *build_solver(config))


def build_solver(config: TrainConfig) -> tuple[RegularizedFMSolver, UnsupervisedFMLoss]:
    """``(solver, loss)`` of the recipe, without building a network (inference)."""
    return RegularizedFMSolver(w_lap=config.w_lap), UnsupervisedFMLoss(**config.loss_weights)


class CosineBudget:
    """``LambdaLR`` factor: cosine from 1 to ``floor`` over ``max(step / step_bound, seconds / (60 minutes))``
    of a :class:`Budget` (``batches_per_epoch`` needed with epochs); ``state_dict`` saves the time counted.

    Raises:
        ParameterError: a budget with epochs and no ``batches_per_epoch``, or ``floor`` outside ``[0, 1]``."""

    def __init__(self, budget: Budget, batches_per_epoch: int | None = None, floor: float = 0.02) -> None:
        if not isinstance(budget, Budget):
            raise ParameterError(
                f"CosineBudget follows a Budget, got {type(budget).__name__}. Fix: Budget(steps=...)."
            )
        if budget.epochs is not None and not batches_per_epoch:
            raise ParameterError(
                "a budget in epochs needs the batches of an epoch. Fix: "
                "CosineBudget(budget, batches_per_epoch=...)."
            )
        if not 0 <= floor <= 1:
            raise ParameterError(f"floor must be in [0, 1], got {floor}.")
        steps = budget.step_bound(batches_per_epoch or 0) or 0
        self.seconds, self.steps, self.floor = 60.0 * budget.minutes, int(steps), floor
        self.counted, self.last, self.pid = 0.0, None, os.getpid()

    @property
    def bounds(self) -> tuple[float, int, float]:
        """``(seconds, steps, floor)`` the factor follows (settable: a resumed run puts its own back)."""
        return self.seconds, self.steps, self.floor

    @bounds.setter
    def bounds(self, value: tuple[float, int, float]) -> None:
        self.seconds, self.steps, self.floor = value

    def set_clock(self, seconds: float) -> None:
        """Set the training time spent to ``seconds`` (DDP ranks agree on one clock before each step)."""
        self.counted, self.last = float(seconds), None

    def fraction(self, step: int) -> float:
        """The part of the budget spent at ``step`` (and the time counted), in ``[0, 1]``."""
        by_time = self.counted / self.seconds if self.seconds else 0.0
        by_steps = step / self.steps if self.steps else 0.0
        return min(max(by_time, by_steps), 1.0)

    def __call__(self, step: int) -> float:
        now = time.perf_counter()
        if self.last is not None and self.pid == os.getpid():
            self.counted += now - self.last
        self.last, self.pid = now, os.getpid()
        return self.floor + (1 - self.floor) * 0.5 * (1 + math.cos(math.pi * self.fraction(step)))
