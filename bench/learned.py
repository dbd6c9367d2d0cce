"""Suite ``learned``: trained checkpoints on validation pairs (before / after training, point-map
rules, ZoomOut, test-time adaptation), where a recipe converges, adaptation's steps x learning
rate, the self-seeded second stage, the learned path on dense meshes, and every model under a
random rotation and scale (``invariance``).

Pairs come from ``bench/pairs.py`` (``sets``: name -> pair specs, ``@faust_val`` etc.; files are
read through :class:`torchfmap.nn.ShapeDataset` with the checkpoint's recipe, ``cache``: a
folder, null for the per-user cache, false for none). Errors: mean normalised geodesic error
x100 at ``max_points`` ground-truth points per pair, averaged over pairs; ground truth is read
for the errors only. Checkpoints: ``label=path`` or a shipped model's name (``torchfmap
models``); null for every shipped model.
"""

from __future__ import annotations

import glob
import multiprocessing
import resource
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import torch
import trimesh

from torchfmap import Mesh, prepare_shape
from torchfmap.bases.prepared import with_eigenpairs
from torchfmap.data import demo_pair_paths
from torchfmap.evaluate.ground_truth import vts_ground_truth
from torchfmap.evaluate.scores import geodesic_errors
from torchfmap.experimental.stages import StageTwo, StageTwoLoss, two_stage_p2p
from torchfmap.fmap import p2p_to_fmap
from torchfmap.io import load_mesh
from torchfmap.kinds import get_kind
from torchfmap.nn import (
    LearnedMatcher,
    ShapeDataset,
    TrainConfig,
    Trainer,
    adapt,
    build_model,
    build_solver,
    collate_pairs,
    load_checkpoint,
    predict_p2p,
    shipped_models,
    unsupervised_score,
)
from torchfmap.nn.coarse import COARSE_VERTICES
from torchfmap.nn.data import class_pairs
from torchfmap.nn.train import pair_loss
from torchfmap.operators.geodesic import GeodesicSolver

from . import common
from .common import Report, Settings, Skip, log, nanmean
from .pairs import Pair, expand


class PairSet:
    """The pairs of some specs as items of one :class:`ShapeDataset` (each file once), with
    their :class:`~bench.pairs.Pair` (meshes, errors) and each mesh prepared at most once."""

    def __init__(self, specs: list[str], config: TrainConfig, cfg: Settings) -> None:
        self.pairs = [Pair(s).subsample(max_points=cfg.max_points) for s in specs]
        if any(p.path_y is None for p in self.pairs):
            raise SystemExit("the learned suite needs pairs of files (no deformed copies such as A~B)")
        files = list(dict.fromkeys(str(p) for pair in self.pairs for p in (pair.path_x, pair.path_y)))
        self.shapes = ShapeDataset(files, cfg.cache, **config.dataset_kwargs(), progress=False)
        self.index = [(files.index(str(p.path_x)), files.index(str(p.path_y))) for p in self.pairs]
        self._prepared: dict[int, object] = {}

    def prepared(self, i: int, mesh, n_eigen: int = 0):
        if i not in self._prepared:
            self._prepared[i] = prepare_shape(mesh, n_eigen)  # grown in place by the matcher
        return self._prepared[i]

    def __iter__(self):
        for pair, (a, b) in zip(self.pairs, self.index, strict=True):
            yield pair, a, b, self.shapes[a], self.shapes[b]


def _checkpoints(spec) -> list[tuple[str, str]]:
    if spec is None:
        return [(name, str(path)) for name, path in shipped_models().items()]
    return [tuple(s.split("=", 1)) if "=" in s else (s, s) for s in spec]


def _sets(cfg: Settings) -> dict[str, list[str]]:
    return {name: expand(specs) for name, specs in cfg.sets.items()}


#: The row of the ground truth's own floor (:func:`torchfmap.evaluate.scores.error_floor`): a remeshing's
#: coarser regions raise it, so a ratio of errors across meshings is read against it.
FLOOR = "ground truth's floor (best vertex map)"


def checkpoints(cfg: Settings, report: Report) -> None:
    """Errors of trained checkpoints on validation sets: untrained baseline (same recipe and
    seed), the functional map's point map (orthogonal and pull-back rules), nearest features,
    ZoomOut (the matcher's, anchored by the features; with ``all_rules`` also without them),
    and test-time adaptation, with seconds per pair and the loss curves; and the floor of each
    set's ground truth (:data:`FLOOR`)."""
    rows, curves, described = [], {}, set()
    floors: dict[str, float] = {}
    for set_name, specs in _sets(cfg).items():
        for label, path in _checkpoints(cfg.checkpoints):
            net, config, ckpt = load_checkpoint(path)
            state = ckpt.get("train_state") or {}
            curves[label] = state.get("losses", [])
            data = PairSet(specs, config, cfg)
            solver, loss_fn = build_model(config)[1:]
            untrained = build_model(config)[0].eval()
            errors: dict[str, list[float]] = {}
            seconds: dict[str, float] = {}

            def add(method, fn, pair):
                t0 = time.perf_counter()
                p2p = fn()
                seconds[method] = seconds.get(method, 0.0) + time.perf_counter() - t0  # noqa: B023
                errors.setdefault(method, []).append(float(pair.errors(p2p).mean()))  # noqa: B023
                return p2p

            def zoomout(network, shapes):
                matcher = LearnedMatcher(network, config, device="cpu")  # noqa: B023
                return matcher(shapes[0].mesh, shapes[1].mesh, refine="zoomout", shapes=shapes).p2p_yx

            for i, (pair, a, b, x, y) in enumerate(data):
                shapes = (data.prepared(a, pair.x), data.prepared(b, pair.y))
                if cfg.all_rules:
                    add("untrained, fmap", lambda: predict_p2p(untrained, solver, x, y), pair)  # noqa: B023
                base = add("trained, fmap", lambda: predict_p2p(net, solver, x, y), pair)  # noqa: B023
                if cfg.all_rules:
                    add(
                        "trained, fmap, pull-back",
                        lambda: predict_p2p(net, solver, x, y, p2p_mode="pullback"),  # noqa: B023
                        pair,
                    )  # noqa: B023
                    add("trained, features", lambda: predict_p2p(net, solver, x, y, mode="features"), pair)  # noqa: B023
                if cfg.zoomout:
                    add("trained, fmap + zoomout", lambda: zoomout(net, shapes), pair)  # noqa: B023
                    if cfg.all_rules:  # the baseline: ZoomOut not anchored by the features
                        add(
                            "trained, fmap + zoomout without features",
                            lambda: zoomout_from(base, shapes, config.k, 2 * config.k),  # noqa: B023
                            pair,
                        )
                if cfg.adapt and i < cfg.adapt_pairs:
                    add("trained, fmap (adapt subset)", lambda: base, pair)  # noqa: B023
                    tuned = adapt(net, solver, loss_fn, x, y, steps=cfg.adapt, lr=cfg.adapt_lr)
                    add(f"adapt {cfg.adapt}, fmap", lambda: predict_p2p(tuned, solver, x, y), pair)  # noqa: B023
                    if cfg.zoomout:
                        add(f"adapt {cfg.adapt} + zoomout", lambda: zoomout(tuned, shapes), pair)  # noqa: B023
                if pair.name not in floors:  # one per pair, whatever the model
                    floors[pair.name] = pair.floor()
                errors.setdefault(FLOOR, []).append(floors[pair.name])
                seconds[FLOOR] = float("nan")
                pair.free()
                log(
                    f"{set_name} {label} pair {i + 1}/{len(data.pairs)}: "
                    + ", ".join(f"{m} {100 * e[-1]:.2f}" for m, e in errors.items())
                )
            base_t = seconds.get("trained, fmap", float("nan")) / max(len(errors.get("trained, fmap", [])), 1)
            for method, errs in errors.items():
                rows.append(
                    {
                        "model": label,
                        "set": set_name,
                        "method": method,
                        "pairs": len(errs),
                        "mean error x100": 100 * nanmean(errs),
                        "s / pair": seconds[method] / len(errs),
                        "t / trained fmap": seconds[method] / len(errs) / base_t,
                    }
                )
            if label not in described:  # once per model, not per set
                described.add(label)
                epochs = ", ".join(f"{s:.0f}" for s in state.get("epoch_seconds", [])) or "n/a"
                shipped = (ckpt.get("provenance") or {}).get("training", "not recorded")
                own = f"{state.get('step')} steps; seconds per epoch: {epochs}"
                trained = own if "step" in state else shipped
                recipe = f"{config.basis} basis K={config.k}, inputs {config.inputs}"
                report.add(f"**{label}** (`{path}`): {recipe}; {trained}")
    report.table("Mean geodesic error / sqrt(area) x100; seconds per pair (precompute excluded)", rows)
    report.rows_csv(rows)
    if any(curves.values()):
        report.figure(loss_curves, curves)


def loss_curves(plt, curves: dict):
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, losses in curves.items():
        total = np.array([t["total"] for t in losses])
        if len(total):  # a shipped model keeps no loss history
            w = max(1, len(total) // 50)
            ax.plot(np.convolve(total, np.ones(w) / w, mode="valid"), label=f"{label} (mean of {w})")
    ax.set(yscale="log", xlabel="step", ylabel="unsupervised loss")
    ax.legend()
    return fig


def curve(cfg: Settings, report: Report) -> None:
    """Where a recipe converges: validation error and loss against steps and wall time, while
    training through the Trainer (weights never selected by the ground truth)."""
    torch.set_num_threads(cfg.threads)
    if cfg.train == "demo":
        files = [str(p) for p in demo_pair_paths()[:2]]
    else:
        files = sorted(glob.glob(str(common.DATA_DIR / cfg.train)))
        if not files:
            raise Skip(f"no training files {common.DATA_DIR / cfg.train}")
    config = TrainConfig(**cfg.recipe, minutes=cfg.minutes, max_steps=cfg.max_steps, epochs=None)
    shapes = ShapeDataset(files, cfg.cache, **config.dataset_kwargs(), progress=False)
    val = PairSet(expand(cfg.val), config, cfg)
    pairs = class_pairs(shapes.names)
    solver, loss_fn = build_solver(config)
    unsupervised = unsupervised_score(shapes, pairs[:: max(1, len(pairs) // 6)][:6], solver, loss_fn)
    points, t_start, eval_s = [], time.perf_counter(), [0.0]

    def validate(model) -> float:
        t0 = time.perf_counter()
        score = unsupervised(model)
        errors = [float(p.errors(predict_p2p(model, solver, x, y)).mean()) for p, _, _, x, y in val]
        eval_s[0] += time.perf_counter() - t0
        points.append(
            {
                "step": (len(points) + 1) * cfg.every,
                "minutes": (time.perf_counter() - t_start - eval_s[0]) / 60,
                "val error x100": 100 * float(np.mean(errors)),
                "val loss": score,
            }
        )
        log(f"step {points[-1]['step']}: error {points[-1]['val error x100']:.2f}, loss {score:.4g}")
        model.train()
        return score

    state = Trainer.from_config(
        config, shapes, pairs, device="cpu", validate=validate, validate_every=cfg.every
    ).fit()
    if points:
        points[-1]["step"] = state.step
    report.table(
        f"Validation against steps ({state.step} steps in {state.seconds:.0f} s, {len(pairs)} pairs "
        f"per epoch)",
        points,
        note="Minutes exclude the validations. A shorter budget anneals sooner: the curve's shape, "
        "not a final error.",
    )
    report.figure(curve_figure, points, state.losses)


def curve_figure(plt, points: list[dict], losses: list):
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    steps = [p["step"] for p in points]
    ax1.plot(steps, [p["val error x100"] for p in points], "C3-o")
    ax1.set(xlabel="step", ylabel="validation error x100")
    ax1.grid(alpha=0.3)
    total = np.array([t["total"] for t in losses])
    w = max(1, len(total) // 50)
    ax2.plot(np.convolve(total, np.ones(w) / w, mode="valid"), label=f"training loss (mean of {w})")
    ax2.plot(steps, [p["val loss"] for p in points], "C1-o", label="validation loss")
    ax2.set(yscale="log", xlabel="step")
    ax2.legend()
    return fig


def adapt_sweep(cfg: Settings, report: Report) -> None:
    """Unsupervised test-time adaptation: steps x learning rate, raw and after ZoomOut, and what
    it costs per pair."""
    torch.set_num_threads(cfg.threads)
    ((label, path),) = _checkpoints([cfg.checkpoint])
    net, config, _ = load_checkpoint(path)
    _, solver, loss_fn = build_model(config)
    results: dict[tuple[int, float], list] = {}
    for specs in _sets(cfg).values():
        data = PairSet(specs, config, cfg)
        for pair, a, b, x, y in data:
            shapes = (data.prepared(a, pair.x), data.prepared(b, pair.y))
            for n in cfg.steps:
                for lr in cfg.lrs if n else cfg.lrs[:1]:
                    t0 = time.perf_counter()
                    tuned = adapt(net, solver, loss_fn, x, y, steps=n, lr=lr) if n else net
                    seconds = time.perf_counter() - t0
                    raw = predict_p2p(tuned, solver, x, y)
                    ref = LearnedMatcher(tuned, config, device="cpu")(
                        pair.x, pair.y, refine="zoomout", shapes=shapes
                    ).p2p_yx
                    results.setdefault((n, lr), []).append(
                        (pair.errors(raw).mean(), pair.errors(ref).mean(), seconds)
                    )
            pair.free()
    rows = [
        {
            "method": f"adapt {n} steps" if n else "no adaptation",
            "lr": f"{lr:g}" if n else "-",
            "raw x100": 100 * nanmean(r[0] for r in res),
            "ZoomOut x100": 100 * nanmean(r[1] for r in res),
            "adapt s / pair": nanmean(r[2] for r in res),
        }
        for (n, lr), res in results.items()
    ]
    report.table(
        f"`{label}`: mean geodesic error x100 and the adaptation's cost ({cfg.threads} thread(s))", rows
    )


def zoomout_from(p2p_yx, shapes, k0: int, k_final: int) -> np.ndarray:
    """ZoomOut of a given map in the prepared shapes' eigenbases, ``k0`` -> ``k_final`` (capped
    at ``V - 1``): the eigenbasis kind's refiner, as ``match`` refines (``LearnedMatcher`` also
    anchors it by the network's features)."""
    cap = min(s.mesh.n_vertices for s in shapes) - 1
    k0, k_final = min(k0, cap), min(k_final, cap)
    shapes = tuple(with_eigenpairs(s, k_final) for s in shapes)
    bx, by = (s.eigenbasis.truncated(k0) for s in shapes)
    refiner = get_kind("laplacian").refiner("zoomout", k_final=k_final, mode="orthogonal")
    return refiner(p2p_to_fmap(p2p_yx, bx, by), p2p_yx, *shapes, bx, by).p2p_yx


def stage_two(cfg: Settings, report: Report) -> None:
    """The learned path's self-seeded second stage (experimental.stages) against stage 1, raw
    and after ZoomOut, with the time per pair and per training step."""
    rows = []
    specs = _checkpoints(cfg.checkpoints)
    for (set_name, pair_specs), (label, path) in zip(_sets(cfg).items(), specs * len(cfg.sets), strict=False):
        net, config, _ = load_checkpoint(path)
        data = PairSet(pair_specs, config, cfg)
        solver, loss_fn = build_solver(config)
        stage = StageTwo(n_seeds=cfg.seeds) if cfg.seeds else StageTwo()
        errors: dict[str, list[float]] = {}
        seconds, counts = {"stage 1": 0.0, "stage 2": 0.0}, []
        for pair, a, b, x, y in data:
            sx, sy = data.prepared(a, pair.x, 2 * config.k), data.prepared(b, pair.y, 2 * config.k)
            t0 = time.perf_counter()
            first, second, used = two_stage_p2p(net, solver, x, y, sx, sy, stage)
            seconds["stage 2"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            predict_p2p(net, solver, x, y)
            seconds["stage 1"] += time.perf_counter() - t0
            counts.append(used)
            for method, p2p in (("stage 1", first), ("stage 2", second)):
                errors.setdefault(method, []).append(float(pair.errors(p2p).mean()))
                if cfg.zoomout:
                    refined = zoomout_from(p2p, (sx, sy), config.k, 2 * config.k)
                    errors.setdefault(method + " +ZO", []).append(float(pair.errors(refined).mean()))
            pair.free()
        step = [float("nan"), float("nan")]
        if cfg.step_pairs:  # one training step (forward, both losses, backward), stage 1 alone and both
            batches = [
                collate_pairs([(data.shapes[a], data.shapes[b])]) for a, b in data.index[: cfg.step_pairs]
            ]
            gen, net_t = torch.Generator().manual_seed(0), net.train()
            for j, extra in enumerate(((), (StageTwoLoss(data.shapes.mesh),))):
                for timed_pass in (False, True):  # the first pass prepares the second stage's shapes
                    t0 = time.perf_counter()
                    for batch in batches:
                        net_t.zero_grad()
                        pair_loss(net_t, solver, loss_fn, batch, gen, extra)["total"].backward()
                    if timed_pass:
                        step[j] = (time.perf_counter() - t0) / len(batches)
            net.eval()
        n = len(data.pairs)
        for method, errs in errors.items():
            stage_n = method.split(" +")[0]
            rows.append(
                {
                    "set": set_name,
                    "model": label,
                    "method": method,
                    "pairs": n,
                    "mean error x100": 100 * nanmean(errs),
                    "s / pair": seconds[stage_n] / n,
                    "t / stage 1": seconds[stage_n] / max(seconds["stage 1"], 1e-12),
                    "s / training step": step[0 if stage_n == "stage 1" else 1],
                }
            )
        report.add(f"{set_name}, {label}: {nanmean(counts):.1f} consistent seed pairs per pair (mean).")
    report.table("Second stage of the learned path against stage 1 (mean geodesic error x100)", rows)


def _dense_pair(names: list[str], level: int, at_5k: bool):
    """FAUST_r meshes Loop-subdivided ``level`` times (the original vertices keep their ids, so
    the ``.vts`` rows apply), or with ``at_5k`` the same surface at 5K (the subdivided positions
    of the original vertices on the original faces), and their ground truth."""
    folder, meshes = common.require_data("faust_r_train"), []
    for name in names:
        m = load_mesh(folder / f"{name}.off")
        v, f = (
            trimesh.remesh.subdivide_loop(m.vertices, m.faces, iterations=level)
            if level
            else (m.vertices, m.faces)
        )
        meshes.append(Mesh(v[: m.n_vertices], m.faces, name=name) if at_5k else Mesh(v, f, name=name))
    return meshes, vts_ground_truth(folder / "corres", *names)


def _dense_run(names, level, at_5k, coarse, checkpoint, threads, data_dir):
    """One match in a fresh process: ``(p2p raw, p2p ZoomOut, seconds, peak RSS MiB)``."""
    common.DATA_DIR = data_dir
    torch.set_num_threads(threads)
    (x, y), _ = _dense_pair(names, level, at_5k)
    t0 = time.perf_counter()
    res = LearnedMatcher.from_checkpoint(checkpoint, device="cpu", coarse=coarse)(x, y, refine="zoomout")
    seconds = time.perf_counter() - t0
    return res.p2p_yx_initial, res.p2p_yx, seconds, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def dense(cfg: Settings, report: Report) -> None:
    """The learned path on dense meshes: a FAUST_r pair Loop-subdivided to ~80K / ~320K vertices
    against the same surface at 5K, the network on every vertex and on a simplification, with
    time, peak memory and error (raw and after ZoomOut)."""
    rows, spawn = [], multiprocessing.get_context("spawn")
    runs = [("same surface at 5K", True, None), ("every vertex", False, None)]
    runs.append((f"simplified to {COARSE_VERTICES // 1000}K", False, COARSE_VERTICES))
    for level in cfg.levels:
        (mesh_x, _), gt = _dense_pair(cfg.pair, level, False)
        solver, ref = GeodesicSolver(mesh_x), None
        for route, at_5k, coarse in runs:
            args = (cfg.pair, level, at_5k, coarse, cfg.checkpoint, cfg.threads, common.DATA_DIR)
            with ProcessPoolExecutor(1, mp_context=spawn) as pool:  # a process per run: its own peak
                out = common.attempt(route, lambda a=args, p=pool: p.submit(_dense_run, *a).result())
            row = {"mesh": f"level {level}", "V": 5001 if at_5k else mesh_x.n_vertices, "route": route}
            if isinstance(out, common.Failed):
                rows.append({**row, "seconds": out})
                continue
            raw, zo, seconds, peak = out  # errors on the dense surface, the same rows for every map
            err = [
                100 * geodesic_errors(mesh_x, p, gt, max_points=cfg.max_points, solver=solver).mean()
                for p in (raw, zo)
            ]
            ref = err if at_5k else ref
            log(f"level {level} {route}: {seconds:.0f} s, {peak:.0f} MiB, errors {err[0]:.2f} / {err[1]:.2f}")
            ratios = [e / r for e, r in zip(err, ref, strict=True)] if ref else [float("nan")] * 2
            row |= {"seconds": seconds, "peak MiB": peak, "raw x100": err[0], "ZoomOut x100": err[1]}
            rows.append(row | {"raw / 5K": ratios[0], "ZoomOut / 5K": ratios[1]})
        report.rows_csv(rows)
    note = (
        f"Errors: mean geodesic error / sqrt(area) x100 on the subdivided surface at {cfg.max_points} "
        "ground-truth rows, the same rows for every map (the 5K map's vertices are the dense mesh's first)."
    )
    title = f"`{cfg.checkpoint}`, {' -> '.join(cfg.pair)} Loop-subdivided, match + ZoomOut"
    report.table(f"{title} ({cfg.threads} thread(s)): seconds with preparation, peak RSS", rows, note=note)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation drawn uniformly from SO(3) (QR of a Gaussian matrix, signs fixed)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def invariance(cfg: Settings, report: Report) -> None:
    """Every model on its pairs as they come and with the target turned by a random rotation
    (about its centroid; whole-shape models also scaled by ``scale``), raw and after ZoomOut, and
    the ratio turned / as is. Models in ``partial_models`` match plane cuts of the target
    (``ratios`` of its area, ``LearnedMatcher(partial=True)``), turned in the whole's units (a
    part's area against the whole's tells how partial it is). One rotation per pair and cut,
    drawn from ``seed``."""
    import warnings

    from torchfmap.data.cuts import cut_plane
    from torchfmap.evaluate.scores import Correspondence
    from torchfmap.operators import DistanceRows

    rows = []
    for label, path in _checkpoints(cfg.checkpoints):
        matcher = LearnedMatcher.from_checkpoint(path, device="cpu")
        partial = label in cfg.partial_models
        specs = expand(cfg.sets.get(label, cfg.sets["default"]))
        rng = np.random.default_rng(cfg.seed)
        errors: dict[tuple[str, str], list[float]] = {}
        for i, spec in enumerate(specs):
            pair = Pair(spec).subsample(max_points=cfg.max_points)
            solver = DistanceRows(pair.x)
            targets = []
            if partial:
                for ratio in cfg.ratios:
                    cut = cut_plane(pair.y, ratio, seed=i)
                    inv = np.full(pair.y.n_vertices, -1)
                    inv[cut.vertices] = np.arange(cut.n_vertices)
                    keep = inv[pair.gt.idx_y] >= 0
                    gt = Correspondence(pair.gt.idx_x[keep], inv[pair.gt.idx_y][keep])
                    targets.append((cut.mesh, gt, 1.0))
            else:
                targets.append((pair.y, pair.gt, cfg.scale))
            for y, gt, scale in targets:
                R = random_rotation(rng)
                centre = y.vertices.mean(axis=0)
                turned = Mesh((y.vertices - centre) @ R.T * scale + centre, y.faces, name=y.name)
                for how, mesh in (("as is", y), ("turned", turned)):
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        r = matcher(pair.x, mesh, refine="zoomout", partial=partial)
                    for refine, p2p in (("raw", r.p2p_yx_initial), ("zoomout", r.p2p_yx)):
                        err = float(geodesic_errors(pair.x, p2p, gt, solver=solver).mean())
                        errors.setdefault((how, refine), []).append(err)
                log(
                    f"{label} {spec}: "
                    + ", ".join(f"{h} {f} {100 * e[-1]:.2f}" for (h, f), e in errors.items())
                )
            pair.free()
        for refine in ("raw", "zoomout"):
            still, turned = (100 * nanmean(errors[(h, refine)]) for h in ("as is", "turned"))
            what = f"plane cuts {cfg.ratios}" if partial else f"whole, scale {cfg.scale}"
            rows.append(
                {
                    "model": label,
                    "targets": what,
                    "pairs": len(errors[("as is", refine)]),
                    "map": refine,
                    "as is x100": still,
                    "turned x100": turned,
                    "turned / as is": turned / still,
                }
            )
    report.table(
        "Mean geodesic error / sqrt(area) x100 on the source, target as it comes and turned by a random "
        "rotation (whole shapes also scaled)",
        rows,
        note="One uniform random rotation per pair (or cut), about the target's centroid, the same for "
        "every model; the ratio is the turned error over the as-is error of the same pairs.",
    )
    report.rows_csv(rows)


CASES = {
    "checkpoints": checkpoints,
    "curve": curve,
    "adapt": adapt_sweep,
    "stage_two": stage_two,
    "dense": dense,
    "invariance": invariance,
}
