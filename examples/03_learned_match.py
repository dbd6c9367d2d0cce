"""Match two meshes with a trained network: ``torchfmap.nn.LearnedMatcher``.

The matcher is called like ``torchfmap.match`` and returns the same ``MatchResult``
(``p2p_yx[i]``: the vertex of ``x`` for vertex ``i`` of ``y``). It runs on the shipped model
``faust_r`` (trained on FAUST humans) by default, or on a checkpoint written by ``torchfmap
train`` / ``examples/04_train.py`` (``--model PATH``). Each mesh is prepared once
(``prepare_shape``) and the prepared shapes serve both calls, the raw network map and the
ZoomOut one; the result's ``timings`` say where the time went. No download, no dataset folder,
no cache::

    python examples/03_learned_match.py                                   # the demo pair
    python examples/03_learned_match.py X.off Y.ply --model model.ckpt --device cuda --out map.txt
    python examples/03_learned_match.py --adapt 5 --png transfer.png      # test-time adaptation

On the demo pair (blobs, not humans) the raw map is rough and ZoomOut does most of the work;
on humans the raw map is already close (README, "Pretrained model").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torchfmap as tf
from torchfmap.data import demo_pair_paths
from torchfmap.errors import TorchFmapError
from torchfmap.evaluate.scores import evaluate_map, gt_from_map
from torchfmap.io import read_map, write_map
from torchfmap.nn import LearnedMatcher
from torchfmap.operators import DistanceRows
from torchfmap.viz import plot_color_transfer


def main(argv: list[str] | None = None) -> dict:
    """Run the example; returns ``{'errors': {'raw', 'zoomout'}, 'timings': {...}, 'out': path
    or None}`` (errors only with a ground truth)."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("x", nargs="?", type=Path, help="source mesh (default: the demo's blob_a)")
    parser.add_argument("y", nargs="?", type=Path, help="target mesh (default: the demo's blob_b)")
    parser.add_argument("--model", default="faust_r", help="a shipped model's name or a checkpoint path")
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto (CUDA where there is one)")
    parser.add_argument("--adapt", type=int, default=0, help="test-time adaptation steps on the pair")
    parser.add_argument("--gt", type=Path, help="the true map y -> x (demo: its shipped map)")
    parser.add_argument("--out", type=Path, help="write the ZoomOut map here")
    parser.add_argument("--png", type=Path, help="colour transfer picture (matplotlib)")
    args = parser.parse_args(argv)

    demo_x, demo_y, demo_gt = demo_pair_paths()
    x, y = tf.load_mesh(args.x or demo_x), tf.load_mesh(args.y or demo_y)
    gt_file = args.gt or (demo_gt if args.x is None else None)

    matcher = LearnedMatcher.from_checkpoint(args.model, device=args.device, adapt_steps=args.adapt)
    print(matcher)  # the model's basis kind and size k, the device
    shapes = (tf.prepare_shape(x, 0), tf.prepare_shape(y, 0))  # grown in place as the calls need
    results = {
        "raw": matcher(x, y, shapes=shapes),  # the network's features -> C_xy -> point map
        "zoomout": matcher(x, y, refine="zoomout", shapes=shapes),  # eigenbases k -> 2k
    }
    for label, result in results.items():
        timings = ", ".join(f"{name} {t:.2f}" for name, t in result.timings.items())
        print(f"{label:<8} C_xy {result.C_xy.shape}, p2p_yx {result.p2p_yx.shape}; seconds: {timings}")

    errors = {}
    if gt_file:
        gt, rows = gt_from_map(read_map(gt_file)), DistanceRows(x)
        for label, result in results.items():
            report, _ = evaluate_map(x, y, result.p2p_yx, gt, solver=rows)
            errors[label] = report.mean_error
            print(f"{label:<8} mean geodesic error {report.mean_error:.4f} (units of sqrt(area))")
    out = write_map(args.out, results["zoomout"].p2p_yx) if args.out else None
    if out:
        print(f"wrote {out}")
    if args.png:
        try:
            print(f"wrote {plot_color_transfer(x, y, results['zoomout'].p2p_yx, args.png)}")
        except TorchFmapError as err:  # no matplotlib: the message names the install
            print(f"no picture: {err}")
    timings = {label: result.timings for label, result in results.items()}
    return {"errors": errors, "timings": timings, "out": out}


if __name__ == "__main__":
    main()
