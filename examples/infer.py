"""Match two meshes with a trained checkpoint (``torchfmap train`` or examples/train.py).

    python examples/infer.py model.ckpt SRC.off TGT.ply --out map.txt [--adapt 10] [--refine] [--png t.png]

No dataset folder and no cache: each mesh is prepared once in memory, as in training
(:class:`torchfmap.nn.LearnedMatcher`). Writes one line per target vertex: the 0-based index of
its source vertex (the ``torchfmap match`` format).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from torchfmap.io import load_mesh, write_map
from torchfmap.nn import LearnedMatcher


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("source", type=Path)
    parser.add_argument("target", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--adapt", type=int, default=0, help="test-time adaptation steps on this pair")
    parser.add_argument("--refine", action="store_true", help="ZoomOut in the eigenbases")
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto")
    parser.add_argument("--png", type=Path)
    args = parser.parse_args()
    matcher = LearnedMatcher.from_checkpoint(args.checkpoint, device=args.device, adapt_steps=args.adapt)
    src, tgt = load_mesh(args.source), load_mesh(args.target)
    p2p = matcher(src, tgt, refine="zoomout" if args.refine else None).p2p_yx
    write_map(args.out, p2p)
    print(f"{args.target.name} -> {args.source.name}: {len(p2p)} vertices -> {args.out}")
    if args.png:
        from torchfmap.viz import plot_color_transfer

        plot_color_transfer(src, tgt, p2p, args.png)


if __name__ == "__main__":
    main()
