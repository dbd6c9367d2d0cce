"""Benchmark: diffusion bases at small times, global vs local (``local='auto'``) kernels.

Run by hand from the repository root (prints a markdown table to stdout, progress to stderr, and
writes it to ``bench/results/heat_support.md``)::

    python3 bench/heat_support.py                         # 50K and 200K vertices
    python3 bench/heat_support.py --sizes 3000 --repeats 1   # quick check

(Formerly Table 3 of ``bench/bases.py``; ``--sizes`` was ``--small-time-sizes``.) Meshes,
operators and seeds: see ``bench/_bases.py``. After one warm-up of every operation on a
``--warmup-size`` mesh, per mesh size: ``diffusion_basis`` with 50 seeds x relative times 1e-5,
1e-4, krylov tol 1e-6, ``local=False`` (the baseline) and ``local='auto'``, median of
``--repeats`` calls (one call at or above ``--large`` vertices, or when the first call took longer
than ``--max-repeat-s``); ``speed-up`` is the ratio of the two medians, ``max rel. diff`` the
column-wise ``max|ΔK| / max|K_global|``, ``local support`` the mean fraction of vertices where the
local kernels are non-zero.
"""

from __future__ import annotations

import argparse
from typing import Any

from _bases import HEAT_TOL, N_SEEDS, SMALL_TIMES, diffusion, rel_diff, run_timed, setup, warm_up
from _common import Report, int_list, load_note, log, versions
from _meshes import mesh_name


def bench_small_times(n: int, args) -> dict[str, Any]:
    """One table row: times of global and local kernels, their ratio, difference and support."""
    name = mesh_name(n)
    reps = 1 if n >= args.large else args.repeats
    log(f"{name}: building mesh, laplacian, seeds")
    mesh, L, B, seeds = setup(n, args.seed)
    row: dict[str, Any] = {"mesh": name, "V": n, "t (rel.)": ", ".join(f"{t:g}" for t in SMALL_TIMES)}
    out = {}
    for local in (False, "auto"):
        log(f"{name}: small times krylov local={local}")
        fn = lambda local=local: diffusion(mesh, seeds, (L, B), SMALL_TIMES, local=local)  # noqa: E731
        row[f"local={local} [s]"], out[str(local)] = run_timed(f"local={local}", fn, reps, args.max_repeat_s)
    g, a = out["False"], out["auto"]
    if g is not None and a is not None:
        row["speed-up"] = row["local=False [s]"] / row["local=auto [s]"]
        row["max rel. diff"] = rel_diff(a.values, g.values)
        row["local support (mean % of V)"] = 100.0 * float((a.values != 0).mean())
    return row


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="50000,200000", help="comma-separated vertex counts")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (median)")
    parser.add_argument("--large", type=int, default=100_000, help="time only once from this size")
    parser.add_argument("--max-repeat-s", type=float, default=30.0, help="no repeats if a call takes longer")
    parser.add_argument("--warmup-size", type=int, default=1000, help="mesh size of the warm-up")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    warm_up(args.warmup_size, args.seed)
    rows = [bench_small_times(n, args) for n in int_list(args.sizes)]
    out = Report("heat_support")
    out.table(
        f"## Small times: diffusion_basis krylov tol {HEAT_TOL:g}, {N_SEEDS} seeds, local False/auto",
        rows,
        note=f"({versions('scipy')}; {load_note()} at end.) speed-up: local=False / local=auto, same run. "
        "'local support': mean over columns of the fraction of vertices where the local kernel is "
        "non-zero (its patch). 'max rel. diff': max over columns of max|ΔK| / max|K_global|.",
    )
    out.save()


if __name__ == "__main__":
    main()
