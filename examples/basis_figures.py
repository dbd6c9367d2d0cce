"""Reproduce Figs. 3 and 4 of the feature-aware bases paper on a real mesh.

Fig. 3 -- support size of the diffusion functions versus the number of seeds, at six relative
diffusion scales ``t = 10^-i`` (``i = 1..6``; absolute time ``t * |M|``). The support of a
function is the percentage of vertices where ``|f| > eps * max|f|``. Left panel: the input heat
kernels; right panel: the same functions after B-orthonormalising the stack of all scales,
ordered from small to large ``t`` (the support of each orthonormalised column is reported at the
scale of the input column it comes from, read from ``basis.columns[i].time``).

Fig. 4 -- numerical rank of the stack (number of columns kept by the orthonormalisation) and
number of dropped columns versus the number of seeds, for the diffusion stack (six scales), the
harmonic functions, and the diffusion + harmonic stack; a third panel breaks the diffusion stack
down by scale (columns kept in the stack, and numerical rank of each scale on its own).

Seeds are chosen once by farthest-point sampling for the largest count; by the FPS prefix
property the seeds for a smaller count are the first ones of that run.

Run from the repository root::

    python examples/basis_figures.py            # default mesh: ../shared/data/tosca5k_dev/cat0.off
    python examples/basis_figures.py --mesh my.off --out figs/ --seeds 5,10,20,40 --eps 1e-3

It prints the numbers as tables and writes ``fig3_support.png``, ``fig4_rank.png`` and
``basis_figures.csv`` to ``--out`` (default ``examples/out/``). If the default mesh is absent, it
falls back to the demo mesh shipped with the package.
"""

from __future__ import annotations

import argparse
import csv
import time
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: must be set before pyplot is imported

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

import torchfmap  # noqa: E402
from torchfmap.bases import Basis, concatenate, orthonormalize, support_fraction  # noqa: E402
from torchfmap.data import demo_pair_paths  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MESH = REPO_ROOT.parent / "shared" / "data" / "tosca5k_dev" / "cat0.off"
DEFAULT_OUT = REPO_ROOT / "examples" / "out"
#: Relative diffusion times ``10^-1 .. 10^-6`` (the paper's six scales).
TIMES: tuple[float, ...] = tuple(10.0**-i for i in range(1, 7))


@dataclass
class SupportStats:
    """Support percentages of the columns at one scale: mean, min, max and count."""

    mean: float
    lo: float
    hi: float
    n: int

    @classmethod
    def of(cls, fractions: np.ndarray) -> SupportStats:
        if fractions.size == 0:
            return cls(float("nan"), float("nan"), float("nan"), 0)
        pct = 100.0 * fractions
        return cls(float(pct.mean()), float(pct.min()), float(pct.max()), int(pct.size))


@dataclass
class SeedResult:
    """Everything measured for one number of seeds."""

    n_seeds: int
    support_input: dict[float, SupportStats] = field(default_factory=dict)
    support_ortho: dict[float, SupportStats] = field(default_factory=dict)
    rank: dict[str, int] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)
    n_input: dict[str, int] = field(default_factory=dict)
    rank_alone: dict[float, int] = field(default_factory=dict)  # rank of one scale's kernels alone
    seconds: float = 0.0


STACKS = ("diffusion", "harmonic", "diffusion+harmonic")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mesh", type=Path, default=None, help=f"mesh file (default {DEFAULT_MESH})")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder for the PNGs and CSV")
    p.add_argument("--seeds", type=str, default="5,10,20,40,80,160", help="comma-separated seed counts")
    p.add_argument("--eps", type=float, default=1e-3, help="support threshold: |f| > eps * max|f|")
    p.add_argument("--metric", choices=("geodesic", "euclidean"), default="geodesic", help="FPS metric")
    p.add_argument("--heat-tol", type=float, default=1e-6, help="accuracy of the heat kernels")
    return p.parse_args(argv)


def resolve_mesh(path: Path | None) -> Path:
    """The mesh to use: ``path``, else the default mesh, else the shipped demo mesh."""
    if path is not None:
        return path
    if DEFAULT_MESH.exists():
        return DEFAULT_MESH
    fallback = demo_pair_paths()[0]
    print(f"note: default mesh {DEFAULT_MESH} not found; using the shipped demo mesh {fallback}")
    return fallback


def per_scale_support(basis: Basis, eps: float) -> dict[float, SupportStats]:
    """Support statistics of ``basis``' kept diffusion columns, grouped by their relative time."""
    fractions = support_fraction(basis.values, eps)
    times = np.array([np.nan if c.time is None else c.time for c in basis.columns])
    return {t: SupportStats.of(fractions[np.isclose(times, t, rtol=1e-9, atol=0.0)]) for t in TIMES}


def measure(mesh: torchfmap.Mesh, ops, seeds: np.ndarray, eps: float, heat_tol: float) -> SeedResult:
    """Build the diffusion and harmonic bases for ``seeds``, orthonormalise, and measure."""
    start = time.perf_counter()
    res = SeedResult(n_seeds=len(seeds))
    diffusion = torchfmap.diffusion_basis(mesh, seeds, times=TIMES, operators=ops, tol=heat_tol, local="auto")
    harmonic = torchfmap.harmonic_basis(mesh, seeds, operators=ops)
    stacks = {
        "diffusion": diffusion,  # time-major: small t first, the paper's order
        "harmonic": harmonic,
        "diffusion+harmonic": concatenate([diffusion, harmonic]),
    }
    ortho = {name: orthonormalize(basis, scheme="mgs") for name, basis in stacks.items()}
    res.support_input = per_scale_support(diffusion, eps)
    res.support_ortho = per_scale_support(ortho["diffusion"], eps)
    for name in STACKS:
        res.rank[name] = ortho[name].k
        res.dropped[name] = len(ortho[name].dropped)
        res.n_input[name] = stacks[name].k
    times = np.array([c.time for c in diffusion.columns])
    for t in TIMES:
        block = diffusion.values[:, np.isclose(times, t, rtol=1e-9, atol=0.0)]
        res.rank_alone[t] = orthonormalize(Basis(block, diffusion.mass), scheme="mgs").k
    res.seconds = time.perf_counter() - start
    return res


def print_tables(results: list[SeedResult]) -> None:
    """Support (mean % [min, max]) per scale and the rank of every stack, as plain-text tables."""
    for title, attr in (
        ("input diffusion functions", "support_input"),
        ("orthonormalised functions", "support_ortho"),
    ):
        print(f"\nFig. 3 -- mean support % [min-max] of the {title}, per relative time t")
        print(f"{'seeds':>6} " + " ".join(f"{f't={t:.0e}':>22}" for t in TIMES))
        for r in results:
            stats: dict[float, SupportStats] = getattr(r, attr)
            cells = []
            for t in TIMES:
                s = stats[t]
                cells.append(
                    f"{'-':>22}" if s.n == 0 else f"{s.mean:7.2f} [{s.lo:5.2f}-{s.hi:6.2f}]".rjust(22)
                )
            print(f"{r.n_seeds:>6} " + " ".join(cells))
    print(
        "\nFig. 4c -- per scale: columns kept in the orthonormalised diffusion stack / rank of the "
        "scale alone"
    )
    print(f"{'seeds':>6} " + " ".join(f"{f't={t:.0e}':>11}" for t in TIMES))
    for r in results:
        print(
            f"{r.n_seeds:>6} " + " ".join(f"{r.support_ortho[t].n:>5} / {r.rank_alone[t]:<3}" for t in TIMES)
        )
    print("\nFig. 4 -- numerical rank (kept / input columns, dropped) of each stack")
    print(f"{'seeds':>6} " + " ".join(f"{name:>24}" for name in STACKS) + f" {'time [s]':>9}")
    for r in results:
        cells = [f"{r.rank[n]:>5} / {r.n_input[n]:<5} ({r.dropped[n]:>3} dropped)" for n in STACKS]
        print(f"{r.n_seeds:>6} " + " ".join(f"{c:>24}" for c in cells) + f" {r.seconds:>9.1f}")


def write_csv(results: list[SeedResult], path: Path) -> None:
    """One row per (seed count, quantity) for later re-plotting."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["n_seeds", "quantity", "stack_or_time", "value", "min", "max", "n_columns"])
        for r in results:
            for attr in ("support_input", "support_ortho"):
                for t, s in getattr(r, attr).items():
                    w.writerow([r.n_seeds, f"{attr}_pct", f"{t:g}", s.mean, s.lo, s.hi, s.n])
            for n in STACKS:
                w.writerow([r.n_seeds, "rank", n, r.rank[n], "", "", r.n_input[n]])
                w.writerow([r.n_seeds, "dropped", n, r.dropped[n], "", "", r.n_input[n]])
            for t in TIMES:
                w.writerow([r.n_seeds, "kept_in_stack", f"{t:g}", r.support_ortho[t].n, "", "", r.n_seeds])
                w.writerow([r.n_seeds, "rank_alone", f"{t:g}", r.rank_alone[t], "", "", r.n_seeds])


def _seed_axis(ax: plt.Axes, counts: list[int]) -> None:
    ax.set_xscale("log", base=2)
    ax.set_xticks(counts)
    ax.set_xticklabels([str(c) for c in counts])
    ax.minorticks_off()
    ax.set_xlabel("number of seeds")
    ax.grid(True, which="major", alpha=0.3)


def _time_label(t: float) -> str:
    return f"t = 1e{int(round(np.log10(t)))}"


def plot_support(results: list[SeedResult], path: Path, mesh_name: str, eps: float) -> None:
    """Fig. 3: mean support (band: min-max) per scale, input vs orthonormalised."""
    counts = [r.n_seeds for r in results]
    colors = plt.cm.viridis(np.linspace(0.0, 0.9, len(TIMES)))
    fig, axes = plt.subplots(1, 2, figsize=(13, 5), sharey=True, layout="constrained")
    panels = (("support_input", "input diffusion functions"), ("support_ortho", "after B-orthonormalisation"))
    for ax, (attr, title) in zip(axes, panels, strict=True):
        for t, color in zip(TIMES, colors, strict=True):
            stats = [getattr(r, attr)[t] for r in results]
            ax.fill_between(
                counts, [s.lo for s in stats], [s.hi for s in stats], color=color, alpha=0.12, lw=0
            )
            ax.plot(counts, [s.mean for s in stats], "o-", color=color, label=_time_label(t))
        _seed_axis(ax, counts)
        ax.set_yscale("log")
        ax.set_title(title)
    axes[0].set_ylabel(f"support size [% of vertices with |f| > {eps:g} max|f|]")
    axes[1].tick_params(labelleft=True)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, title="relative time t", loc="outside right center")
    fig.suptitle(
        f"Fig. 3 -- support of the diffusion functions vs number of seeds ({mesh_name}; line: mean over "
        "the functions of a scale, band: min-max)"
    )
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_rank(results: list[SeedResult], path: Path, mesh_name: str) -> None:
    """Fig. 4: numerical rank (dashed: input column count), dropped columns, per-scale breakdown."""
    counts = [r.n_seeds for r in results]
    styles = {
        "diffusion": dict(color="C0", marker="o", lw=4, ms=9, alpha=0.5),
        "harmonic": dict(color="C1", marker="s", lw=1.5, ms=6),
        "diffusion+harmonic": dict(color="C2", marker="^", lw=1.5, ms=6),
    }
    fig, (ax_rank, ax_drop, ax_scale) = plt.subplots(1, 3, figsize=(18, 5.2), layout="constrained")
    for name in STACKS:
        style = styles[name]
        ax_rank.plot(counts, [r.rank[name] for r in results], label=f"{name}: rank", **style)
        ax_rank.plot(
            counts,
            [r.n_input[name] for r in results],
            ls="--",
            color=style["color"],
            lw=1,
            label=f"{name}: # input columns",
        )
        ax_drop.plot(counts, [r.dropped[name] for r in results], label=name, **style)
    ax_rank.set_xscale("log", base=2)
    ax_rank.set_yscale("log")
    ax_rank.set_ylabel("number of columns")
    ax_rank.set_title("(a) numerical rank = columns kept by orthonormalisation")
    ax_rank.legend(fontsize=8, loc="upper left")
    ax_drop.set_ylabel("number of dropped (dependent) columns")
    ax_drop.set_title("(b) columns dropped as numerically dependent")
    ax_drop.legend(fontsize=9, loc="upper left")

    # (c) the diffusion stack per scale: columns kept in the stack and rank of the scale on its own
    colors = dict(zip(TIMES, plt.cm.viridis(np.linspace(0.0, 0.9, len(TIMES))), strict=True))
    full = [
        t
        for t in TIMES
        if all(r.support_ortho[t].n == r.n_seeds and r.rank_alone[t] == r.n_seeds for r in results)
    ]
    ax_scale.plot(counts, counts, "-", color="0.5", lw=4, alpha=0.5, label="number of seeds S")
    for t in TIMES:
        if t in full:
            continue
        kept = [r.support_ortho[t].n for r in results]
        alone = [r.rank_alone[t] for r in results]
        ax_scale.plot(counts, kept, "o-", color=colors[t], label=f"{_time_label(t)}: kept in the stack")
        ax_scale.plot(
            counts, alone, "x:", color=colors[t], ms=8, label=f"{_time_label(t)}: rank of the scale alone"
        )
        for x, y in zip(counts, alone, strict=True):
            ax_scale.annotate(
                str(y), (x, y), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=8
            )
        ax_scale.annotate(
            str(kept[-1]),
            (counts[-1], kept[-1]),
            textcoords="offset points",
            xytext=(-10, -3),
            ha="right",
            fontsize=8,
            color=colors[t],
        )
    if full:
        span = (
            _time_label(full[0])
            if len(full) == 1
            else f"{_time_label(full[0])} .. 1e{int(round(np.log10(full[-1])))}"
        )
        ax_scale.plot([], [], " ", label=f"({span}: all S kept, on the grey line)")
    ax_scale.set_yscale("symlog", linthresh=1)  # columns kept can be 0: a log axis would hide them
    ax_scale.set_ylabel("number of columns of one scale")
    ax_scale.set_title("(c) diffusion stack per scale (small t is orthonormalised first)")
    ax_scale.legend(fontsize=8, loc="upper left")
    for ax in (ax_rank, ax_drop, ax_scale):
        _seed_axis(ax, counts)
    fig.suptitle(
        f"Fig. 4 -- numerical rank vs number of seeds ({mesh_name}; diffusion: 6 scales t = 1e-1 .. 1e-6, "
        "orthonormalised by MGS, tol 1e-8)"
    )
    fig.savefig(path, dpi=130)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    counts = sorted({int(s) for s in args.seeds.split(",") if s.strip()})
    mesh_path = resolve_mesh(args.mesh)
    args.out.mkdir(parents=True, exist_ok=True)

    start = time.perf_counter()
    mesh = torchfmap.load_mesh(mesh_path)
    ops = torchfmap.laplacian(mesh)
    all_seeds = np.asarray(torchfmap.farthest_point_sampling(mesh, max(counts), metric=args.metric))
    print(f"mesh {mesh_path} ({mesh.n_vertices} vertices, area {mesh.area:.4g})")
    print(f"seed counts {counts} ({args.metric} FPS), eps {args.eps:g}, relative times {list(TIMES)}")

    results = [
        measure(mesh, ops, all_seeds[:k], args.eps, args.heat_tol) for k in tqdm(counts, desc="seed counts")
    ]

    print_tables(results)
    fig3, fig4, table = (
        args.out / "fig3_support.png",
        args.out / "fig4_rank.png",
        args.out / "basis_figures.csv",
    )
    plot_support(results, fig3, mesh_path.stem, args.eps)
    plot_rank(results, fig4, mesh_path.stem)
    write_csv(results, table)
    print(f"\nwrote {fig3}\nwrote {fig4}\nwrote {table}\ntotal {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
