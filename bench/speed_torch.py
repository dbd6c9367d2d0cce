"""Suite ``speed``, the torch side: the differentiable batched solve against a per-row loop, one
CPU training step split by phase, and the recipe's step on real meshes against the earlier ones.

Random inputs are built in float64 and cast, so both dtypes see the same numbers: per side a
``BasisBatch`` with ``values = sqrt(V) Q`` (``Q`` from the QR of a Gaussian ``(V, K)``, so
``valuesᵀ diag(mass) values = I`` with the uniform ``mass = 1/V``), ``lam`` sorted uniform in
``[0, 100]``, ``U`` orthogonal. ``torch.set_num_threads`` is left at its default unless
``threads`` is set: on a loaded machine every parallel op can wait for a descheduled worker
thread, which swamps small ops (compare with ``threads: 1``).
"""

from __future__ import annotations

import contextlib
import gc
import json
import resource
import statistics
import subprocess
import sys
import time
from typing import Any

import torch

from torchfmap.experimental.networks import FeatureNet
from torchfmap.nn import DiffusionNet, TrainConfig, UnsupervisedFMLoss, collate_shapes
from torchfmap.nn import functional as F
from torchfmap.nn.functional import BasisBatch, solve_fmap_batch
from torchfmap.nn.inputs import shape_arrays, shape_item

from .common import REPO_ROOT, MiB, Report, Settings, load1, log, reset_peak_rss, status_mib
from .pairs import Pair

DTYPES = {"float32": torch.float32, "float64": torch.float64}
W_DESC, W_LAP = 1.0, 1e-3


def random_basis(b: int, v: int, k: int, dtype: torch.dtype, gen: torch.Generator) -> BasisBatch:
    """B-orthonormal random basis (uniform mass ``1/V``) with a random spectral frame."""
    f64 = torch.float64
    q, _ = torch.linalg.qr(torch.randn(b, v, k, generator=gen, dtype=f64))
    u, _ = torch.linalg.qr(torch.randn(b, k, k, generator=gen, dtype=f64))
    lam = torch.sort(100.0 * torch.rand(b, k, generator=gen, dtype=f64), dim=-1).values
    parts = (q * v**0.5, torch.full((b, v), 1.0 / v, dtype=f64), lam, u, torch.ones(b, k, dtype=f64))
    return BasisBatch(*(t.to(dtype).contiguous() for t in parts))


def solver_inputs(b: int, v: int, k: int, d: int, dtype: torch.dtype, seed: int) -> dict[str, Any]:
    gen = torch.Generator().manual_seed(seed)
    bx, by = random_basis(b, v, k, dtype, gen), random_basis(b, v, k, dtype, gen)
    rand = lambda *shape: torch.randn(*shape, generator=gen, dtype=torch.float64).to(dtype)  # noqa: E731
    fx, fy = rand(b, v, d).requires_grad_(True), rand(b, v, d).requires_grad_(True)
    return {"fx": fx, "fy": fy, "bx": bx, "by": by, "r_xy": rand(b, k, k), "r_yx": rand(b, k, k)}


# -- (1) the solver against a per-row loop -----------------------------------------------------------
def loop_systems(A_x, A_y, lam_x, U_x, lam_y, U_y):
    """Rotated Gram matrix ``G (B, Kx, Kx)``, right-hand sides ``(B, Ky, Kx)`` and the mask
    ``(λ_x,j - λ_y,i)²`` normalised to mean 1 per batch item."""
    A_xr, A_yr = U_x.transpose(-1, -2) @ A_x, U_y.transpose(-1, -2) @ A_y
    m = (lam_x.clip(min=0)[:, None, :] - lam_y.clip(min=0)[:, :, None]) ** 2
    return (
        W_DESC * (A_xr @ A_xr.transpose(-1, -2)),
        W_DESC * (A_yr @ A_xr.transpose(-1, -2)),
        m / m.mean(dim=(-2, -1), keepdim=True),
    )


def loop_solve(fx, fy, bx: BasisBatch, by: BasisBatch):
    """``solve_fmap_batch``'s math (project, rotate by ``U``, masked rows), one ``(K, K)`` solve per row
    of every batch item in a Python loop, both directions."""
    A_x = bx.values.transpose(-1, -2) @ (bx.mass[..., None] * fx)
    A_y = by.values.transpose(-1, -2) @ (by.mass[..., None] * fy)

    def one(A_x, A_y, lx, Ux, ly, Uy):
        G, rhs, mask = loop_systems(A_x, A_y, lx, Ux, ly, Uy)
        C = [
            torch.stack(
                [
                    torch.linalg.solve(G[b] + W_LAP * torch.diag(mask[b, i]), rhs[b, i])
                    for i in range(rhs.shape[1])
                ]
            )
            for b in range(G.shape[0])
        ]
        return Uy @ torch.stack(C) @ Ux.transpose(-1, -2)

    return one(A_x, A_y, bx.lam, bx.U, by.lam, by.U), one(A_y, A_x, by.lam, by.U, bx.lam, bx.U)


METHODS = {
    "batched": lambda fx, fy, bx, by: solve_fmap_batch(fx, fy, bx, by, w_desc=W_DESC, w_lap=W_LAP, both=True),
    "loop": loop_solve,
}


def fwd_bwd(method: str, inp: dict) -> tuple[float, float, dict]:
    fx, fy = inp["fx"], inp["fy"]
    fx.grad = fy.grad = None
    t0 = time.perf_counter()
    C_xy, C_yx = METHODS[method](fx, fy, inp["bx"], inp["by"])
    total = (inp["r_xy"] * C_xy).sum() + (inp["r_yx"] * C_yx).sum()
    t1 = time.perf_counter()
    total.backward()
    t2 = time.perf_counter()
    return (
        t1 - t0,
        t2 - t1,
        {"C_xy": C_xy.detach(), "C_yx": C_yx.detach(), "gx": fx.grad.clone(), "gy": fy.grad.clone()},
    )


def child_memory(spec: str) -> None:
    """``python -m bench.speed_torch method,dtype,B,V,K,D,seed``: one fwd+bwd call in a fresh
    process; prints the resident peak above the start (MiB) as JSON."""
    method, dtype_name, *nums = spec.split(",")
    b, v, k, d, seed = (int(x) for x in nums)
    inp = solver_inputs(b, v, k, d, DTYPES[dtype_name], seed)
    gc.collect()
    ru_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    source = "VmHWM" if reset_peak_rss() else "ru_maxrss"
    rss_before = status_mib("VmRSS")
    fwd_bwd(method, inp)
    ru_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    peak = status_mib("VmHWM") - rss_before if source == "VmHWM" else ru_after - max(ru_before, rss_before)
    print(json.dumps({"peak": peak, "source": source}))


def _threads(cfg: Settings):
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    return f"{torch.get_num_threads()} torch threads"


def solver(cfg: Settings, report: Report) -> None:
    """The differentiable batched functional-map solve (solve_fmap_batch) against a per-row loop:
    forward + backward, both directions, agreement, conditioning, memory."""
    rows = []
    for dtype_name in cfg.dtypes:
        for k in cfg.ks:
            for order in (("batched", "loop"), ("loop", "batched")):  # the allocator state differs
                inp = solver_inputs(cfg.batch, cfg.v, k, cfg.d, DTYPES[dtype_name], cfg.seed)
                times: dict[str, list] = {m: [] for m in order}
                outs = {m: fwd_bwd(m, inp)[2] for m in order}  # warm-up
                for _ in range(cfg.repeats):
                    for m in order:
                        gc.collect()
                        f, bw, outs[m] = fwd_bwd(m, inp)
                        times[m].append((f, bw))
                ob, ol = outs["batched"], outs["loop"]
                diff = max(
                    (ob[c] - ol[c]).abs().max().item() / max(ol[c].abs().max().item(), 1e-300) for c in ob
                )
                with torch.no_grad():  # conditioning of the row systems of item 0, x -> y, in float64
                    bx, by = (BasisBatch(*(t[:1].double() for t in bb[:5])) for bb in (inp["bx"], inp["by"]))
                    A_x = bx.values.transpose(-1, -2) @ (bx.mass[..., None] * inp["fx"][:1].double())
                    A_y = by.values.transpose(-1, -2) @ (by.mass[..., None] * inp["fy"][:1].double())
                    G, _, mask = loop_systems(A_x, A_y, bx.lam, bx.U, by.lam, by.U)
                    cond = torch.linalg.cond(G[0][None] + W_LAP * torch.diag_embed(mask[0]))
                for m in order:
                    row = {
                        "dtype": dtype_name,
                        "B": cfg.batch,
                        "K": k,
                        "V": cfg.v,
                        "D": cfg.d,
                        "order": " then ".join(order),
                        "method": m,
                        "fwd [s]": statistics.median(t[0] for t in times[m]),
                        "bwd [s]": statistics.median(t[1] for t in times[m]),
                        "fwd+bwd [s]": statistics.median(sum(t) for t in times[m]),
                    }
                    rows.append(row)
                base = rows[-2] if rows[-2]["method"] == "batched" else rows[-1]
                for r in rows[-2:]:
                    r["t / batched"] = r["fwd+bwd [s]"] / base["fwd+bwd [s]"]
                    r |= {
                        "max rel. |Δ| (C, ∇f)": diff,
                        "cond median": cond.median().item(),
                        "cond max": cond.max().item(),
                        "system MiB": cfg.batch * k**3 * DTYPES[dtype_name].itemsize / MiB,
                        "load": load1(),
                    }
                    if cfg.memory and order == ("batched", "loop"):
                        spec = ",".join(
                            str(x) for x in (r["method"], dtype_name, cfg.batch, cfg.v, k, cfg.d, cfg.seed)
                        )
                        res = subprocess.run(
                            [sys.executable, "-m", "bench.speed_torch", spec],
                            cwd=REPO_ROOT,
                            capture_output=True,
                            text=True,
                            check=False,
                        )
                        got = (
                            json.loads(res.stdout.strip().splitlines()[-1])
                            if res.returncode == 0
                            else {"peak": float("nan")}
                        )
                        r["RSS peak MiB"] = got["peak"]
                log(
                    f"solver {dtype_name} K={k} {order[0]} first: loop / batched "
                    f"{rows[-1]['t / batched']:.2f}"
                )
    report.table(
        f"solve_fmap_batch against a per-row loop, median of {cfg.repeats} alternating rounds "
        f"({_threads(cfg)})",
        rows,
        note="rel |Δ|: max over C_xy, C_yx, ∇feat_x, ∇feat_y of max|Δ| / max|loop|. cond: row "
        "systems of item 0. "
        "system MiB: one (B, K, K, K) tensor per direction. RSS peak: one fwd+bwd call in a fresh process. "
        "Target: loop / batched >= 3.",
    )


class _Hooks:
    """Time at which the gradients of all given tensors are complete, per label."""

    def __init__(self) -> None:
        self.at: dict[str, float] = {}

    def watch(self, label: str, *tensors: torch.Tensor) -> None:
        left = [len(tensors)]

        def hook(grad):
            left[0] -= 1
            if left[0] == 0:
                self.at[label] = time.perf_counter()

        for t in tensors:
            t.register_hook(hook)


def train_step(cfg: Settings, report: Report) -> None:
    """One CPU training step (FeatureNet + solve_fmap_batch + UnsupervisedFMLoss + Adam), split by phase."""
    threads, rows = _threads(cfg), []
    for dtype_name in cfg.dtypes:
        for b in cfg.batches:
            for k in cfg.ks:
                dtype, gen = DTYPES[dtype_name], torch.Generator().manual_seed(cfg.seed)
                bx, by = random_basis(b, cfg.v, k, dtype, gen), random_basis(b, cfg.v, k, dtype, gen)
                xin, yin = (
                    torch.randn(b, cfg.v, 32, generator=gen, dtype=torch.float64).to(dtype) for _ in range(2)
                )
                torch.manual_seed(cfg.seed)
                net = FeatureNet(32, 64, width=64, n_blocks=3).to(dtype)
                loss_fn, opt = UnsupervisedFMLoss(), torch.optim.Adam(net.parameters(), lr=1e-3)
                steps = []
                for r in range(cfg.repeats + 1):  # the first is a warm-up  # noqa: B007
                    gc.collect()
                    opt.zero_grad(set_to_none=True)
                    hooks, t0 = _Hooks(), time.perf_counter()
                    fx, fy = net(xin, bx), net(yin, by)
                    t1 = time.perf_counter()
                    C_xy, C_yx = solve_fmap_batch(fx, fy, bx, by)
                    t2 = time.perf_counter()
                    total = loss_fn(C_xy, C_yx, fx, fy, bx, by)["total"]
                    t3 = time.perf_counter()
                    hooks.watch("loss", C_xy, C_yx)
                    hooks.watch("solver", fx, fy)
                    total.backward()
                    t4 = time.perf_counter()
                    opt.step()
                    t5 = time.perf_counter()
                    steps.append(
                        {
                            "net fwd": t1 - t0,
                            "solver fwd": t2 - t1,
                            "loss fwd": t3 - t2,
                            "loss bwd": hooks.at["loss"] - t3,
                            "solver bwd": hooks.at["solver"] - hooks.at["loss"],
                            "net bwd": t4 - hooks.at["solver"],
                            "adam": t5 - t4,
                            "step": t5 - t0,
                            "loss": total.item(),
                        }
                    )
                steps = steps[1:]
                row = {"dtype": dtype_name, "B": b, "K": k, "V": cfg.v}
                row |= {
                    f"{key} [s]": statistics.median(s[key] for s in steps)
                    for key in steps[0]
                    if key != "loss"
                }
                for part in ("net", "solver", "loss"):
                    row[f"{part} %"] = 100 * statistics.median(
                        (s[f"{part} fwd"] + s[f"{part} bwd"]) / s["step"] for s in steps
                    )
                row |= {"loss first→last": f"{steps[0]['loss']:.4g}→{steps[-1]['loss']:.4g}", "load": load1()}
                rows.append(row)
    report.table(
        f"Training step: FeatureNet(32 -> 64, width 64, 3 blocks) + solve_fmap_batch + UnsupervisedFMLoss "
        f"+ Adam; median of "
        f"{cfg.repeats} steps after a warm-up ({threads})",
        rows,
        note="Backward split by gradient hooks (loss bwd ends when the gradients of C are complete, "
        "solver bwd when "
        "those of the features are; approximate).",
    )


def _coo_spatial_gradient(f: torch.Tensor, grad, *, check=None):
    """The spatial gradient as the previous recipe applied it (a baseline kept here): a COO
    operator built and coalesced on every call, ``torch.sparse.mm``."""
    V, gx, gy = f.shape[1], [], []
    for b in range(f.shape[0]):
        rows, cols = grad.rows[b], grad.cols[b]
        index = torch.stack([torch.cat([rows, rows + V]), torch.cat([cols, cols])])
        weights = torch.cat([grad.weight_x[b], grad.weight_y[b]]).to(f.dtype)
        out = torch.sparse.mm(
            torch.sparse_coo_tensor(index, weights, (2 * V, V), check_invariants=False).coalesce(), f[b]
        )
        gx.append(out[:V])
        gy.append(out[V:])
    return torch.stack(gx), torch.stack(gy)


def train_recipe(cfg: Settings, report: Report) -> None:
    """The recipe's training step on a real pair against the previous recipe (COO gradients,
    4 blocks) and the first learned path (FeatureNet, full soft maps)."""
    from unittest import mock

    threads, pair, rows = _threads(cfg), Pair(cfg.pair), []
    for k in cfg.ks:
        shapes = [collate_shapes([shape_item(shape_arrays(m, k, 32, k_net=k))]) for m in (pair.x, pair.y)]
        (sx, sy), rc = shapes, TrainConfig()
        torch.manual_seed(cfg.seed)
        nets = {
            "recipe": DiffusionNet(32, rc.c_out, rc.width, rc.n_blocks, rc.dropout, rc.gradients),
            "previous": DiffusionNet(32, rc.c_out, 64, 4, rc.dropout, rc.gradients),
            "first": FeatureNet(32, 64, width=64, n_blocks=3),
        }
        losses = {key: UnsupervisedFMLoss(**rc.loss_weights) for key in nets} | {
            "first": UnsupervisedFMLoss()
        }
        opts = {key: torch.optim.Adam(net.parameters(), lr=1e-3) for key, net in nets.items()}
        draws = torch.Generator().manual_seed(cfg.seed)

        def step(key: str, nets=nets, sx=sx, sy=sy, losses=losses, opts=opts, draws=draws) -> float:
            net, t0 = nets[key], time.perf_counter()
            ax = (sx.inputs, sx.basis) if key == "first" else (sx.inputs, sx.net_basis, sx.grad)
            ay = (sy.inputs, sy.basis) if key == "first" else (sy.inputs, sy.net_basis, sy.grad)
            patch = mock.patch.object(F, "spatial_gradient", _coo_spatial_gradient)
            with patch if key == "previous" else contextlib.nullcontext():
                fx, fy = net(*ax), net(*ay)
                C_xy, C_yx = solve_fmap_batch(fx, fy, sx.basis, sy.basis)
                total = losses[key](C_xy, C_yx, fx, fy, sx.basis, sy.basis, generator=draws)["total"]
                opts[key].zero_grad(set_to_none=True)
                total.backward()
            opts[key].step()
            return time.perf_counter() - t0

        times: dict[str, list[float]] = {key: [] for key in nets}
        for key in times:
            step(key)  # warm-up
        for _ in range(cfg.repeats):
            for key in times:
                gc.collect()
                times[key].append(step(key))
        med = {key: statistics.median(t) for key, t in times.items()}
        for key in nets:
            rows.append(
                {
                    "K": k,
                    "V (x, y)": f"{pair.x.n_vertices}, {pair.y.n_vertices}",
                    "method": key,
                    "step [s]": med[key],
                    "t / recipe": med[key] / med["recipe"],
                    "load": load1(),
                }
            )
    report.table(
        f"Training step of the recipe (DiffusionNet width {TrainConfig().width}, "
        f"{TrainConfig().n_blocks} blocks) on "
        f"{pair.name}, float32; median of {cfg.repeats} alternating steps ({threads})",
        rows,
    )


CASES = {"solver": solver, "train_step": train_step, "train_recipe": train_recipe}

if __name__ == "__main__":
    child_memory(sys.argv[1])
