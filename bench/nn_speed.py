"""Benchmark: point-map conversion, brute-force nearest neighbours at 50K x 50K, ours vs pyFM.

Run by hand from the repository root (prints a markdown table to stdout, progress to stderr, and
writes it to ``bench/results/nn_speed.md``)::

    python3 bench/nn_speed.py                             # 50K x 50K points in 100 dimensions
    python3 bench/nn_speed.py --nn-n 2000 --nn-dim 20     # quick check

(Part (b) of ``bench/match_speed.py``, which still runs it unless ``--no-nn``.)
``torchfmap.fmap.nearest_neighbor(query, reference, search='brute')`` with ``--nn-n`` x ``--nn-n``
points in ``--nn-dim`` dimensions (reference Gaussian, query a shuffled copy plus 1e-3 noise, so
the answer is known) for every ``block_bytes`` of ``--nn-blocks`` (32 MiB and 128 MiB): wall time
and peak resident memory (``VmHWM`` reset through ``/proc/self/clear_refs``) of one untraced
call, and the tracemalloc peak of a second call, against the size of the naive full ``(M, N)``
float64 distance matrix (not allocated). pyFM's brute-force ``knn_query`` (scikit-learn,
``working_memory`` 1024 MB) is timed the same way as the baseline; ``t / pyFM`` is the ratio.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import time
from collections.abc import Callable
from typing import Any

import numpy as np
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
    traced_peak_mib,
)

from torchfmap.fmap import nearest_neighbor

PYFM = "pyFM knn_query brute (sklearn)"


def _malloc_trim() -> None:
    """Give freed heap memory back to the OS (glibc), so that a call reusing it counts in RSS."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def timed_rss(fn: Callable[[], Any]) -> tuple[float, float, Any]:
    """Wall time of one call and its peak resident memory above the start (MiB; Linux, else nan).

    Freed heap memory is first given back to the OS (``malloc_trim``) and the high-water mark
    ``VmHWM`` reset, so the peak counts everything the call touches: numpy, BLAS buffers,
    scikit-learn's C++ buffers.
    """
    gc.collect()
    _malloc_trim()
    start = status_mib("VmRSS") if reset_peak_rss() else float("nan")
    t0 = time.perf_counter()
    out = fn()
    sec = time.perf_counter() - t0
    return sec, status_mib("VmHWM") - start, out


def cases(query, reference, blocks: list[int]) -> list[tuple[str, Callable[[], np.ndarray]]]:
    from pyFM.spectral.nearest_neighbor import knn_query

    out: list[tuple[str, Callable[[], np.ndarray]]] = [
        (
            f"ours block_bytes={mb} MiB",
            lambda mb=mb: nearest_neighbor(query, reference, search="brute", block_bytes=mb * MiB),
        )
        for mb in blocks
    ]
    out.append((PYFM, lambda: knn_query(reference, query, method="brute")))
    return out


def bench_nn(args) -> list[str]:
    """Runs every case; returns the report sections (title, table, note)."""
    n, d = args.nn_n, args.nn_dim
    rng = np.random.default_rng(args.seed)
    log(f"nearest neighbours: {n} x {n} in {d} dimensions")
    reference = rng.standard_normal((n, d))
    perm = rng.permutation(n)
    query = reference[perm] + 1e-3 * rng.standard_normal((n, d))
    naive = n * n * 8
    rows = []
    for name, fn in cases(query, reference, args.nn_blocks):
        log(f"  {name}: timed call (load {load1():.1f})")
        sec, rss, idx = timed_rss(fn)
        correct = float(np.mean(idx == perm))
        del idx
        log(f"  {name}: {sec:.1f} s; traced call")
        peak, _ = traced_peak_mib(fn)
        rows.append({"method": name, "M x N x D": f"{n:,} x {n:,} x {d}", "time [s]": sec})
        rows[-1] |= {"tracemalloc peak [MiB]": peak, "peak RSS [MiB]": rss, "RSS / naive": rss * MiB / naive}
        rows[-1] |= {"correct": correct, "load": load1()}
    t_pyfm = rows[-1]["time [s]"]
    for r in rows:
        r["t / pyFM"] = r["time [s]"] / t_pyfm
    return [
        f"## (b) p2p conversion: nearest neighbour of {n:,} queries among {n:,} points, {d} dims",
        markdown(rows),
        f"Naive full (M, N) float64 distance matrix: {naive / 2**30:.1f} GiB ({naive / 1e9:.1f} GB), "
        f"not allocated. Inputs: two {n * d * 8 / MiB:.0f} MiB arrays, not counted. tracemalloc peak: "
        "above the inputs during a second, traced call; it sees numpy allocations only (not BLAS "
        "buffers, not scikit-learn's C++ chunk buffers). peak RSS: resident-memory high-water mark "
        "(VmHWM, reset before the call) minus the resident memory at the start of the timed call: "
        "everything touched. correct = fraction of queries whose known nearest neighbour was found. "
        "t / pyFM: time over knn_query's time, same run.",
    ]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--nn-n", type=int, default=50000)
    parser.add_argument("--nn-dim", type=int, default=100)
    parser.add_argument("--nn-blocks", default="32,128", help="block_bytes in MiB, comma-separated")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_arguments(parser)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.nn_blocks = int_list(args.nn_blocks)
    out = Report("nn_speed")
    out.add(*bench_nn(args), f"{load_note()} at end.")
    out.save()


if __name__ == "__main__":
    main()
