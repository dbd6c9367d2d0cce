"""Benchmark: the differentiable batched functional-map solve and a CPU training step (torch).

Run by hand from the repository root (prints markdown tables to stdout, progress to stderr, and
writes them to ``bench/results/solver.md``)::

    python3 bench/solver.py                        # both parts, float32 and float64
    python3 bench/solver.py --ks 100 --no-train --no-memory
    python3 bench/solver.py --no-solver --train-ks 30 --train-batches 1
    python3 bench/solver.py --ks 10 --v 200 --batch 2 --repeats 1 --no-train --dtypes float64  # quick

Inputs: random, seeded bases and features, see ``bench/_torch_inputs.py``.

(1) Solver. ``solve_fmap(feat_x, feat_y, bx, by, w_desc=1, w_lap=1e-3, both=True)`` (one
batched ``torch.linalg.solve`` over ``(B, K, K, K)`` per direction) against a per-row loop
written here: the same math (project, rotate by ``U``, Laplacian mask normalised to mean 1,
then one ``torch.linalg.solve`` of a ``(K, K)`` system per row of every batch item in a Python
loop, un-rotate), both directions, both with autograd. Features ``(B, V, D)`` Gaussian with
``requires_grad``; the scalar is ``Σ R_xy ∘ C_xy + Σ R_yx ∘ C_yx`` with fixed Gaussian ``R``.
One warm-up of each, then ``--repeats`` rounds alternating batched and loop (so a load from
another process hits both alike); each cell is a median over rounds. Every configuration runs
twice, batched first in each round and loop first (``order``): the batched solve's large
``(B, K, K, K)`` buffer meets a different allocator state in each (memory just freed by the
loop's many small tensors, or by its own previous call). ``loop/batched`` is the
ratio of the fwd+bwd medians (target >= 3). Agreement: max ``|ΔC|`` over ``C_xy`` and
``C_yx`` and max ``|Δ∇feat_x|``, ``|Δ∇feat_y|`` (absolute and relative to the largest entry).
``cond`` is the 2-norm condition number of the ``K`` row systems of the first batch item
(``x -> y``, float64): with ``D < K`` the Gram matrix ``A_x A_xᵀ`` is singular and only the
``w_lap`` mask term regularises it. Memory: ``system`` is the size of one ``(B, K, K, K)``
system tensor (two per call, one per direction); ``RSS peak`` is the resident high-water mark
(``VmHWM``, reset through ``/proc/self/clear_refs``) above the resident size just before the
first fwd+bwd call in a fresh subprocess (inputs built, nothing run yet; includes first-call
library set-up), falling back to ``ru_maxrss`` where ``clear_refs`` is not writable.

(2) Training step: ``bench/train_step.py`` (run here too unless ``--no-train``; its options
``--train-*`` and ``--recipe-ks`` are accepted): random bases, and (3) the recipe's step on
real meshes against the previous recipe and the first learned path (``--recipe-ks ''`` skips it).

``torch.set_num_threads`` is left at its default unless ``--threads N`` is given (also in the
memory subprocesses); the 1-minute load average is recorded with every row, since another job
may share the CPUs. On a loaded machine with the default thread count every parallel torch op can
wait for a descheduled worker thread (milliseconds each), which swamps small ops: compare with
``--threads 1``.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import torch
import train_step
from _common import (
    MiB,
    Report,
    int_list,
    load1,
    load_note,
    log,
    markdown,
    reset_peak_rss,
    status_mib,
)
from _torch_inputs import DTYPES, solver_inputs

from torchfmap.nn.functional import BasisBatch, solve_fmap

W_DESC, W_LAP = 1.0, 1e-3


# -- the per-row loop baseline ---------------------------------------------------------------------
def loop_mask(lam_x: torch.Tensor, lam_y: torch.Tensor) -> torch.Tensor:
    """``(B, K_y, K_x)`` mask ``(λ_x,j - λ_y,i)²`` normalised to mean 1 per batch item."""
    m = (lam_x.clip(min=0)[:, None, :] - lam_y.clip(min=0)[:, :, None]) ** 2
    return m / m.mean(dim=(-2, -1), keepdim=True)


def loop_systems(A_x, A_y, lam_x, U_x, lam_y, U_y):
    """Rotated Gram matrix, right-hand sides and mask: ``G (B, Kx, Kx)``, ``rhs (B, Ky, Kx)``."""
    A_xr = U_x.transpose(-1, -2) @ A_x
    A_yr = U_y.transpose(-1, -2) @ A_y
    G = W_DESC * (A_xr @ A_xr.transpose(-1, -2))
    rhs = W_DESC * (A_yr @ A_xr.transpose(-1, -2))
    return G, rhs, loop_mask(lam_x, lam_y)


def loop_rotate_and_solve(A_x, A_y, lam_x, U_x, lam_y, U_y) -> torch.Tensor:
    """Same math as ``rotate_and_solve``, one ``(K_x, K_x)`` solve per row in a Python loop."""
    G, rhs, mask = loop_systems(A_x, A_y, lam_x, U_x, lam_y, U_y)
    batch = []
    for b in range(G.shape[0]):
        rows = [
            torch.linalg.solve(G[b] + W_LAP * torch.diag(mask[b, i]), rhs[b, i]) for i in range(rhs.shape[1])
        ]
        batch.append(torch.stack(rows))
    return U_y @ torch.stack(batch) @ U_x.transpose(-1, -2)


def loop_fmap_solve(fx, fy, bx: BasisBatch, by: BasisBatch) -> tuple[torch.Tensor, torch.Tensor]:
    A_x = bx.values.transpose(-1, -2) @ (bx.mass[..., None] * fx)
    A_y = by.values.transpose(-1, -2) @ (by.mass[..., None] * fy)
    C_xy = loop_rotate_and_solve(A_x, A_y, bx.lam, bx.U, by.lam, by.U)
    C_yx = loop_rotate_and_solve(A_y, A_x, by.lam, by.U, bx.lam, bx.U)
    return C_xy, C_yx


def batched_fmap_solve(fx, fy, bx: BasisBatch, by: BasisBatch) -> tuple[torch.Tensor, torch.Tensor]:
    return solve_fmap(fx, fy, bx, by, w_desc=W_DESC, w_lap=W_LAP, both=True)


METHODS: dict[str, Callable] = {"batched": batched_fmap_solve, "loop": loop_fmap_solve}


def fwd_bwd(method: str, inp: dict[str, Any]) -> tuple[float, float, dict[str, torch.Tensor]]:
    """One forward (with the scalar) and backward; returns (fwd s, bwd s, C's and gradients)."""
    fx, fy = inp["fx"], inp["fy"]
    fx.grad = fy.grad = None
    t0 = time.perf_counter()
    C_xy, C_yx = METHODS[method](fx, fy, inp["bx"], inp["by"])
    total = (inp["r_xy"] * C_xy).sum() + (inp["r_yx"] * C_yx).sum()
    t1 = time.perf_counter()
    total.backward()
    t2 = time.perf_counter()
    out = {"C_xy": C_xy.detach(), "C_yx": C_yx.detach(), "gx": fx.grad.clone(), "gy": fy.grad.clone()}
    return t1 - t0, t2 - t1, out


def max_diff(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    """(max |a - b|, that over max |b|)."""
    diff = (a - b).abs().max().item()
    return diff, diff / max(b.abs().max().item(), 1e-300)


def system_cond(inp: dict[str, Any]) -> tuple[float, float]:
    """Median and max 2-norm condition number of the row systems of batch item 0, x -> y (float64)."""
    with torch.no_grad():
        bx, by = (BasisBatch(*(t[:1].double() for t in b[:5])) for b in (inp["bx"], inp["by"]))
        A_x = bx.values.transpose(-1, -2) @ (bx.mass[..., None] * inp["fx"][:1].double())
        A_y = by.values.transpose(-1, -2) @ (by.mass[..., None] * inp["fy"][:1].double())
        G, _, mask = loop_systems(A_x, A_y, bx.lam, bx.U, by.lam, by.U)
        systems = G[0][None] + W_LAP * torch.diag_embed(mask[0])
        cond = torch.linalg.cond(systems)
    return cond.median().item(), cond.max().item()


def bench_solver_config(
    dtype_name: str, b: int, v: int, k: int, d: int, args, order: tuple[str, ...] = tuple(METHODS)
) -> dict[str, Any]:
    dtype = DTYPES[dtype_name]
    inp = solver_inputs(b, v, k, d, dtype, args.seed)
    row: dict[str, Any] = {"dtype": dtype_name, "B": b, "K": k, "V": v, "D": d, "order": " then ".join(order)}
    row["load1 start"] = load1()
    times: dict[str, list[tuple[float, float]]] = {m: [] for m in order}
    outs: dict[str, dict[str, torch.Tensor]] = {}
    for m in order:  # warm-up
        fwd_bwd(m, inp)
    for r in range(args.repeats):
        for m in order:
            gc.collect()
            f, bw, outs[m] = fwd_bwd(m, inp)
            times[m].append((f, bw))
        done = ", ".join(f"{m} {sum(times[m][-1]):.3f} s" for m in METHODS)
        log(f"    round {r + 1}/{args.repeats}: {done}")
    for m in METHODS:
        row[f"{m} fwd [s]"] = statistics.median(t[0] for t in times[m])
        row[f"{m} bwd [s]"] = statistics.median(t[1] for t in times[m])
        row[f"{m} fwd+bwd [s]"] = statistics.median(t[0] + t[1] for t in times[m])
    row["loop/batched"] = row["loop fwd+bwd [s]"] / row["batched fwd+bwd [s]"]
    ob, ol = outs["batched"], outs["loop"]
    dc = [max_diff(ob[c], ol[c]) for c in ("C_xy", "C_yx")]
    row["max|ΔC|"] = max(x[0] for x in dc)
    row["max|ΔC| rel"] = max(x[1] for x in dc)
    row["max|Δ∇fx|"], row["max|Δ∇fx| rel"] = max_diff(ob["gx"], ol["gx"])
    row["max|Δ∇fy|"], row["max|Δ∇fy| rel"] = max_diff(ob["gy"], ol["gy"])
    row["max|C|"] = ol["C_xy"].abs().max().item()
    row["max|∇fx|"] = ol["gx"].abs().max().item()
    finite = all(bool(torch.isfinite(t).all()) for o in outs.values() for t in o.values())
    row["finite"] = "yes" if finite else "NO"
    row["cond median"], row["cond max"] = system_cond(inp)
    row["system MiB"] = b * k**3 * dtype.itemsize / MiB
    row["load1 end"] = load1()
    return row


# -- memory (fresh subprocess per configuration) --------------------------------------------------
def child_memory(spec: str) -> None:
    """``--child method,dtype,B,V,K,D,seed``: one fwd+bwd call; prints JSON peaks (MiB) to stdout."""
    method, dtype_name, *nums = spec.split(",")
    b, v, k, d, seed = (int(x) for x in nums)
    inp = solver_inputs(b, v, k, d, DTYPES[dtype_name], seed)
    gc.collect()
    ru_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    source = "VmHWM" if reset_peak_rss() else "ru_maxrss"
    rss_before = status_mib("VmRSS")
    fwd_bwd(method, inp)
    ru_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if source == "VmHWM":
        peak = status_mib("VmHWM") - rss_before
    else:
        peak = ru_after - max(ru_before, rss_before)
    print(json.dumps({"peak": peak, "source": source, "rss_before": rss_before, "ru_maxrss": ru_after}))


def measure_memory(method: str, dtype_name: str, b: int, v: int, k: int, d: int, args) -> dict:
    spec = ",".join(str(x) for x in (method, dtype_name, b, v, k, d, args.seed))
    cmd = [sys.executable, os.path.abspath(__file__), "--threads", str(args.threads), "--child", spec]
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        log(f"    memory child {spec} failed ({res.returncode}): {res.stderr.strip()[-500:]}")
        return {"peak": float("nan"), "source": "failed"}
    return json.loads(res.stdout.strip().splitlines()[-1])


def run_solver(args) -> list[str]:
    """Every (dtype, K) configuration, with the memory subprocesses; returns the report sections."""
    rows = []
    for dtype_name in args.dtypes:
        for k, order in ((k, o) for k in args.ks for o in (tuple(METHODS), tuple(reversed(METHODS)))):
            log(f"solver: {dtype_name}, B={args.batch}, K={k}, V={args.v}, D={args.d}, {order[0]} first")
            row = bench_solver_config(dtype_name, args.batch, args.v, k, args.d, args, order)
            for m in () if args.no_memory or order != tuple(METHODS) else METHODS:
                log(f"    memory: {m} (fresh subprocess)")
                mem = measure_memory(m, dtype_name, args.batch, args.v, k, args.d, args)
                row[f"RSS peak {m} MiB"], row["RSS source"] = mem["peak"], mem["source"]
            rows.append(row)
    cols = [
        "dtype",
        "B",
        "K",
        "V",
        "D",
        "order",
        *(f"{m} {p} [s]" for m in METHODS for p in ("fwd", "bwd", "fwd+bwd")),
    ]
    agree = ["dtype", "K", "order", "max|ΔC|", "max|ΔC| rel", "max|Δ∇fx|", "max|Δ∇fx| rel", "max|Δ∇fy|"]
    agree += ["max|Δ∇fy| rel", "max|C|", "max|∇fx|", "finite", "cond median", "cond max", "system MiB"]
    if not args.no_memory:
        agree += [f"RSS peak {m} MiB" for m in METHODS] + ["RSS source"]
    return [
        "## (1) solve_fmap (batched) vs per-row loop: forward + backward, both directions; "
        f"median of {args.repeats} alternating rounds after 1 warm-up",
        markdown(rows, [*cols, "loop/batched", "load1 start", "load1 end"]),
        "### Agreement (batched vs loop, last round), conditioning and memory",
        markdown(rows, agree),
        "rel = max|Δ| / max|loop value|. cond: row systems of batch item 0, x -> y, in float64. "
        "system MiB: one (B, K, K, K) tensor (solve_fmap builds one per direction). RSS peak: "
        "resident high-water mark above the start of one fwd+bwd call in a fresh process.",
    ]


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batch", type=int, default=8, help="B of the solver benchmark")
    parser.add_argument("--ks", default="100,50", help="K of the solver benchmark, comma-separated")
    parser.add_argument("--v", type=int, default=5000, help="vertices of the solver benchmark")
    parser.add_argument("--d", type=int, default=64, help="feature channels of the solver benchmark")
    parser.add_argument("--dtypes", default="float32,float64")
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds/steps (median), after 1 warm-up")
    train_step.add_arguments(parser)
    parser.add_argument("--no-solver", action="store_true")
    parser.add_argument("--no-memory", action="store_true", help="skip the subprocess RSS measurements")
    parser.add_argument("--no-train", action="store_true")
    parser.add_argument("--threads", type=int, default=0, help="torch.set_num_threads (0: leave default)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    train_step.parse_lists(args)
    args.ks = int_list(args.ks)
    return args


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    if args.child:
        child_memory(args.child)
        return
    t_start = time.perf_counter()
    out = Report("solver")
    out.add(
        f"# Differentiable solver and training step (torch {torch.__version__}, "
        f"{torch.get_num_threads()} torch threads, {os.cpu_count()} CPUs; {load_note()} at start)"
    )
    if not args.no_solver:
        out.add(*run_solver(args))
    if not args.no_train:
        if args.train_ks and args.train_batches:
            out.add(*train_step.run_train(args))
        if args.recipe_ks:
            out.add(*train_step.run_recipes(args))
    out.add(f"{load_note()} at end; total {time.perf_counter() - t_start:.0f} s.")
    out.save()


if __name__ == "__main__":
    main()
