"""Command line: ``torchfmap demo | info | basis | match | eval | train`` (see ``torchfmap --help``)."""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import __version__
from ._checks import is_symmetric
from ._files import atomic_write
from .bases import Basis, basis_stack, eigenpairs
from .data import demo_pair
from .errors import TorchFmapError
from .eval import discover_pairs, evaluate_map, gt_from_map, landmarks_from_gt, pck_curve
from .io import load_mesh
from .operators import GeodesicSolver, available_backends, laplacian
from .pipeline import evaluate_pairs, match
from .seeds import farthest_point_sampling
from .viz import plot_color_transfer, plot_pck


def _operator_summary(mesh, out) -> None:
    rep = mesh.report
    out(
        f"{mesh.name or 'mesh'}: {rep.summary()}; area {mesh.area:.4g}, mean edge {mesh.mean_edge_length:.3g}"
    )
    for kind in ("cotan", "robust", "mean_value"):
        t0 = time.perf_counter()
        L, B = laplacian(mesh, kind=kind)
        dt = time.perf_counter() - t0
        sym = is_symmetric(L)
        neg = int((L.data[L.indices != np.repeat(np.arange(L.shape[0]), np.diff(L.indptr))] > 0).sum())
        out(
            f"  L[{kind:<10}] nnz {L.nnz:>7}  symmetric {str(sym):<5}  positive off-diagonals "
            f"(negative weights) {neg:>5}  mass sum {B.sum():.4g}  ({dt * 1e3:.1f} ms)"
        )
    L, B = laplacian(mesh)
    vals = eigenpairs(L, B, min(6, mesh.n_vertices))[0]
    out(
        "  first eigenvalues of L phi = lambda B phi (x area): "
        + ", ".join(f"{x:.3f}" for x in np.sort(vals) * mesh.area)
    )
    d = GeodesicSolver(mesh).distance(0)
    out(
        f"  largest geodesic distance from vertex 0: {d.max():.4g} "
        f"({d.max() / np.sqrt(mesh.area):.3f} sqrt(area)); solver backends: {available_backends()}"
    )


def cmd_demo(args: argparse.Namespace) -> int:
    a, b, gt_ba = demo_pair()
    print(f"torchfmap demo: match {b.name} to {a.name} (shipped pair, ground truth {len(gt_ba)} vertices)")
    for mesh in (a, b):
        _operator_summary(mesh, print)
    gt = gt_from_map(gt_ba)
    landmarks = landmarks_from_gt(a, gt, 8)
    print(f"\n{'basis':<10} {'refine':<8} {'K':>4} {'mean err':>9} {'median':>8} {'AUC':>6} {'time [s]':>9}")
    for basis, refine in (
        ("laplacian", None),
        ("laplacian", "zoomout"),
        ("diffusion", None),
        ("diffusion", "zoomout"),
    ):
        t0 = time.perf_counter()
        lm = landmarks if basis != "laplacian" else None
        result = match(a, b, landmarks=lm, basis=basis, k=40, refine=refine)
        dt = time.perf_counter() - t0
        report, _ = evaluate_map(a, b, result.p2p_yx, gt)
        print(
            f"{basis:<10} {refine or '-':<8} {result.basis_x.k:>4} {report.mean_error:>9.4f} "
            f"{report.median_error:>8.4f} {report.auc:>6.3f} {dt:>9.2f}"
        )
    print(
        "errors: geodesic distance to the true match / sqrt(area); 'diffusion' (the default with "
        "landmarks) uses 8 landmarks and heat kernels at corresponding seeds"
    )
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    mesh = load_mesh(args.mesh, allow_components=True)
    _operator_summary(mesh, print)
    return 0


def read_index_table(path: str, columns: int, what: str) -> np.ndarray:
    """``(N, columns)`` 0-based integer rows of a text file (``#`` comments, blank lines and a
    UTF-8 byte-order mark ignored), or a :class:`TorchFmapError` naming the file, line and fix.

    Refuses a missing or unreadable file, an empty one, a line with another number of columns
    (e.g. a pairs file where single indices are expected, or a third column), and anything
    that is not an integer.
    """
    try:
        with open(path, encoding="utf-8-sig") as fh:
            text = fh.read()
    except (OSError, UnicodeDecodeError) as err:
        raise TorchFmapError(f"cannot read the {what} file {path!r} ({err}). Fix: check the path.") from err
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        if len(fields) != columns:
            raise TorchFmapError(
                f"{path}:{number}: expected {columns} integer column(s) per line ({what}), got "
                f"{len(fields)}: {line.strip()!r}. Fix: one {what} entry per line."
            )
        try:
            rows.append([int(f) for f in fields])
        except ValueError as err:
            raise TorchFmapError(f"{path}:{number}: {what} must be integer vertex indices ({err}).") from err
    if not rows:
        raise TorchFmapError(f"the {what} file {path!r} holds no entries. Fix: one entry per line.")
    return np.array(rows, dtype=np.int64)


def read_landmarks(path: str) -> np.ndarray:
    """0-based vertex indices, one per line."""
    return read_index_table(path, 1, "landmark")[:, 0]


def cmd_basis(args: argparse.Namespace) -> int:
    mesh = load_mesh(args.mesh, allow_components=True)
    times = list(args.times)
    with tqdm(total=3, desc="basis", unit="step", disable=args.quiet) as bar:
        bar.set_postfix_str("operators")
        ops = laplacian(mesh, kind=args.laplacian)
        bar.update()
        landmarks = read_landmarks(args.landmarks) if args.landmarks else None
        n_seeds = args.seeds if args.seeds else (len(landmarks) if landmarks is not None else 0)
        seeds = np.zeros(0, dtype=np.int64)
        if args.kind != "laplacian":
            if n_seeds < 1:
                raise TorchFmapError("this kind needs seeds. Fix: pass --seeds N and/or --landmarks FILE.")
            bar.set_postfix_str("seeds")
            seeds = farthest_point_sampling(mesh, n_seeds, landmarks=landmarks, metric=args.metric)
        bar.update()
        bar.set_postfix_str(f"{args.kind} ({len(seeds)} seeds)")
        basis = basis_stack(
            mesh,
            seeds,
            times=times if args.kind in ("stack", "diffusion") else (),
            harmonic=args.kind in ("stack", "harmonic"),
            n_eigen=args.n_eigen if args.kind in ("stack", "laplacian") else 0,
            operators=ops,
            method=args.method,
            heat_tol=args.tol,
            orthonormalization=args.ortho if (args.kind == "stack" or args.orthonormalize) else None,
        )
        bar.update()
        path = basis.save(args.out)
    print(f"{basis} -> {path}")
    return 0


def read_landmark_pairs(path: str) -> np.ndarray:
    """``(L, 2)`` 0-based pairs ``source_vertex target_vertex``, one per line."""
    return read_index_table(path, 2, "landmark pair")


def cmd_match(args: argparse.Namespace) -> int:
    src = load_mesh(args.source, allow_components=args.allow_components)
    tgt = load_mesh(args.target, allow_components=args.allow_components)
    t0 = time.perf_counter()
    if args.checkpoint:
        if args.landmarks:
            raise TorchFmapError("--checkpoint matches without landmarks. Fix: drop --landmarks.")
        from .nn.train import load_checkpoint, match_with_network  # torch: only for this path

        net, config, _ = load_checkpoint(args.checkpoint)
        p2p = match_with_network(
            net, config, src, tgt, adapt_steps=args.adapt, refine=args.refine is not None
        )
        how = f"with {args.checkpoint} (adapt {args.adapt} steps, refine {args.refine or '-'}"
        return _write_map(args, src, tgt, p2p, f"{how}, {time.perf_counter() - t0:.2f} s)")
    if args.adapt:
        raise TorchFmapError("--adapt tunes a trained network. Fix: pass --checkpoint too.")
    landmarks = read_landmark_pairs(args.landmarks) if args.landmarks else None
    bases = tuple(Basis.load(path) for path in args.bases) if args.bases else None
    result = match(
        src,
        tgt,
        landmarks=landmarks,
        basis=args.basis,
        k=args.k,
        refine=args.refine,
        k_final=args.k_final,
        w_lap=args.w_lap,
        times=args.times,
        p2p_mode=args.p2p_mode,
        bases=bases,
    )
    how = f"(K={result.basis_x.k}, {sum(result.timings.values()):.2f} s)"
    return _write_map(args, src, tgt, result.p2p_yx, how)


def _write_map(args: argparse.Namespace, src, tgt, p2p: np.ndarray, how: str) -> int:
    """Write the map file atomically (line i: source vertex of target vertex i), report, and
    draw ``--png``."""
    atomic_write(args.out, lambda fh: np.savetxt(fh, p2p, fmt="%d"))
    print(f"matched {tgt.n_vertices} target vertices to {src.name} {how} -> {args.out}")
    if args.png:
        print(f"colour transfer -> {plot_color_transfer(src, tgt, p2p, args.png, up=args.up)}")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    import torch  # the learning path; the classical commands never import torch

    from .nn.data import PairDataset, ShapeDataset, class_pairs
    from .nn.train import CosineByTime, TrainConfig, build_model, load_checkpoint, train, unsupervised_score

    config = TrainConfig(
        k=args.k,
        basis=args.basis,
        inputs=args.inputs,
        epochs=args.epochs,
        minutes=args.minutes,
        seed=args.seed,
    )
    if args.resume and Path(args.out).exists():
        saved = load_checkpoint(args.out)[1]
        config = TrainConfig(**{**vars(saved), "epochs": args.epochs, "minutes": args.minutes})
    cache = False if args.no_cache else args.cache
    shapes = ShapeDataset(args.folder, cache, **config.dataset_kwargs(), progress=not args.quiet)
    pairs = class_pairs(shapes.names)
    net, solver, loss_fn = build_model(config)
    opt = torch.optim.Adam(net.parameters(), lr=config.lr)
    scheduler = None
    if args.minutes:
        scheduler = torch.optim.lr_scheduler.LambdaLR(opt, CosineByTime(args.minutes))
    print(
        f"training on {len(shapes)} meshes, {len(pairs)} ordered pairs ({config.basis} basis, K={config.k})"
    )
    # validation: the unsupervised loss (full soft maps) on a fixed spread of training pairs
    picked = pairs[:: max(1, len(pairs) // args.validate_pairs)][: args.validate_pairs]
    validate = unsupervised_score(shapes, picked, solver, loss_fn) if args.validate_every else None
    state = train(
        net,
        PairDataset(shapes, pairs),
        loss_fn,
        opt,
        solver=solver,
        scheduler=scheduler,
        epochs=args.epochs,
        minutes=args.minutes,
        max_steps=args.max_steps,
        augment=config.inputs == "xyz",
        validate=validate,
        validate_every=args.validate_every,
        checkpoint=args.out,
        config=config,
        resume=args.resume,
        seed=config.seed,
        progress=not args.quiet,
    )
    last = state.losses[-1]["total"] if state.losses else float("nan")
    best = f"; best validation score {state.best_score:.4g}" if state.scores else ""
    summary = f"{state.step} steps, {state.epoch} epochs, {state.seconds:.0f} s; last loss {last:.4g}"
    print(f"{summary}{best} -> {args.out}")
    return 0


def _dask_executor(address: str):
    """A ``concurrent.futures`` executor on the Dask cluster at ``address`` (the 'cluster' extra)."""
    try:
        from distributed import Client
    except ImportError as err:
        raise TorchFmapError("--dask needs Dask distributed. Fix: pip install 'torchfmap[cluster]'.") from err
    return Client(address).get_executor()


def cmd_eval(args: argparse.Namespace) -> int:
    pairs = list(discover_pairs(args.folder))[: args.max_pairs or None]
    results = evaluate_pairs(
        pairs,
        gt_landmarks=args.gt_landmarks,
        max_points=args.max_points,
        workers=args.workers,
        threads=args.threads,
        executor=_dask_executor(args.dask) if args.dask else None,
        progress=not args.quiet,
        basis=args.basis,
        k=args.k,
        refine=args.refine,
    )
    rows = [(r.source, r.target, r.report, r.seconds) for r in results]
    curves = {f"{r.source}-{r.target}": pck_curve(r.errors) for r in results}
    all_errors = [r.errors for r in results]
    print(
        "| source | target | mean err | median | AUC | coverage | time [s] |\n|---|---|---|---|---|---|---|"
    )
    for a, b, rep, dt in rows:
        print(
            f"| {a} | {b} | {rep.mean_error:.4f} | {rep.median_error:.4f} | {rep.auc:.3f} | "
            f"{rep.coverage:.3f} | {dt:.2f} |"
        )
    errors = np.concatenate(all_errors)
    print(f"| **all** | | {errors.mean():.4f} | {np.median(errors):.4f} | | | |")
    if args.png:
        curves = {"all pairs": pck_curve(errors), **(curves if len(curves) <= 8 else {})}
        title = f"{args.basis or 'auto'} basis, k={args.k}"
        print(f"PCK plot -> {plot_pck(curves, args.png, title=title)}")
    return 0


DESCRIPTION = """torchfmap: functional maps with feature-aware bases.

  torchfmap demo                      match the shipped demo pair, print errors
  torchfmap info MESH                 validate a mesh, summarise its operators
  torchfmap basis MESH --out B.npz    compute and save a basis
  torchfmap match SRC TGT --out MAP   map target vertices to source vertices
  torchfmap eval FOLDER               match every pair with ground truth: table, PCK plot
  torchfmap train FOLDER --out CKPT   train a feature network, unsupervised

Flags mean the same in every subcommand: --landmarks is always a FILE (0-based vertex
indices), --k the basis size, --out the output file. Run 'torchfmap COMMAND --help'."""

BASES = ["laplacian", "harmonic", "diffusion", "stack"]


def _sub(sub, name: str, help_text: str) -> argparse.ArgumentParser:
    return sub.add_parser(
        name, help=help_text, description=help_text, formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torchfmap", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--version", action="version", version=f"torchfmap {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    p = _sub(sub, "demo", "run on the demo pair shipped in the package")
    p.set_defaults(func=cmd_demo)
    p = _sub(sub, "info", "validate a mesh and summarise its operators")
    p.add_argument("mesh", help="mesh file (.off/.ply/.obj/.stl, optionally .gz)")
    p.set_defaults(func=cmd_info)

    p = _sub(sub, "basis", "compute a basis of one mesh and save it as .npz (Basis.load reads it)")
    p.add_argument("mesh", help="mesh file (.off/.ply/.obj/.stl, optionally .gz)")
    p.add_argument("--kind", choices=BASES, default="stack", help="basis kind")
    p.add_argument(
        "--seeds", type=count, default=0, help="number of seeds, landmarks included (0: landmarks only)"
    )
    p.add_argument("--landmarks", metavar="FILE", help="0-based vertex indices, one per line; seeded first")
    p.add_argument(
        "--times", type=time_list, default="0.001,0.003,0.01,0.03", help="relative diffusion times"
    )
    p.add_argument(
        "--n-eigen",
        type=count,
        default=50,
        help="Laplacian eigenfunctions (the laplacian kind; appended to stack)",
    )
    p.add_argument("--laplacian", choices=["cotan", "robust", "mean_value"], default="cotan", help="operator")
    p.add_argument(
        "--method",
        choices=["krylov", "rational", "backward_euler", "spectral"],
        default="krylov",
        help="heat solver",
    )
    p.add_argument("--tol", type=float, default=1e-8, help="heat kernel relative accuracy")
    p.add_argument(
        "--metric", choices=["geodesic", "euclidean"], default="geodesic", help="seed sampling distance"
    )
    p.add_argument("--ortho", choices=["mgs", "cholqr"], default="mgs", help="orthonormalisation scheme")
    p.add_argument("--orthonormalize", action="store_true", help="orthonormalise single kinds too")
    p.add_argument("--out", required=True, help="output .npz")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_basis)

    p = _sub(sub, "match", "map a target mesh to a source mesh; write the target->source vertex map")
    p.add_argument("source", help="source mesh x (the map's values are its vertex indices)")
    p.add_argument("target", help="target mesh y (one map line per vertex)")
    p.add_argument(
        "--landmarks", metavar="FILE", help="0-based pairs 'source_vertex target_vertex', one per line"
    )
    p.add_argument(
        "--basis",
        choices=BASES,
        default=None,
        help="basis kind (default: diffusion with landmarks, else laplacian)",
    )
    p.add_argument(
        "--bases", nargs=2, metavar=("SRC.npz", "TGT.npz"), help="solve in saved bases ('torchfmap basis')"
    )
    p.add_argument(
        "--k", type=positive_int, default=50, help="basis size (every basis has exactly k columns)"
    )
    p.add_argument("--refine", choices=["icp", "zoomout"], default=None, help="refinement (default: none)")
    p.add_argument(
        "--k-final", type=positive_int, default=None, help="eigenbasis ZoomOut target size (default 2k)"
    )
    p.add_argument(
        "--w-lap", type=float, default=None, help="Laplacian-commutativity weight (default: per basis)"
    )
    p.add_argument("--times", type=time_list, default=None, help="relative diffusion times of feature bases")
    p.add_argument(
        "--p2p-mode",
        choices=["pullback", "orthogonal"],
        default=None,
        help="point-map rule (default: orthogonal for laplacian, else pullback)",
    )
    p.add_argument(
        "--allow-components", action="store_true", help="accept meshes with several connected components"
    )
    p.add_argument("--out", required=True, help="output: line i = source vertex of target vertex i (0-based)")
    p.add_argument("--png", help="also save a colour-transfer picture (needs matplotlib)")
    p.add_argument("--up", choices=["x", "y", "z"], default="z", help="the meshes' vertical axis in --png")
    p.add_argument("--checkpoint", help="a network trained by 'torchfmap train': its features replace WKS")
    p.add_argument("--adapt", type=count, default=0, help="test-time adaptation steps (with --checkpoint)")
    p.set_defaults(func=cmd_match)

    p = _sub(sub, "eval", "match every pair of a folder with ground truth; table + PCK plot")
    p.add_argument("folder", help="folder of meshes (+ corres/*.vts and test_pairs.txt, or same-size meshes)")
    p.add_argument("--basis", choices=BASES, default=None, help="basis kind (default as in match)")
    p.add_argument("--k", type=positive_int, default=50, help="basis size")
    p.add_argument("--refine", choices=["icp", "zoomout"], default=None, help="refinement (default: none)")
    p.add_argument(
        "--gt-landmarks",
        type=count,
        default=0,
        help="use N ground-truth pairs per pair as landmarks (0: none)",
    )
    p.add_argument("--max-pairs", type=count, default=0, help="at most this many pairs (0: all)")
    p.add_argument(
        "--max-points",
        type=positive_int,
        default=None,
        help="evaluate at most this many points per pair (default: all)",
    )
    p.add_argument("--png", help="save the PCK curves here (needs matplotlib)")
    p.add_argument(
        "--workers",
        type=positive_int,
        default=1,
        help="local processes (each mesh prepared once per process)",
    )
    p.add_argument(
        "--threads",
        type=positive_int,
        default=None,
        help="BLAS/torch threads per process (default: all CPUs / workers); equal --threads give "
        "identical results with any --workers",
    )
    p.add_argument("--dask", metavar="ADDRESS", help="run the pairs on a Dask cluster (e.g. tcp://host:8786)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_eval)

    p = _sub(sub, "train", "train a feature network, unsupervised, on every mesh of a folder")
    p.add_argument(
        "folder", help="meshes (.off/.ply/.obj/.stl, .gz); pairs within classes sharing a name prefix"
    )
    p.add_argument("--out", required=True, help="checkpoint (written atomically during training)")
    p.add_argument("--minutes", type=float, default=0.0, help="time budget (0: --epochs only)")
    p.add_argument("--epochs", type=positive_int, default=1000, help="epochs (upper bound)")
    p.add_argument("--max-steps", type=count, default=0, help="steps (0: no limit)")
    p.add_argument(
        "--basis", choices=["laplacian", "diffusion", "stack"], default="laplacian", help="basis kind"
    )
    p.add_argument("--k", type=positive_int, default=50, help="functional-map basis size")
    p.add_argument("--inputs", choices=["wks", "xyz"], default="wks", help="per-vertex network inputs")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--cache", default=None, help="precompute cache folder (default: per-user cache)")
    p.add_argument("--no-cache", action="store_true", help="compute without a cache")
    p.add_argument("--resume", action="store_true", help="continue from --out if it exists")
    p.add_argument("--validate-every", type=count, default=100, help="steps between validations (0: none)")
    p.add_argument("--validate-pairs", type=positive_int, default=6, help="pairs of the validation score")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_train)
    return parser


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1 or str(value) != text.strip().lstrip("+"):
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return value


def count(text: str) -> int:
    """argparse type: an integer >= 0."""
    return 0 if text.strip() == "0" else positive_int(text)


def time_list(text: str) -> list[float]:
    """argparse type: comma-separated finite times > 0 (empty: none)."""
    if not text.strip():
        return []
    try:
        times = [float(t) for t in text.split(",")]
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"times must be comma-separated numbers, got {text!r}") from err
    if not all(np.isfinite(t) and t > 0 for t in times):
        raise argparse.ArgumentTypeError(f"times must be finite and > 0, got {text!r}")
    return times


def check_outputs(args: argparse.Namespace) -> None:
    """Refuse, before any work, output paths that cannot be written: a missing or read-only
    folder, an existing folder as the file; ``--png`` without matplotlib installed."""
    for flag in ("out", "png"):
        value = getattr(args, flag, None)
        if not value:
            continue
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
    if getattr(args, "png", None) and importlib.util.find_spec("matplotlib") is None:
        raise TorchFmapError("--png needs matplotlib. Fix: pip install matplotlib (or the 'plot' extra).")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        check_outputs(args)
        return args.func(args)
    except TorchFmapError as err:
        print(f"torchfmap: error: {type(err).__name__}: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
