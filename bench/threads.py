"""Benchmark: no configuration slower with all BLAS/torch threads than with one (issue 14).

Run by hand from the repository root (table to stdout and ``bench/results/threads.md``)::

    python3 bench/threads.py                 # cat0 of the dev data (the demo mesh without it)
    python3 bench/threads.py --repeats 1     # quick

Each workload runs in this process under ``threadpoolctl.threadpool_limits(1)`` (+
``torch.set_num_threads(1)``) and with the default thread counts, alternating, median of
``--repeats``; the ratio all / one is printed (> 1: threads make it slower). Workloads:
``diffusion_basis`` (50 seeds x 2 times, tol 1e-6), ``laplacian_eigenbasis`` (k = 100), the
default landmark ``match`` (7 landmarks, k = 60, refined) and the eigenbasis ``match``
(ZoomOut). Since the machine may be shared, the 1-minute load is recorded.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from _common import Report, data_path, load1, log, timed
from threadpoolctl import threadpool_info, threadpool_limits

import torchfmap
from torchfmap.data import demo_pair
from torchfmap.eval import gt_from_vts, landmarks_from_gt
from torchfmap.io import read_vts


def workloads(mesh_x, mesh_y, landmarks):
    seeds = torchfmap.farthest_point_sampling(mesh_x, 50, metric="euclidean")
    return {
        "diffusion_basis 50 x 2": lambda: torchfmap.diffusion_basis(mesh_x, seeds, [1e-3, 1e-2], tol=1e-6),
        "laplacian_eigenbasis k=100": lambda: torchfmap.laplacian_eigenbasis(mesh_x, 100),
        "match default (L=7), refined": lambda: torchfmap.match(
            mesh_x, mesh_y, landmarks=landmarks, k=60, refine="zoomout"
        ),
        "match laplacian, ZoomOut": lambda: torchfmap.match(
            mesh_x, mesh_y, basis="laplacian", k=60, refine="zoomout"
        ),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    folder = data_path("tosca5k_dev")
    if folder is not None:
        x, y = torchfmap.load_mesh(folder / "cat0.off"), torchfmap.load_mesh(folder / "cat1.off")
        gt = gt_from_vts(read_vts(folder / "corres/cat0.vts"), read_vts(folder / "corres/cat1.vts"))
    else:
        x, y, y_to_x = demo_pair()
        gt = torchfmap.eval.gt_from_map(y_to_x)
    landmarks = landmarks_from_gt(x, gt, 7)
    blas = sorted(
        {
            f"{i['internal_api']} ({i.get('threading_layer', '?')}, {i['num_threads']} threads)"
            for i in threadpool_info()
        }
    )
    report = Report("threads")
    report.add(
        f"# Threads: one vs all ({x.name}, V={x.n_vertices}; {', '.join(blas)}; "
        f"torch {torch.get_num_threads()} threads)"
    )
    rows = []
    default_torch = torch.get_num_threads()
    for name, fn in workloads(x, y, landmarks).items():
        times = {}
        for label in ("one", "all", "one", "all"):  # alternate: drift in load hits both
            if label == "one":
                with threadpool_limits(limits=1):
                    torch.set_num_threads(1)
                    t, _, _ = timed(fn, args.repeats)
                torch.set_num_threads(default_torch)
            else:
                t, _, _ = timed(fn, args.repeats)
            times.setdefault(label, []).append(t)
        one, all_ = float(np.min(times["one"])), float(np.min(times["all"]))
        log(f"  {name}: one thread {one:.3f} s, all threads {all_:.3f} s")
        rows.append(
            {
                "workload": name,
                "1 thread [s]": one,
                "all threads [s]": all_,
                "all / one": all_ / one,
                "load": load1(),
            }
        )
    report.table("Best of two alternating rounds (median of --repeats each)", rows)
    report.save()


if __name__ == "__main__":
    main()
