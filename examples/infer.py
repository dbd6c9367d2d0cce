"""Match a pair of meshes on the CPU with a trained checkpoint (see examples/train.py).

    python examples/infer.py examples/out/fmnet.ckpt SRC.off TGT.off --out map.txt [--png transfer.png]

Writes one line per target vertex: the 0-based index of its source vertex.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from torchfmap.nn.data import ShapeDataset
from torchfmap.nn.modules import RegularizedFMSolver
from torchfmap.nn.train import load_checkpoint, predict_p2p


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("source", type=Path)
    parser.add_argument("target", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--png", type=Path)
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "torchfmap-cache")
    args = parser.parse_args()
    net, config, _ = load_checkpoint(args.checkpoint)
    shapes = ShapeDataset(
        [args.source, args.target], args.cache, k=config.k, n_wks=config.n_wks, progress=False
    )
    p2p = predict_p2p(net, RegularizedFMSolver(w_lap=config.w_lap), shapes[0], shapes[1])
    np.savetxt(args.out, p2p, fmt="%d")
    print(f"{args.target.name} -> {args.source.name}: {len(p2p)} vertices -> {args.out}")
    if args.png:
        from torchfmap import load_mesh
        from torchfmap.viz import plot_color_transfer

        plot_color_transfer(load_mesh(args.source), load_mesh(args.target), p2p, args.png)


if __name__ == "__main__":
    main()
