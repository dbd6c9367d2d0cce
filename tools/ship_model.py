"""Ship a trained checkpoint as a pretrained model: ``torchfmap/nn/models/<name>.ckpt``.

Run by hand from the repository root, after ``torchfmap train`` and the validation bench::

    python -m tools.ship_model /tmp/humans.ckpt humans --command "torchfmap train ..." \\
        --data "FAUST_r 000..069 + SCAPE 000..040, ..." --validation "..." --use "..."

The shipped file keeps the weights of the best unsupervised validation score (what
``load_checkpoint`` returns), the recipe's config, the network record and a ``provenance``
dict (command, data, commit, training, validation, use) that ``torchfmap models`` prints; the
training state (optimiser, loss history) is left out. It is written atomically and read back.
"""

from __future__ import annotations

import argparse
import subprocess
from pathlib import Path

from torchfmap.nn.checkpoints import load_checkpoint, save_checkpoint
from torchfmap.nn.shipped import MODELS_DIR

REPO_ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", help="a file written by torchfmap train")
    p.add_argument("name", help="the shipped name (torchfmap match --checkpoint NAME)")
    for field in ("command", "data", "validation", "use"):
        p.add_argument(f"--{field}", required=True)
    args = p.parse_args()
    net, config, ckpt = load_checkpoint(args.checkpoint)
    state = ckpt.get("train_state") or {}
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, check=False
    ).stdout.strip()
    best = state.get("best_score")
    provenance = {
        "command": args.command,
        "data": args.data,
        "commit": commit,
        "training": f"{state.get('step', '?')} steps, {state.get('seconds', 0):.0f} s"
        + (f"; weights of the best unsupervised validation score {best:.4g}" if best is not None else ""),
        "validation": args.validation,
        "use": args.use,
    }
    out = save_checkpoint(MODELS_DIR / f"{args.name}.ckpt", net, config, provenance=provenance)
    again, _, shipped = load_checkpoint(out)
    if shipped["provenance"] != provenance or type(again) is not type(net):
        raise SystemExit(f"{out} did not read back as written")
    print(f"shipped {out} ({out.stat().st_size / 1e6:.1f} MB)")


if __name__ == "__main__":
    main()
