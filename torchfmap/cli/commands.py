"""The ``torchfmap`` subcommands: one ``cmd_<name>(args) -> exit code`` per command of
:func:`torchfmap.cli.build_parser`; only ``--checkpoint`` paths import torch."""

from __future__ import annotations

import argparse
import functools
import itertools
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .._util.checks import is_symmetric
from .._util.files import output_lock
from .._util.progress import Steps
from ..bases import Basis, prepare_shape
from ..data import demo_pair
from ..errors import EvaluationInterrupted, TorchFmapError, WorkerLost
from ..evaluate.collection import LandmarkFiles, MapFiles, evaluate_pairs
from ..evaluate.partial import discover_partial_pairs
from ..evaluate.saved_pairs import SavedPairs
from ..evaluate.scores import (
    discover_pairs,
    evaluate_map,
    gt_from_map,
    landmarks_from_gt,
    pck_curve,
    select_pairs,
)
from ..fmap.defaults import DEFAULT_K
from ..io import load_mesh, read_landmark_pairs, read_landmarks, write_map
from ..kinds import get_kind
from ..matching.pipeline import match
from ..matching.solve import match_bases
from ..operators import GeodesicSolver, available_backends, laplacian
from ..operators.eigen import eigenpairs
from ..viz import plot_color_transfer, plot_pck, save_transfer_html


def _operator_summary(mesh, out) -> None:
    rep = mesh.report
    out(
        f"{mesh.name or 'mesh'}: {rep.summary()}; area {mesh.area:.4g}, mean edge {mesh.mean_edge_length:.3g}"
    )
    for scheme in ("cotan", "robust", "mean_value"):
        t0 = time.perf_counter()
        L, B = laplacian(mesh, scheme=scheme)
        dt = time.perf_counter() - t0
        sym = is_symmetric(L)
        neg = int((L.data[L.indices != np.repeat(np.arange(L.shape[0]), np.diff(L.indptr))] > 0).sum())
        out(
            f"  L[{scheme:<10}] nnz {L.nnz:>7}  symmetric {str(sym):<5}  positive off-diagonals "
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
    t0 = time.perf_counter()
    shapes = (prepare_shape(a, 100), prepare_shape(b, 100))
    print(f"\nboth shapes prepared once (operators, 100 eigenpairs): {time.perf_counter() - t0:.2f} s")
    rows = GeodesicSolver(a)
    print(f"{'basis':<10} {'refine':<8} {'K':>4} {'mean err':>9} {'median':>8} {'AUC':>6} {'time [s]':>9}")
    for basis, refine in itertools.product(("laplacian", "diffusion"), (None, "zoomout")):
        t0 = time.perf_counter()
        lm = landmarks if basis != "laplacian" else None
        result = match(a, b, landmarks=lm, basis=basis, k=40, refine=refine, shapes=shapes)
        dt = time.perf_counter() - t0
        report, _ = evaluate_map(a, b, result.p2p_yx, gt, solver=rows)
        print(
            f"{basis:<10} {refine or '-':<8} {result.basis_x.k:>4} {report.mean_error:>9.4f} "
            f"{report.median_error:>8.4f} {report.auc:>6.3f} {dt:>9.2f}"
        )
    print(
        "errors: geodesic distance to the true match / sqrt(area); 'diffusion' (feature-aware: "
        "basis='diffusion') uses 8 landmarks and heat kernels at corresponding seeds"
    )
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    mesh = load_mesh(args.mesh, allow_components=True)
    _operator_summary(mesh, print)
    if mesh.n_components > 1:
        print(
            f"note: {mesh.n_components} connected components; match and basis refuse such a mesh "
            "unless given --allow-components (every component then needs its own seeds)"
        )
    return 0


def cmd_basis(args: argparse.Namespace) -> int:
    meshes, outs = args.mesh, args.out
    if len(meshes) > 2:
        raise TorchFmapError(f"basis takes one mesh or a pair, got {len(meshes)} meshes. Fix: one or two.")
    if len(outs) != len(meshes):
        raise TorchFmapError(
            f"{len(meshes)} mesh{'es' if len(meshes) > 1 else ''} and {len(outs)} --out files. Fix: one "
            "--out file per mesh (--out src.npz tgt.npz for a pair)."
        )
    bad = [o for o in outs if not o.endswith(".npz")]
    if bad:
        raise TorchFmapError(
            f"--out {bad[0]!r}: a basis file is .npz (it would be written as {bad[0]}.npz). Fix: name "
            "it *.npz."
        )
    loaded = [load_mesh(m, allow_components=args.allow_components) for m in meshes]
    kind = get_kind(args.kind or ("diffusion" if args.landmarks else "laplacian"))
    pair = len(loaded) == 2
    read = read_landmark_pairs if pair else read_landmarks
    landmarks = read(args.landmarks) if args.landmarks else None
    if landmarks is not None and kind.n_eigen(args.k) >= args.k:  # no seeded column
        raise TorchFmapError(
            f"--landmarks are seeds, and the {kind.name} basis has none. Fix: drop --landmarks, or "
            "pick a feature-aware --basis (diffusion, harmonic, stack, hybrid)."
        )
    small = min(m.n_vertices for m in loaded)
    if args.k >= small:
        what = "meshes" if pair else "a mesh"
        raise TorchFmapError(f"--k {args.k} needs {what} of more than {args.k} vertices ({small}).")
    with tqdm(total=2, desc="basis", unit="step", disable=args.quiet) as bar:
        bar.set_postfix_str("operators")
        shapes = [prepare_shape(m, 0, laplacian=args.laplacian) for m in loaded]
        bar.update()
        bar.set_postfix_str(f"{kind.name}, k={args.k}")
        if pair:
            bases = list(match_bases(shapes[0], shapes[1], kind, args.k, landmarks, args.times)[:2])
        else:
            bases = [kind.shape_basis(shapes[0], args.k, seeds=landmarks, times=args.times)]
        bar.update()
        paths = [b.save(o) for b, o in zip(bases, outs, strict=True)]
    for b, path in zip(bases, paths, strict=True):
        if not args.quiet:
            print(f"{kind.name} {b} -> {path}")
    return 0


#: Flags a checkpoint fixes, refused with ``--checkpoint``.
CHECKPOINT_FIXES = ("k", "basis", "bases", "w_lap", "times", "p2p_mode")


def _learned_matcher(args: argparse.Namespace):
    """The :class:`~torchfmap.nn.LearnedMatcher` of ``--checkpoint`` (None without it) after checking
    the flags ``match`` and ``eval`` share; :class:`TorchFmapError` for conflicting ones."""
    if not args.checkpoint:
        for flag, value in (("--adapt", args.adapt), ("--device", args.device)):
            if value:
                raise TorchFmapError(
                    f"{flag} is a setting of a trained network. Fix: pass --checkpoint too (the "
                    "classical pipeline runs on the CPU and is not trained)."
                )
        return None
    if getattr(args, "partial", False) and args.adapt:
        raise TorchFmapError(
            "--adapt tunes the network by the whole-shape loss, which a part breaks. Fix: drop --adapt "
            "with --partial."
        )
    fixed = [f"--{n.replace('_', '-')}" for n in CHECKPOINT_FIXES if getattr(args, n, None) is not None]
    if fixed:
        raise TorchFmapError(
            f"--checkpoint matches in the network's own basis with its own settings, so "
            f"{', '.join(fixed)} would change nothing. Fix: drop {' / '.join(fixed)} (or drop "
            "--checkpoint for the classical pipeline)."
        )
    given = (("--landmarks", args.landmarks), ("--gt-landmarks", getattr(args, "gt_landmarks", 0)))
    landmarks = [flag for flag, value in given if value]
    if landmarks:
        raise TorchFmapError(
            f"--checkpoint matches without landmarks, so {' / '.join(landmarks)} would not be used. Fix: "
            f"drop {' / '.join(landmarks)}, or drop --checkpoint: the classical pipeline takes them "
            "(torchfmap match --landmarks)."
        )
    if args.refine not in (None, "zoomout"):
        raise TorchFmapError("--checkpoint refines by ZoomOut only. Fix: --refine zoomout (or no --refine).")
    if args.k_final is not None and args.refine != "zoomout":
        raise TorchFmapError(
            "--k-final is the size ZoomOut grows to; without --refine zoomout it changes nothing. "
            "Fix: --refine zoomout, or drop --k-final."
        )
    from ..nn import LearnedMatcher

    device = args.device or "auto"
    return LearnedMatcher.from_checkpoint(args.checkpoint, device=device, adapt_steps=args.adapt)


def _learned_how(matcher, args: argparse.Namespace, grown: int | None = None) -> str:
    """What a learned match ran, in words; ``grown``: the size ZoomOut reached (default: as asked)."""
    refine = "-"
    if args.refine:
        k = matcher.config.k
        refine = f"zoomout {k} -> {grown or args.k_final or 2 * k}"
    return f"{args.checkpoint} (adapt {args.adapt} steps, refine {refine}, device {matcher.device})"


def cmd_match(args: argparse.Namespace) -> int:
    with Steps("match", enabled=not args.quiet) as steps:
        steps("reading the meshes")
        src = load_mesh(args.source, allow_components=args.allow_components)
        tgt = load_mesh(args.target, allow_components=args.allow_components)
    matcher = _learned_matcher(args)
    if matcher is not None:
        result = matcher(src, tgt, refine=args.refine, k_final=args.k_final, partial=args.partial)
        how = _learned_how(matcher, args, result.basis_x.k)
        if result.overlap is not None:
            how += f", partial: {_partial_how(result)}"
        return _write_map(args, src, tgt, result.p2p_yx, f"with {how}, {sum(result.timings.values()):.2f} s")
    landmarks = read_landmark_pairs(args.landmarks) if args.landmarks else None
    bases = tuple(Basis.load(path) for path in args.bases) if args.bases else None
    result = match(
        src,
        tgt,
        landmarks=landmarks,
        basis=args.basis,
        k=DEFAULT_K if args.k is None else args.k,
        refine=args.refine,
        k_final=args.k_final,
        w_lap=args.w_lap,
        times=args.times,
        p2p_mode=args.p2p_mode,
        bases=bases,
        partial=args.partial,
        progress=not args.quiet,
    )
    refined = ""
    if args.refine:
        refined = f", refined by {args.refine}" if result.refined else f", {args.refine} dropped"
        if result.refine_check is not None:
            refined += f" ({result.refine_check})"
    chose = ""
    if result.candidates:
        judge = "geodesic distortion and held-out landmarks" if result.fold_scores else "geodesic distortion"
        chose = f"chosen by {judge} ({result.scores()} sqrt(area)), "
    if result.overlap is not None:
        chose = f"{_partial_how(result)}, "
    seconds = sum(result.timings.values())
    how = f"({result.kind} basis, {chose}{_sizes(args, result)}{refined}, {seconds:.2f} s)"
    return _write_map(args, src, tgt, result.p2p_yx, how)


def _sizes(args: argparse.Namespace, result) -> str:
    """The basis size, and where ZoomOut grew it from."""
    start, final = DEFAULT_K if args.k is None else args.k, result.C_xy.shape[1]
    if result.refined and args.refine == "zoomout" and final != start:
        return f"k {start} -> {final} (ZoomOut grows k to --k-final, default 2k)"
    return f"k {final}"


def _partial_how(result) -> str:
    """A partial map's rank and estimated overlap, in words."""
    share = float((result.overlap > 0.5).mean())
    return (
        f"rank {result.partial_rank} of the whole's {result.C_xy.shape[1]} eigenfunctions (the part's share "
        f"of them, about k times the area ratio), overlap {share:.0%} of the source's vertices"
    )


def _write_map(args: argparse.Namespace, src, tgt, p2p: np.ndarray, how: str) -> int:
    """Write the map (``--out -``: stdout, status on stderr), report, and draw ``--png`` / ``--html``."""
    to_stdout = args.out == "-"
    if to_stdout:
        sys.stdout.write("".join(f"{int(i)}\n" for i in p2p))
        sys.stdout.flush()
    else:
        write_map(args.out, p2p)
    quiet = getattr(args, "quiet", False)
    say = (lambda *_: None) if quiet else functools.partial(print, file=sys.stderr if to_stdout else None)
    where = "stdout" if to_stdout else args.out
    say(f"matched {tgt.n_vertices} target vertices to {src.name} {how} -> {where}")
    if args.png:
        say(f"colour transfer -> {plot_color_transfer(src, tgt, p2p, args.png, up=args.up)}")
    if args.html:
        say(f"colour transfer (browser page) -> {save_transfer_html(src, tgt, p2p, args.html, up=args.up)}")
    return 0


def _dask_executor(address: str):
    """A ``concurrent.futures`` executor on the Dask cluster at ``address`` (the 'cluster' extra)."""
    try:
        from distributed import Client
    except ImportError as err:
        raise TorchFmapError("--dask needs Dask distributed. Fix: pip install 'torchfmap[cluster]'.") from err
    return Client(address).get_executor()


def _eval_method(args: argparse.Namespace) -> tuple[dict, str]:
    """``evaluate_pairs`` settings of ``torchfmap eval`` and the plot's title."""
    if args.landmarks and args.gt_landmarks:
        raise TorchFmapError("--landmarks and --gt-landmarks both give landmarks. Fix: pass one of them.")
    if args.maps:
        matching = (args.checkpoint, args.gt_landmarks, args.landmarks, args.basis, args.refine, args.adapt)
        if any(matching) or args.device:
            raise TorchFmapError(
                "--maps scores saved maps, so it takes no matching options. Fix: drop --checkpoint, "
                "--gt-landmarks, --landmarks, --basis, --refine, --adapt and --device (or drop --maps "
                "to match here)."
            )
        return {"matcher": MapFiles(args.maps)}, f"saved maps in {args.maps}"
    matcher = _learned_matcher(args)
    if matcher is not None:
        settings = {"matcher": matcher, "refine": args.refine, "k_final": args.k_final}
        if args.partial:
            settings["partial"] = True
        return settings, _learned_how(matcher, args) + (", partial" if args.partial else "")
    k = DEFAULT_K if args.k is None else args.k
    settings = dict(
        gt_landmarks=LandmarkFiles(args.landmarks) if args.landmarks else args.gt_landmarks,
        basis=args.basis,
        k=k,
        refine=args.refine,
        k_final=args.k_final,
        w_lap=args.w_lap,
        **({"partial": True} if args.partial else {}),
    )
    lm = f", {args.gt_landmarks} ground-truth landmarks" if args.gt_landmarks else ""
    lm += f", landmarks from {args.landmarks}" if args.landmarks else ""
    basis = args.basis or ("auto" if lm else "laplacian")
    basis = "partial" if args.partial else basis
    return settings, f"{basis} basis, k={k}, refine {args.refine or '-'}{lm}"


def cmd_eval(args: argparse.Namespace) -> int:
    """``torchfmap eval``; with ``--out``, under :func:`~torchfmap._util.files.output_lock`."""
    if not args.out:
        return _eval(args)
    with output_lock(args.out, "--out"):
        return _eval(args)


def _eval(args: argparse.Namespace) -> int:
    settings, title = _eval_method(args)
    identity = {None: None, "identity": True, "files": False}[args.gt]
    folder = Path(args.folder).resolve()  # workers of a cluster may run in another folder
    if args.partial:
        if args.pairs != "auto" or args.gt:
            raise TorchFmapError(
                "--partial pairs each part with its whole by the collection's layout, so --pairs and --gt "
                "do not apply. Fix: drop them."
            )
        pairs = list(discover_partial_pairs(folder, args.map_base))[: args.max_pairs or None]
        protocol = (
            f"{len(pairs)} parts of {folder / 'partial'} against their wholes (maps {args.map_base}-based); "
            "errors over the part's vertices with ground truth; IoU: estimated overlap v > 0.5 against "
            "the true part on the whole, area-weighted"
        )
    else:
        _, protocol = select_pairs(folder, args.pairs)  # refuses a bad --pairs first
        pairs = list(discover_pairs(folder, identity, args.pairs))[: args.max_pairs or None]
    if args.max_pairs and len(pairs) == args.max_pairs:
        protocol += f", the first {len(pairs)} (--max-pairs)"
    saved = None
    if args.out:  # what changes a pair's score
        scored_by = {"folder": folder, "method": title, "k_final": args.k_final, "w_lap": args.w_lap,
                     "gt": args.gt, "partial": args.partial, "map_base": args.map_base,
                     "max_points": args.max_points}  # fmt: skip
        saved = SavedPairs(args.out, scored_by)
        todo = [p for p in pairs if (p[0], p[1]) not in saved.done]
        if len(todo) < len(pairs) and not args.quiet:
            print(
                f"resuming: {len(pairs) - len(todo)} of {len(pairs)} pairs read from {args.out}",
                file=sys.stderr,
            )
        pairs, all_pairs = todo, pairs
    try:
        results = pairs and evaluate_pairs(  # nothing to score when every pair was kept
            pairs,
            max_points=args.max_points,
            workers=args.workers,
            threads=args.threads,
            executor=_dask_executor(args.dask) if args.dask else None,
            progress=not args.quiet,
            on_results=None if saved is None else saved.add,
            **settings,
        )
    except (EvaluationInterrupted, WorkerLost) as stop:
        finished = stop.finished if saved is None else saved.in_order(all_pairs)
        why = "Ctrl-C" if isinstance(stop, EvaluationInterrupted) else "a worker died"
        if finished:
            _print_table(finished, title, f"{protocol}; {stop} ({why})", None)
        kept = ""
        if saved is not None:
            saved.flush()
            if saved.done and Path(args.out).exists():
                kept = f"; the finished pairs are in {args.out}: the same command resumes"
        print(f"torchfmap: {stop} ({why}){kept}", file=sys.stderr)
        return 130 if isinstance(stop, EvaluationInterrupted) else 1
    finally:
        if saved is not None:
            saved.flush()
    if saved is not None:
        results = saved.in_order(all_pairs)
    _print_table(results, title, protocol, args.png)
    return 0


def _print_table(results, title: str, protocol: str, png) -> None:
    """The ``eval`` table of ``results``, its footer and, with ``png``, the PCK plot."""
    partial = any(r.iou is not None for r in results)
    print(
        "| source | target | mean err | median | AUC | coverage | time [s] |" + (" IoU |" if partial else "")
    )
    print("|---|---|---|---|---|---|---|" + ("---|" if partial else ""))
    sampled = [r for r in results if 0 < r.report.n_points < r.report.n_total]
    for r in results:
        rep = r.report
        iou = f" {r.iou:.3f} |" if partial else ""
        mean = f"{rep.mean_error:.4f}" + (f" ± {rep.mean_error_se:.4f}" if rep.mean_error_se else "")
        print(
            f"| {r.source} | {r.target} | {mean} | {rep.median_error:.4f} | {rep.auc:.3f} | "
            f"{rep.coverage:.3f} | {r.seconds:.2f} |{iou}"
        )
    errors = np.concatenate([r.errors for r in results])
    mean_iou = f" {np.mean([r.iou for r in results]):.3f} |" if partial else ""
    print(f"| **all** | | {errors.mean():.4f} | {np.median(errors):.4f} | | | |{mean_iou}")
    print(
        f"\n{title}. Pairs: {protocol}. Errors: geodesic distance on the source to the true match "
        "/ sqrt(area); AUC: area under the PCK curve up to 0.25; coverage: fraction of source "
        "vertices the map reaches; time: matching only (preparing shapes and scoring excluded)."
    )
    if sampled:
        print(
            f"Points: {len(sampled)} of {len(results)} pairs scored on a seeded random sample, e.g. "
            f"{sampled[0].report.sampling()}: mean err ± its standard error (--max-points all: every point)."
        )
    if png:
        curves = {f"{r.source}-{r.target}": pck_curve(r.errors) for r in results}
        curves = {"all pairs": pck_curve(errors), **(curves if len(curves) <= 8 else {})}
        print(f"PCK plot -> {plot_pck(curves, png, title=title)}")
