"""The ``torchfmap`` command line's flags (:func:`build_parser`, :func:`check_outputs`) and :func:`main`;
the commands are in :mod:`torchfmap.cli.commands` and :mod:`torchfmap.cli.train`."""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import warnings
from collections.abc import Sequence

from .. import __version__
from .._util.files import check_file_name
from ..errors import TorchFmapError
from ..evaluate.scores import FULL_EVAL_VERTICES, SAMPLED_EVAL_POINTS
from ..fmap.defaults import DEFAULT_K
from ..kinds import KINDS, REFINE_METHODS
from .commands import cmd_basis, cmd_demo, cmd_eval, cmd_info, cmd_match
from .messages import error_line as _error_line
from .messages import in_cli_terms as in_cli_terms
from .messages import warning_line as _warning_line
from .train import cmd_models, cmd_train
from .types import count, nonnegative_float, point_count, positive_float, positive_int, time_list

DESCRIPTION = """torchfmap: functional maps with feature-aware bases.

  torchfmap demo                      match the shipped demo pair, print errors
  torchfmap info MESH                 validate a mesh, summarise its operators
  torchfmap basis MESH --out B.npz    compute and save a basis
  torchfmap match SRC TGT --out MAP   map target vertices to source vertices
  torchfmap eval FOLDER               match every pair with ground truth: table, PCK plot
  torchfmap train FOLDER --out CKPT   train a feature network, unsupervised
  torchfmap models                    list the pretrained models shipped in the package

Flags mean the same in every subcommand: --k is the basis size, --out the output file,
--landmarks 0-based vertex indices (match: a FILE of pairs; basis: a FILE of one column for a
mesh, two for a pair; eval: a FOLDER of <source>-<target>.txt pair files). Run
'torchfmap COMMAND --help'."""

BASES = list(KINDS)
LEARNED_BASES = [name for name, kind in KINDS.items() if kind.learned]


class _DefaultsFormatter(argparse.HelpFormatter):
    """Appends ``(default: X)`` to an option's help unless the help states it, the option is required
    or positional, or the default is None, False or suppressed."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        silent = (
            "default" in text
            or action.required
            or action.default is None
            or action.default is False
            or action.default == argparse.SUPPRESS
            or not action.option_strings
        )
        return text if silent else f"{text} (default: %(default)s)"


def _refine_flags(p: argparse.ArgumentParser) -> None:
    """The refinement and solver flags ``match`` and ``eval`` share."""
    p.add_argument("--refine", choices=list(REFINE_METHODS), help="refinement (default: none)")
    p.add_argument("--k-final", type=positive_int, help="eigenbasis ZoomOut target size (default: 2k)")
    p.add_argument(
        "--w-lap", type=nonnegative_float, help="Laplacian-commutativity weight (default: per basis)"
    )


def _checkpoint_flags(p: argparse.ArgumentParser, what: str) -> None:
    """The trained-network flags ``match`` and ``eval`` share."""
    p.add_argument(
        "--checkpoint",
        help=f"a network trained by 'torchfmap train' (a path, or a shipped name, see 'torchfmap "
        f"models'): {what}",
    )
    p.add_argument("--adapt", type=count, default=0, help="test-time adaptation steps (with --checkpoint)")
    p.add_argument(
        "--device",
        choices=["auto", "cpu", "cuda"],
        help="where the network, its solver and the point-map search run (with --checkpoint; default: "
        "auto, CUDA when available); operators and eigenbases stay on the CPU",
    )


QUIET = "no progress bar and no status lines (the results and errors still come)"
ALLOW_COMPONENTS = "accept meshes with several connected components"


def _sub(sub, name: str, help_text: str) -> argparse.ArgumentParser:
    return sub.add_parser(name, help=help_text, description=help_text, formatter_class=_DefaultsFormatter)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torchfmap", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--version", action="version", version=f"torchfmap {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    p = _sub(sub, "demo", "run on the demo pair shipped in the package")
    p.set_defaults(func=cmd_demo)
    p = _sub(sub, "models", "list the pretrained models shipped in the package, with their provenance")
    p.add_argument("--recipe", metavar="CKPT", help="print the recipe (JSON) of a checkpoint or shipped name")
    p.set_defaults(func=cmd_models)
    p = _sub(sub, "info", "validate a mesh and summarise its operators")
    p.add_argument("mesh", help="mesh file (.off/.ply/.obj/.stl, optionally .gz)")
    p.set_defaults(func=cmd_info)

    p = _sub(
        sub,
        "basis",
        "compute the basis of one mesh, or the corresponding bases of a pair (as match builds them), "
        "and save them as .npz (Basis.load reads them; match --bases solves in a pair)",
    )
    p.add_argument(
        "mesh",
        nargs="+",
        metavar="MESH",
        help="one mesh file (.off/.ply/.obj/.stl, optionally .gz), or SOURCE TARGET for a pair",
    )
    p.add_argument(
        "--basis",
        dest="kind",
        choices=BASES,
        help="basis kind (default: diffusion with --landmarks, else laplacian)",
    )
    p.add_argument("--k", type=positive_int, default=DEFAULT_K, help="basis size (exactly k columns)")
    p.add_argument("--allow-components", action="store_true", help=ALLOW_COMPONENTS)
    p.add_argument(
        "--landmarks",
        metavar="FILE",
        help="with one mesh: 0-based vertex indices, one per line (seeds of feature-aware kinds, "
        "placed first; farthest points fill the rest); with a pair: 0-based pairs 'source_vertex "
        "target_vertex', as for match (corresponding seeds on both meshes)",
    )
    p.add_argument(
        "--times",
        type=time_list,
        help="relative diffusion times of feature-aware kinds (default: one, matched to the seed count)",
    )
    p.add_argument("--laplacian", choices=["cotan", "robust", "mean_value"], default="cotan", help="operator")
    p.add_argument(
        "--out", required=True, nargs="+", metavar="OUT.npz", help="output .npz file, one per mesh"
    )
    p.add_argument("--quiet", action="store_true", help=QUIET)
    p.set_defaults(func=cmd_basis)

    p = _sub(sub, "match", "map a target mesh to a source mesh; write the target->source vertex map")
    p.add_argument("source", help="source mesh x (the map's values are its vertex indices)")
    p.add_argument("target", help="target mesh y (one map line per vertex)")
    p.add_argument(
        "--landmarks", metavar="FILE", help="0-based pairs 'source_vertex target_vertex', one per line"
    )
    p.add_argument(
        "--basis",
        choices=["auto", *BASES],
        help="basis kind (default: with --landmarks 'auto', the kind whose map distorts geodesic "
        "distances least, eigenbasis preferred; without, laplacian)",
    )
    p.add_argument(
        "--bases", nargs=2, metavar=("SRC.npz", "TGT.npz"), help="solve in saved bases ('torchfmap basis')"
    )
    p.add_argument("--partial", action="store_true", help="the target is a part of the source, same units")
    p.add_argument(
        "--k",
        type=positive_int,
        help=f"basis size, every basis has exactly k columns (default: {DEFAULT_K}; --checkpoint fixes "
        "its own)",
    )
    _refine_flags(p)
    p.add_argument(
        "--times",
        type=time_list,
        help="relative diffusion times of feature bases, e.g. 0.01,0.03 (default: one time matched to "
        "the seed count)",
    )
    p.add_argument(
        "--p2p-mode",
        choices=["pullback", "orthogonal"],
        help="point-map rule (default: orthogonal for laplacian and hybrid, else pullback)",
    )
    p.add_argument("--allow-components", action="store_true", help=ALLOW_COMPONENTS)
    p.add_argument("--out", required=True, help="map file: line i = source of target vertex i; -: stdout")
    p.add_argument("--png", help="also save a colour-transfer picture (needs matplotlib)")
    p.add_argument(
        "--html",
        help="also save the colour transfer as a self-contained page to turn in a browser (needs plotly)",
    )
    p.add_argument(
        "--up",
        choices=["x", "y", "z"],
        default="z",
        help="the meshes' vertical axis in --png and --html (not detected: y for y-up meshes such as "
        "FAUST; TOSCA is z-up)",
    )
    _checkpoint_flags(
        p,
        "match with it instead of the classical pipeline (its own basis and k; no --landmarks, --k, "
        "--basis, --bases, --w-lap, --times, --p2p-mode)",
    )
    p.add_argument("--quiet", action="store_true", help=QUIET)
    p.set_defaults(func=cmd_match)

    p = _sub(sub, "eval", "match every pair of a folder with ground truth; table + PCK plot")
    p.add_argument(
        "--partial", action="store_true", help="FOLDER is a partial collection: full/, partial/, corres/"
    )
    p.add_argument(
        "--map-base", type=int, choices=[0, 1], default=0, help="--partial: maps' first index (default 0)"
    )
    p.add_argument(
        "folder", help="folder of meshes (+ corres/*.vts and test_pairs.txt, or meshes of one template)"
    )
    p.add_argument(
        "--gt",
        choices=["files", "identity"],
        help="ground truth: corres/*.vts files only, or identity (vertex i is vertex i) for meshes "
        "of equal vertex counts (default: the files, else identity where the face lists agree)",
    )
    p.add_argument("--basis", choices=["auto", *BASES], help="basis kind (default: as in match)")
    p.add_argument("--k", type=positive_int, help=f"basis size (default: {DEFAULT_K})")
    _refine_flags(p)
    p.add_argument(
        "--landmarks",
        metavar="DIR",
        help="landmark pairs per pair: DIR/<source>-<target>.txt, 'source_vertex target_vertex' per "
        "line (instead of --gt-landmarks)",
    )
    p.add_argument(
        "--maps",
        metavar="DIR",
        help="score saved maps instead of matching: DIR/<source>-<target>.txt as written by "
        "'torchfmap match --out'",
    )
    p.add_argument(
        "--gt-landmarks",
        type=count,
        default=0,
        help="use N ground-truth pairs per pair as landmarks (0: none)",
    )
    pairs = "which pairs: test_pairs.txt else consecutive (auto); i -> i+1 by name; all ordered; a file"
    p.add_argument("--pairs", default="auto", metavar="auto|consecutive|all|FILE", help=pairs)
    p.add_argument("--max-pairs", type=count, default=0, help="at most this many pairs (0: all)")
    points = f"ground-truth points scored per pair: auto (all on source meshes of up to {FULL_EVAL_VERTICES} "
    points += f"vertices, a seeded random {SAMPLED_EVAL_POINTS} above: the table says so), all, or at most N"
    p.add_argument("--max-points", type=point_count, default="auto", metavar="auto|all|N", help=points)
    p.add_argument("--png", help="save the PCK curves here (needs matplotlib)")
    p.add_argument(
        "--out", metavar="FILE.npz", help="keep the scored pairs here as they finish; the same command "
        "with the same FILE resumes from them (after Ctrl-C, a lost worker, a full disk)",
    )  # fmt: skip
    p.add_argument(
        "--workers",
        type=positive_int,
        default=1,
        help="local processes (each mesh prepared once per process)",
    )
    p.add_argument(
        "--threads",
        type=positive_int,
        help="BLAS/torch threads per process (default: all CPUs / workers); equal --threads give "
        "identical results with any --workers",
    )
    p.add_argument("--dask", metavar="ADDRESS", help="run the pairs on a Dask cluster (e.g. tcp://host:8786)")
    _checkpoint_flags(
        p,
        "match with it instead of the classical pipeline (its own basis and k; no --landmarks, "
        "--gt-landmarks, --k, --basis, --w-lap); each mesh prepared once per worker",
    )
    p.add_argument("--quiet", action="store_true", help=QUIET)
    p.set_defaults(func=cmd_eval)

    p = _sub(sub, "train", "train a feature network, unsupervised, on every mesh of a folder")
    p.add_argument(
        "folder", help="meshes (.off/.ply/.obj/.stl, .gz); pairs within classes sharing a name prefix"
    )
    p.add_argument("--out", required=True, help="checkpoint (written atomically during training)")
    p.add_argument(
        "--config",
        metavar="RECIPE.json",
        help="the recipe (TrainConfig fields as JSON; `torchfmap models --recipe CKPT` prints a "
        "checkpoint's); flags given here override its values",
    )
    p.add_argument(
        "--device",
        choices=["auto", "cpu", "cuda"],
        default="auto",
        help="where the network, solver and loss run (auto: cuda when available; the precompute "
        "stays float64 on the CPU)",
    )
    p.add_argument(
        "--minutes",
        type=positive_float,
        help="time budget of the whole run; any of --minutes / --epochs / --max-steps given replaces "
        "the whole budget (of the recipe file, --init or --resume)",
    )
    p.add_argument(
        "--epochs", type=positive_int, help="epochs of all ordered pairs (default: 5 when no budget is given)"
    )
    p.add_argument("--max-steps", type=count, help="optimiser steps (default, or 0: no limit)")
    p.add_argument(
        "--basis", choices=LEARNED_BASES, help="basis kind of the learned map (default: laplacian)"
    )
    p.add_argument("--k", type=positive_int, help=f"functional-map basis size (default: {DEFAULT_K})")
    p.add_argument(
        "--pairs",
        choices=["classes", "all"],
        default="classes",
        help="training pairs: within classes of names (cat0, cat1; default) or all ordered pairs "
        "(species, data sets)",
    )
    p.add_argument(
        "--inputs",
        choices=["wks", "xyz", "wks+xyz", "shot"],
        help="per-vertex network inputs: WKS, coordinates, both, or SHOT (local, blind to rigid motions "
        "and scale: for parts turned any way; default: wks)",
    )
    p.add_argument(
        "--augment",
        choices=["rigid", "up", "scale", "none"],
        help="moves of XYZ inputs at each step: rotation and scaling, rotation about the y axis and "
        "scaling (shapes standing alike, facing anywhere), scaling only (shapes aligned alike), or "
        "none (default: rigid)",
    )
    p.add_argument(
        "--parts",
        type=count,
        metavar="N",
        help="train on parts, supervised: N cuts of every shape (plane and holes, 0.1-0.9 of the area), "
        "each matched to every shape, the ground truth from FOLDER/corres/<name>.vts (default: 0, "
        "unsupervised on whole shapes)",
    )
    p.add_argument("--n-wks", type=positive_int, help="WKS input channels (default: 32)")
    p.add_argument("--k-net", type=count, help="eigenfunctions of the network's diffusion (default: 96)")
    p.add_argument(
        "--clip-grad", type=nonnegative_float, help="gradient-norm clipping per step (default: 0: none)"
    )
    p.add_argument("--width", type=positive_int, help="network width (default: 48)")
    p.add_argument("--c-out", type=positive_int, help="feature channels (default: 64)")
    p.add_argument("--lr", type=positive_float, help="Adam learning rate (default: 1e-3)")
    p.add_argument("--seed", type=int, help="random seed (default: 0)")
    p.add_argument(
        "--threads",
        type=positive_int,
        help="BLAS/torch threads of the run (default: all CPUs); 1 leaves the other cores to other work",
    )
    p.add_argument("--cache", help="precompute cache folder (default: per-user cache)")
    p.add_argument("--no-cache", action="store_true", help="compute without a cache")
    p.add_argument("--resume", action="store_true", help="continue from --out if it exists")
    p.add_argument(
        "--init",
        metavar="CKPT",
        help="start from the (best) weights and recipe of a checkpoint or shipped model: fine-tuning "
        "(recipe flags given here override its recipe; the network must stay the same)",
    )
    p.add_argument("--validate-every", type=count, default=100, help="steps between validations (0: none)")
    p.add_argument("--validate-pairs", type=positive_int, default=6, help="pairs of the validation score")
    p.add_argument("--quiet", action="store_true", help=QUIET)
    p.set_defaults(func=cmd_train)
    return parser


def _as_list(value) -> list:
    return [] if not value else list(value) if isinstance(value, (list, tuple)) else [value]


def check_outputs(args: argparse.Namespace) -> None:
    """Raise :class:`TorchFmapError`, before any work, for output paths that cannot be written (no or
    read-only folder, a folder as the file, a name too long), ``--png`` / ``--html`` without their
    library."""
    values = [(flag, v) for flag in ("out", "png", "html") for v in _as_list(getattr(args, flag, None))]
    values = [(flag, v) for flag, v in values if not (flag == "out" and v == "-" and args.command == "match")]
    for flag, value in values:
        path = os.path.abspath(value)
        folder = os.path.dirname(path)
        if os.path.isdir(path):
            raise TorchFmapError(f"--{flag} {value!r} is a folder. Fix: give a file name inside it.")
        if not os.path.isdir(folder):
            raise TorchFmapError(f"--{flag} {value!r}: no folder {folder!r}. Fix: create it first.")
        if not os.access(folder, os.W_OK):
            raise TorchFmapError(
                f"--{flag} {value!r}: the folder {folder!r} is not writable. Fix: write elsewhere."
            )
        check_file_name(path)
    if getattr(args, "png", None) and importlib.util.find_spec("matplotlib") is None:
        raise TorchFmapError("--png needs matplotlib. Fix: pip install matplotlib (or the 'plot' extra).")
    if getattr(args, "html", None) and importlib.util.find_spec("plotly") is None:
        raise TorchFmapError("--html needs plotly. Fix: pip install plotly (or the 'html' extra).")


def main(argv: Sequence[str] | None = None) -> int:
    """The ``torchfmap`` command. Exit status: 0 done, 1 a file could not be read or written
    (the message says which and why), 2 bad input (named, with its fix), 130 interrupted
    (Ctrl-C), 141 the output pipe was closed (e.g. ``| head``). No traceback for any of these."""
    args = build_parser().parse_args(argv)
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _warning_line
            check_outputs(args)
            return args.func(args)
    except TorchFmapError as err:
        print(_error_line(err), file=sys.stderr)
        return 1 if isinstance(err, OSError) else 2
    except BrokenPipeError:
        # the reader went away (``| head``): /dev/null as stdout, so the final flush does not raise
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141
    except OSError as err:
        print(f"torchfmap: error: {err}. Fix: check the path and its permissions.", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("torchfmap: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
