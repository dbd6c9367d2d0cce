"""Checkpoints: atomic, checksummed files of weights, recipe, extras and a network record (``'class'`` and
``'kwargs'``: any importable class is rebuilt), read with ``weights_only=True``."""

from __future__ import annotations

import dataclasses
import importlib
import io
from dataclasses import asdict
from pathlib import Path

import torch

from .._util.files import CHECKED_MAGIC, load_checked_bytes, save_checked_bytes
from ..errors import CorruptFileError, ParameterError
from .config import TrainConfig, network_kwargs
from .networks import DiffusionNet
from .shipped import resolve_checkpoint

#: Types a network's recorded constructor arguments may hold (what ``weights_only`` loading reads).
_PLAIN = (type(None), bool, int, float, str)


def _check_plain(value, where: str) -> None:
    if isinstance(value, _PLAIN):
        return
    if isinstance(value, dict) and all(isinstance(k, str) for k in value):
        value = list(value.values())
    if not isinstance(value, (list, tuple)):
        raise ParameterError(
            f"{where} holds {type(value).__name__} {value!r}; a checkpoint records only plain values "
            "(numbers, strings, bools, None, and lists, tuples or str-keyed dicts of those). Fix: record the "
            "constructor arguments as such values."
        )
    for item in value:
        _check_plain(item, where)


def _unwrap(net: torch.nn.Module) -> torch.nn.Module:
    return net.module if isinstance(net, torch.nn.parallel.DistributedDataParallel) else net


def network_record(net: torch.nn.Module, net_kwargs: dict | None = None) -> dict:
    """``{'class': 'module:qualname', 'kwargs': net_kwargs or net.init_kwargs or None}`` of ``net``. Raises
    :class:`ParameterError`: arguments that are not plain values."""
    net = _unwrap(net)
    cls = type(net)
    kwargs = net_kwargs if net_kwargs is not None else getattr(net, "init_kwargs", None)
    if kwargs is not None:
        if not isinstance(kwargs, dict):
            raise ParameterError(
                f"the network's constructor arguments must be a dict, got {type(kwargs).__name__}."
            )
        _check_plain(kwargs, f"the constructor arguments of {cls.__qualname__}")
        kwargs = dict(kwargs)
    return {"class": f"{cls.__module__}:{cls.__qualname__}", "kwargs": kwargs}


def _check_config_fits(record: dict, cfg) -> None:
    """Refuse a recipe config that disagrees with the recipe network it is saved with."""
    recipe_net = f"{DiffusionNet.__module__}:{DiffusionNet.__qualname__}"
    if not isinstance(cfg, dict) or record["class"] != recipe_net:
        return
    if not {"width", "c_out", "n_blocks", "n_wks", "inputs"} <= set(cfg):
        return  # not a recipe config (e.g. train() with a network of the caller's): nothing to compare
    try:
        expected = network_kwargs(TrainConfig(**cfg))
    except TypeError:
        return
    got = record.get("kwargs") or {}
    differ = {k: (v, got[k]) for k, v in expected.items() if k in got and got[k] != v}
    if differ:
        said = ", ".join(f"{k}: config {a!r}, network {b!r}" for k, (a, b) in differ.items())
        raise ParameterError(
            f"the config does not describe the network being saved ({said}). Fix: save the config the "
            "network was built from (build_model(config)), or correct those fields."
        )


def check_config_fits(net: torch.nn.Module, config: TrainConfig | dict) -> None:
    """Refuse (:class:`ParameterError`) a recipe ``config`` not describing the recipe network ``net``."""
    _check_config_fits(network_record(net), asdict(config) if isinstance(config, TrainConfig) else config)


def save_checkpoint(
    path, net: torch.nn.Module, config: TrainConfig | dict, *, net_kwargs: dict | None = None, **extra
) -> Path:
    """Write an atomic, checksummed checkpoint: weights, config, :func:`network_record` and extras."""
    path, cfg = Path(path), (asdict(config) if isinstance(config, TrainConfig) else config)
    record = network_record(net, net_kwargs)
    _check_config_fits(record, cfg)
    path.parent.mkdir(parents=True, exist_ok=True)
    ckpt = {"state_dict": _unwrap(net).state_dict(), "config": cfg, "network": record, **extra}
    buffer = io.BytesIO()
    torch.save(ckpt, buffer)
    return save_checked_bytes(path, buffer.getvalue())


def _refuse_foreign(file) -> None:
    """Refuse a file without torchfmap's header (e.g. another project's ``torch.save``), saying so."""
    try:
        with open(file, "rb") as fh:
            head = fh.read(len(CHECKED_MAGIC))
    except OSError:
        return
    if head != CHECKED_MAGIC:
        raise CorruptFileError(
            f"{str(file)!r} is not a torchfmap checkpoint: it lacks the header torchfmap writes (a "
            "file of torch.save, such as another project's weights?). Nothing in it was read. Fix: "
            "a checkpoint of `torchfmap train` or save_checkpoint(); for foreign weights, load them "
            "into your network yourself (net.load_state_dict(torch.load(path, weights_only=True))) "
            "and match with LearnedMatcher(net, config)."
        )


def read_checkpoint(path, map_location="cpu") -> dict:
    """The checkpoint dict of a file or shipped name, checksum verified, loaded with ``weights_only=True``.

    Raises:
        CorruptFileError: a truncated or altered file, a payload that is not a weights-only torch file, or a
            dict without ``state_dict`` and ``config``.
        ParameterError: neither a file nor a shipped name."""
    file = resolve_checkpoint(path)
    _refuse_foreign(file)
    payload = load_checked_bytes(file, "checkpoint")
    fix = "Fix: pass a file written by `torchfmap train` or save_checkpoint()."
    try:
        ckpt = torch.load(io.BytesIO(payload), map_location=map_location, weights_only=True)
    except Exception as err:  # pickle.UnpicklingError (refused globals), RuntimeError, EOFError, ...
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CorruptFileError(
            f"{file} holds no torchfmap checkpoint: its payload is not a weights-only torch file "
            f"of tensors and plain values ({first}). Nothing in it was run. {fix}"
        ) from None
    missing = [key for key in ("state_dict", "config") if not isinstance(ckpt, dict) or key not in ckpt]
    if missing:
        what = f"a {type(ckpt).__name__}" if not isinstance(ckpt, dict) else f"keys {sorted(ckpt)}"
        raise CorruptFileError(
            f"{file} is not a torchfmap checkpoint: it has {what}, without {missing} (expected "
            f"'state_dict', 'config' and optionally 'network', 'best_state_dict', 'train_state'). {fix}"
        )
    return ckpt


def _network_class(name: str) -> type:
    module_name, _, qualname = str(name).partition(":")
    fix = (
        "Fix: define the class at module level of an importable module (on sys.path), or build the "
        "network yourself and load ckpt['state_dict'] into it."
    )
    if not module_name or not qualname or "<locals>" in qualname:
        raise ParameterError(f"the checkpoint's network class {name!r} cannot be imported. {fix}")
    try:
        obj = importlib.import_module(module_name)
        for part in qualname.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError) as err:
        raise ParameterError(
            f"cannot import the checkpoint's network class {name!r} ({err}). {fix}"
        ) from None
    if not (isinstance(obj, type) and issubclass(obj, torch.nn.Module)):
        raise ParameterError(
            f"the checkpoint's network class {name!r} is not a torch.nn.Module subclass. Fix: record "
            "a network class (save_checkpoint does)."
        )
    return obj


def load_network(ckpt: dict, best: bool = True) -> torch.nn.Module:
    """The network of a checkpoint dict, rebuilt from its record in its weights' dtype, in eval mode
    (``best``: the best validation weights if any).

    Raises:
        ParameterError: no record, a class that cannot be imported or is not a ``torch.nn.Module``, no
            constructor arguments, or weights that are non-finite or do not fit."""
    record = ckpt.get("network")
    if record is not None and not isinstance(record, dict):
        raise ParameterError(
            f"the checkpoint's network record is a {type(record).__name__}, not a dict. Fix: re-save it."
        )
    if record is None:
        raise ParameterError(
            "the checkpoint does not record its network (a development format that was never "
            "released). Fix: train it again with `torchfmap train`, or build the network yourself "
            "and load ckpt['state_dict']."
        )
    cls, kwargs = _network_class(record.get("class")), record.get("kwargs")
    if kwargs is None:
        raise ParameterError(
            f"the checkpoint names the network class {record['class']!r} but not its constructor "
            "arguments. Fix: give the network an init_kwargs dict (or pass net_kwargs to "
            "save_checkpoint) when saving, or build it yourself and load ckpt['state_dict']."
        )
    try:
        net = cls(**kwargs)
    except (TypeError, ValueError) as err:
        raise ParameterError(
            f"the checkpoint's network {record['class']!r} cannot be built from its recorded "
            f"arguments {kwargs} ({err}). Fix: use the torchfmap version that wrote it, or build "
            "the network yourself and load ckpt['state_dict']."
        ) from None
    state = ckpt.get("best_state_dict") if best and ckpt.get("best_state_dict") else ckpt["state_dict"]
    if not isinstance(state, dict):
        raise ParameterError(
            f"the checkpoint's weights are a {type(state).__name__}, not a state dict. Fix: re-save it."
        )
    broken = [k for k, t in state.items() if isinstance(t, torch.Tensor) and not torch.isfinite(t).all()]
    if broken:
        raise ParameterError(
            f"the checkpoint's weights {broken[:3]} hold NaN or infinite values (a diverged run?). Fix: "
            "use an earlier checkpoint of the run, or train again (e.g. with a lower lr or --clip-grad)."
        )
    dtypes = {t.dtype for t in state.values() if isinstance(t, torch.Tensor) and t.is_floating_point()}
    if len(dtypes) == 1:  # weights saved in one dtype (e.g. a float64 network): load them in it
        net = net.to(dtypes.pop())
    try:
        net.load_state_dict(state)
    except RuntimeError as err:  # missing / unexpected keys, size mismatches
        lines = [line.strip() for line in str(err).splitlines() if line.strip()][1:4]
        raise ParameterError(
            f"the checkpoint's weights do not fit its network {type(net).__name__} as its config "
            f"builds it: {'; '.join(lines)}. Fix: the config and the weights must come from the "
            "same training run (do not edit one without the other)."
        ) from None
    return net.eval()


def _config(cfg: dict) -> TrainConfig:
    """``cfg`` (a checkpoint's) as a :class:`TrainConfig`."""
    if not isinstance(cfg, dict):
        raise ParameterError(
            f"the checkpoint's config is a {type(cfg).__name__}, not a dict. Fix: re-save it."
        )
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(cfg) - names)
    if unknown:
        raise ParameterError(
            f"the checkpoint's config has keys {unknown} that TrainConfig does not know. Fix: read it "
            "with read_checkpoint() and rebuild the network with load_network()."
        )
    return TrainConfig.from_dict(cfg, where="the checkpoint's config")


def load_checkpoint(path, best: bool = True) -> tuple[torch.nn.Module, TrainConfig, dict]:
    """``(network in eval mode, config, checkpoint dict)`` (:func:`load_network`).

    Raises:
        ParameterError: as :func:`load_network`, or a config that is not a :class:`TrainConfig`.
        CorruptFileError: a truncated or altered file."""
    ckpt = read_checkpoint(path)
    try:
        return load_network(ckpt, best), _config(ckpt["config"]), ckpt
    except ParameterError as err:
        raise ParameterError(f"{path}: {err}") from None


def read_recipe(path) -> TrainConfig:
    """A checkpoint's :class:`TrainConfig` without building the network; raises as :func:`load_checkpoint`."""
    ckpt = read_checkpoint(path)
    try:
        return _config(ckpt["config"])
    except ParameterError as err:
        raise ParameterError(f"{path}: {err}") from None
