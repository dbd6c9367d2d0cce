"""Benchmark: one CPU training step (torch): FeatureNet + solve_fmap + UnsupervisedFMLoss + Adam.

Run by hand from the repository root (prints markdown tables to stdout, progress to stderr, and
writes them to ``bench/results/train_step.md``)::

    python3 bench/train_step.py                    # float32 and float64, B = 1, 4, K = 30, 100
    python3 bench/train_step.py --train-ks 30 --train-batches 1 --train-v 500 --repeats 1  # quick

(Parts (2) and (3) of ``bench/solver.py``, which runs them unless ``--no-train``.) Inputs of
(2): random bases as in ``bench/_torch_inputs.py``; (3): cat0 and cat1 of the dev data, the
recipe's step against the previous recipe and the first learned path (see :func:`run_recipes`).

(2) Training step. ``FeatureNet(32, 64, width=64, n_blocks=3)`` on a pair of ``--train-v``
vertex shapes (random bases as above, Gaussian ``(B, V, 32)`` inputs): features of x and y,
``solve_fmap`` (both directions, default weights), ``UnsupervisedFMLoss()`` (default weights,
so the soft point maps ``(B, V, V)`` of the coupling term are included), backward, ``Adam``
step (lr 1e-3). One warm-up step, then the median of ``--repeats`` steps of each phase. The
forward phases are timed with ``time.perf_counter`` around each call; the backward is split by
gradient hooks: ``loss bwd`` ends when the gradients of ``C_xy`` and ``C_yx`` are complete,
``solver bwd`` when those of both feature tensors are, ``net bwd`` is the rest (the autograd
engine runs later-created nodes first, so this follows the forward order; approximate).
``torch.set_num_threads`` is left at its default unless ``--threads N`` is given (also in the
memory subprocesses); the 1-minute load average is recorded with every row, since another job
may share the CPUs. On a loaded machine with the default thread count every parallel torch op can
wait for a descheduled worker thread (milliseconds each), which swamps small ops: compare with
``--threads 1``.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import os
import statistics
import time
from typing import Any

import torch
from _common import Report, data_path, int_list, load1, load_note, log, markdown, str_list
from _torch_inputs import DTYPES, random_basis

from torchfmap import load_mesh
from torchfmap.experimental.networks import FeatureNet
from torchfmap.nn import DiffusionNet, UnsupervisedFMLoss, collate_shapes
from torchfmap.nn.config import TrainConfig
from torchfmap.nn.functional import solve_fmap
from torchfmap.nn.inputs import shape_arrays, shape_item


class Hooks:
    """Time at which the gradients of all given tensors are complete, per label."""

    def __init__(self) -> None:
        self.at: dict[str, float] = {}

    def watch(self, label: str, *tensors: torch.Tensor) -> None:
        left = [len(tensors)]

        def hook(grad: torch.Tensor) -> None:
            left[0] -= 1
            if left[0] == 0:
                self.at[label] = time.perf_counter()

        for t in tensors:
            t.register_hook(hook)


def train_step(net, loss_fn, opt, xin, yin, bx, by) -> tuple[dict[str, float], float]:
    opt.zero_grad(set_to_none=True)
    hooks = Hooks()
    t: dict[str, float] = {}
    t0 = time.perf_counter()
    fx, fy = net(xin, bx), net(yin, by)
    t1 = time.perf_counter()
    C_xy, C_yx = solve_fmap(fx, fy, bx, by)
    t2 = time.perf_counter()
    total = loss_fn(C_xy, C_yx, fx, fy, bx, by)["total"]
    t3 = time.perf_counter()
    hooks.watch("loss", C_xy, C_yx)
    hooks.watch("solver", fx, fy)
    total.backward()
    t4 = time.perf_counter()
    opt.step()
    t5 = time.perf_counter()
    t["net fwd"], t["solver fwd"], t["loss fwd"] = t1 - t0, t2 - t1, t3 - t2
    t["loss bwd"] = hooks.at["loss"] - t3
    t["solver bwd"] = hooks.at["solver"] - hooks.at["loss"]
    t["net bwd"] = t4 - hooks.at["solver"]
    t["backward"], t["adam"], t["step"] = t4 - t3, t5 - t4, t5 - t0
    return t, total.item()


def bench_train_config(dtype_name: str, b: int, k: int, args) -> dict[str, Any]:
    dtype = DTYPES[dtype_name]
    v = args.train_v
    gen = torch.Generator().manual_seed(args.seed)
    bx, by = random_basis(b, v, k, dtype, gen), random_basis(b, v, k, dtype, gen)
    xin = torch.randn(b, v, 32, generator=gen, dtype=torch.float64).to(dtype)
    yin = torch.randn(b, v, 32, generator=gen, dtype=torch.float64).to(dtype)
    torch.manual_seed(args.seed)
    net = FeatureNet(32, 64, width=64, n_blocks=3).to(dtype)
    loss_fn = UnsupervisedFMLoss()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    row: dict[str, Any] = {"dtype": dtype_name, "B": b, "K": k, "V": v, "load1 start": load1()}
    train_step(net, loss_fn, opt, xin, yin, bx, by)  # warm-up
    steps, losses = [], []
    for r in range(args.repeats):
        gc.collect()
        t, loss = train_step(net, loss_fn, opt, xin, yin, bx, by)
        steps.append(t)
        losses.append(loss)
        log(f"    step {r + 1}/{args.repeats}: {t['step']:.3f} s, loss {loss:.4g}")
    for key in steps[0]:
        row[f"{key} [s]"] = statistics.median(s[key] for s in steps)
    for part in ("net", "solver", "loss"):
        share = statistics.median((s[f"{part} fwd"] + s[f"{part} bwd"]) / s["step"] for s in steps)
        row[f"{part} %"] = 100 * share
    row["adam %"] = 100 * statistics.median(s["adam"] / s["step"] for s in steps)
    row["loss first→last"] = f"{losses[0]:.4g}→{losses[-1]:.4g}"
    row["finite"] = "yes" if all(torch.isfinite(torch.tensor(losses))) else "NO"
    row["load1 end"] = load1()
    return row


def run_train(args) -> list[str]:
    """Every (dtype, B, K) configuration; returns the report sections."""
    rows = []
    for dtype_name in args.dtypes:
        for b in args.train_batches:
            for k in args.train_ks:
                log(f"train: {dtype_name}, B={b}, K={k}, V={args.train_v}")
                rows.append(bench_train_config(dtype_name, b, k, args))
    cols = ["dtype", "B", "K", "V", "step [s]", "net fwd [s]", "solver fwd [s]", "loss fwd [s]"]
    cols += ["backward [s]", "loss bwd [s]", "solver bwd [s]", "net bwd [s]", "adam [s]"]
    split = ["dtype", "B", "K", "net %", "solver %", "loss %", "adam %", "loss first→last", "finite"]
    return [
        f"## (2) Training step: FeatureNet(32 -> 64, width 64, 3 blocks) + solve_fmap + "
        f"UnsupervisedFMLoss + Adam; median of {args.repeats} steps after 1 warm-up "
        f"({torch.get_num_threads()} torch threads)",
        markdown(rows, cols),
        "### Split of the step (fwd + bwd per part; median of the per-step shares)",
        markdown(rows, [*split, "load1 start", "load1 end"]),
    ]


def coo_spatial_gradient(f: torch.Tensor, grad, *, check=None) -> tuple[torch.Tensor, torch.Tensor]:
    """The spatial gradient as the previous recipe applied it (a baseline kept here, not in the
    library): a COO operator built and coalesced on every call, ``torch.sparse.mm``."""
    B, V, _ = f.shape
    gx, gy = [], []
    for b in range(B):
        rows, cols = grad.rows[b], grad.cols[b]
        index = torch.stack([torch.cat([rows, rows + V]), torch.cat([cols, cols])])
        weights = torch.cat([grad.weight_x[b], grad.weight_y[b]]).to(f.dtype)
        op = torch.sparse_coo_tensor(index, weights, (2 * V, V), check_invariants=False).coalesce()
        out = torch.sparse.mm(op, f[b])
        gx.append(out[:V])
        gy.append(out[V:])
    return torch.stack(gx), torch.stack(gy)


def run_recipes(args) -> list[str]:
    """(3) The training step of the recipe on cat0/cat1 (real meshes, float32) against two
    baselines run alternately in the same process.

    - ``first``: the first learned path, ``FeatureNet(32, 64, width 64, 3 blocks)`` (diffusion +
      MLPs) and ``UnsupervisedFMLoss()`` with full ``(V, V)`` soft maps;
    - ``previous``: the previous recipe, ``DiffusionNet(32, 64, width 64, 4 blocks)`` with its
      spatial gradient rebuilt as a coalesced COO matrix on every call
      (:func:`coo_spatial_gradient`) and the coupling term of :class:`TrainConfig`;
    - ``recipe``: :class:`TrainConfig` as it is (``DiffusionNet`` of its width and blocks,
      compressed-row gradient operators, coupling between ``n_samples`` random vertices, both
      soft maps from one similarity matrix).

    All: ``K`` eigenfunctions for the solver and the diffusion, ``solve_fmap`` both ways,
    backward, Adam. Steps alternate, ``--repeats`` each after one warm-up; medians and the
    ratios to the recipe.
    """
    folder = data_path("tosca5k_dev")
    if folder is None:
        return ["## (3) Recipe vs baselines: skipped (../shared/data/tosca5k_dev absent)"]
    from unittest import mock

    from torchfmap.nn import functional as F

    rows = []
    for k in args.recipe_ks:
        log(f"recipe: precompute cat0, cat1 with K={k}")
        shapes = []
        for name in ("cat0", "cat1"):
            arrays = shape_arrays(load_mesh(folder / f"{name}.off"), k, 32, k_net=k)
            shapes.append(collate_shapes([shape_item(arrays)]))
        (sx, sy), cfg = shapes, TrainConfig()
        torch.manual_seed(args.seed)
        nets = {
            "first": FeatureNet(32, 64, width=64, n_blocks=3),
            "previous": DiffusionNet(32, cfg.c_out, 64, 4, cfg.dropout, cfg.gradients),
            "recipe": DiffusionNet(32, cfg.c_out, cfg.width, cfg.n_blocks, cfg.dropout, cfg.gradients),
        }
        losses = {key: UnsupervisedFMLoss(**cfg.loss_weights) for key in nets}
        losses["first"] = UnsupervisedFMLoss()
        opts = {key: torch.optim.Adam(net.parameters(), lr=1e-3) for key, net in nets.items()}
        draws = torch.Generator().manual_seed(args.seed)  # the vertex samples of the coupling term

        def step(key: str, nets=nets, sx=sx, sy=sy, losses=losses, opts=opts, draws=draws) -> float:
            net, t0 = nets[key], time.perf_counter()
            args_x = (sx.inputs, sx.basis) if key == "first" else (sx.inputs, sx.net_basis, sx.grad)
            args_y = (sy.inputs, sy.basis) if key == "first" else (sy.inputs, sy.net_basis, sy.grad)
            patch = mock.patch.object(F, "spatial_gradient", coo_spatial_gradient)
            with patch if key == "previous" else contextlib.nullcontext():
                fx, fy = net(*args_x), net(*args_y)
                C_xy, C_yx = solve_fmap(fx, fy, sx.basis, sy.basis)
                total = losses[key](C_xy, C_yx, fx, fy, sx.basis, sy.basis, generator=draws)["total"]
                opts[key].zero_grad(set_to_none=True)
                total.backward()
            opts[key].step()
            return time.perf_counter() - t0

        times: dict[str, list[float]] = {key: [] for key in nets}
        for key in times:
            step(key)  # warm-up
        for r in range(args.repeats):
            for key in times:
                gc.collect()
                times[key].append(step(key))
            log(f"    K={k} step {r + 1}: " + ", ".join(f"{key} {t[-1]:.3f} s" for key, t in times.items()))
        med = {key: statistics.median(t) for key, t in times.items()}
        rows.append(
            {
                "K": k,
                "V (x, y)": f"{sx.inputs.shape[1]}, {sy.inputs.shape[1]}",
                "recipe step [s]": med["recipe"],
                "previous step [s]": med["previous"],
                "first step [s]": med["first"],
                "previous / recipe": med["previous"] / med["recipe"],
                "first / recipe": med["first"] / med["recipe"],
                "load1": load1(),
            }
        )
    return [
        f"## (3) Training step of the recipe (DiffusionNet width {TrainConfig().width}, "
        f"{TrainConfig().n_blocks} blocks) vs the previous recipe and the first learned path, "
        f"float32, one pair (cat0, cat1); median of {args.repeats} alternating steps "
        f"({torch.get_num_threads()} torch threads)",
        markdown(rows),
    ]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--train-ks", default="30,100")
    parser.add_argument("--train-batches", default="1,4")
    parser.add_argument("--train-v", type=int, default=5000)
    parser.add_argument("--recipe-ks", default="100", help="K of part (3); empty to skip it")


def parse_lists(args) -> None:
    args.dtypes = str_list(args.dtypes)
    args.train_ks, args.train_batches = int_list(args.train_ks), int_list(args.train_batches)
    args.recipe_ks = int_list(args.recipe_ks) if args.recipe_ks else []


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_arguments(parser)
    parser.add_argument("--dtypes", default="float32,float64")
    parser.add_argument("--repeats", type=int, default=5, help="timed steps (median), after 1 warm-up")
    parser.add_argument("--threads", type=int, default=0, help="torch.set_num_threads (0: leave default)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    parse_lists(args)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    out = Report("train_step")
    out.add(f"# Training step (torch {torch.__version__}, {os.cpu_count()} CPUs; {load_note()} at start)")
    if args.train_ks and args.train_batches:
        out.add(*run_train(args))
    if args.recipe_ks:
        out.add(*run_recipes(args))
    out.add(f"{load_note()} at end; total {time.perf_counter() - t_start:.0f} s.")
    out.save()


if __name__ == "__main__":
    main()
