"""Ship a trained checkpoint as a pretrained model: ``torchfmap/nn/models/<name>.ckpt``.

Run by hand from the repository root, after ``torchfmap train`` and the validation bench::

    python -m tools.ship_model /tmp/humans.ckpt humans --command "torchfmap train ..." \\
        --data "FAUST_r 000..069 + SCAPE 000..040, ..." --validation "..." --use "..."

Given a shipped model instead, it re-documents it: the fields not given, the commit and the
training record are kept. The shipped file keeps the weights of the best validation score
(unsupervised, or the part error of a ``--parts`` run; what ``load_checkpoint`` returns), the
recipe's config, the network record and a ``provenance`` dict (command, data, commit, training,
validation, use) that ``torchfmap models`` prints; the training state (optimiser, loss history)
is left out. It is written atomically and read back.
"""

from __future__ import annotations

import argparse
import subprocess
from pathlib import Path

from torchfmap.nn.checkpoints import load_checkpoint, save_checkpoint
from torchfmap.nn.shipped import MODELS_DIR

REPO_ROOT = Path(__file__).resolve().parents[1]


FIELDS = ("command", "data", "validation", "use")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", help="a file written by torchfmap train, or a shipped model to re-document")
    p.add_argument("name", help="the shipped name (torchfmap match --checkpoint NAME)")
    for field in FIELDS:
        p.add_argument(f"--{field}", help="required unless the checkpoint's provenance has it (kept)")
    args = p.parse_args(argv)
    net, config, ckpt = load_checkpoint(args.checkpoint)
    state = ckpt.get("train_state") or {}
    old = ckpt.get("provenance") or {}
    given = {f: getattr(args, f) if getattr(args, f) is not None else old.get(f) for f in FIELDS}
    missing = [f"--{f}" for f, v in given.items() if v is None]
    if missing:
        p.error(f"{', '.join(missing)} required: {args.checkpoint} has no provenance to keep them from")
    if state:  # a training run: its own commit and figures
        git = ["git", "rev-parse", "--short", "HEAD"]
        run = subprocess.run(git, cwd=REPO_ROOT, capture_output=True, text=True, check=False)
        commit = run.stdout.strip()
        best = state.get("best_score")
        scored = "part error" if config.parts else "unsupervised"  # what the validation scored
        training = f"{state.get('step', '?')} steps, {state.get('seconds', 0):.0f} s" + (
            f"; weights of the best {scored} validation score {best:.4g}" if best is not None else ""
        )
    elif "training" in old and "commit" in old:  # a shipped model re-documented: its run's record
        commit, training = old["commit"], old["training"]
    else:
        p.error(f"{args.checkpoint} has neither a training state nor a shipped model's provenance")
    provenance = {
        "command": given["command"],
        "data": given["data"],
        "commit": commit,
        "training": training,
        "validation": given["validation"],
        "use": given["use"],
    }
    out = save_checkpoint(MODELS_DIR / f"{args.name}.ckpt", net, config, provenance=provenance)
    again, _, shipped = load_checkpoint(out)
    if shipped["provenance"] != provenance or type(again) is not type(net):
        raise SystemExit(f"{out} did not read back as written")
    print(f"shipped {out} ({out.stat().st_size / 1e6:.1f} MB)")


if __name__ == "__main__":
    main()
