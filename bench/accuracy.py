"""Suite ``accuracy``: classical matching (``torchfmap.match``) on real pairs, against pyFM.

Every case runs one grid (:func:`grid`): for each set of pairs (``sets``: name -> pair specs of
``bench/pairs.py``, ``@set`` names allowed), each pair, each number of landmarks ``L`` (0: none;
ground-truth rows spread by FPS, the first L given pairs on cat-lion, all 20 with
``given_landmarks``), each method of ``methods`` (``label``, ``refine``: a refinement or a list of
them, the unrefined map being ``p2p_yx_initial`` of the same call; ``seeded``: true for
``torchfmap.experimental.seeded.seeded_match``; every other key a ``match`` argument, ``k``
from the case unless given) and, if ``pyfm`` is set, pyFM's pipeline (``bench/pairs.run_pyfm``,
with those settings). With ``prepared``, each mesh is prepared once (``prepare_shape``) and its
shapes are handed to every method, so the times compare what follows preparation. Errors: mean
normalised geodesic error x100 at every ``every``-th ground-truth row (or ``max_points`` of them).
Every case writes the rows (``.csv``), the means per method and refinement for every set and L,
the median time over that of ``baseline`` (same refinement, same process), and an error-vs-L
figure when there are several L.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from torchfmap import prepare_shape
from torchfmap.experimental.seeded import seeded_match
from torchfmap.matching.landmark_default import AUTO_KINDS, AUTO_MARGIN

from .common import Report, Settings, fmt, log, require_data
from .pairs import Pair, crash, expand, mean_of, pyfm_missing, pyfm_rows, record, run_match


def _refines(method: dict) -> list[str | None]:
    r = method.get("refine")
    return list(r) if isinstance(r, list) else [r]


def _match_kwargs(method: dict, k: int) -> dict:
    return {"k": k} | {key: v for key, v in method.items() if key not in ("label", "refine", "seeded")}


def run_method(pair: Pair, rows: list, method: dict, lmk, k: int, shapes, info: dict) -> None:
    """The rows of one method on one pair: one ``match`` call per refinement (the unrefined row
    from the first), or ``seeded_match``."""
    label, kwargs = method["label"], _match_kwargs(method, k)
    if shapes is not None:
        kwargs["shapes"] = shapes
    if method.get("seeded"):
        try:
            t0 = time.perf_counter()
            res = seeded_match(pair.x, pair.y, **kwargs).result
            seeds = 0 if res.seeds is None else len(res.seeds)
            rows.append(
                record(pair, label, "seeded", res.p2p_yx, time.perf_counter() - t0, **info, seeds=seeds)
            )
        except Exception:
            crash(f"{pair.name} {label}")
        return
    for i, refine in enumerate(_refines(method)):
        got: list = []
        res = run_match(pair, got, label, refine, info, landmarks=lmk, **kwargs)
        if res is not None and res.candidates:  # the landmark default: what it chose
            chosen = {"chosen": res.kind, "distortion": res.distortion, "refine_kept": res.refined}
            for r in got:
                r |= chosen
        rows += got if i == 0 else got[1:]  # the unrefined map once


def grid(cfg: Settings, report: Report, methods: list[dict] | None = None) -> list[dict]:
    """Run the case's grid (module docstring); returns the rows (also written as ``.csv``)."""
    methods = cfg.methods if methods is None else methods
    pyfm = cfg.get("pyfm")
    if pyfm and pyfm_missing():
        report.add(pyfm_missing())
        pyfm = None
    sets = {name: expand(specs) for name, specs in cfg.sets.items()}
    rows: list[dict] = []
    try:
        for set_name, specs in sets.items():
            for spec in specs:
                log(f"loading {spec}")
                pair = Pair(spec).subsample(cfg.get("every", 1), cfg.get("max_points"))
                shapes = (prepare_shape(pair.x, 0), prepare_shape(pair.y, 0)) if cfg.get("prepared") else None
                for n in cfg.L:
                    lmk = pair.landmarks(n, cfg.get("given_landmarks", False))
                    info = {"set": set_name, "L": n}
                    log(f"{spec} L={n}")
                    for method in methods:
                        run_method(pair, rows, method, lmk, cfg.k, shapes, info)
                    if pyfm:
                        settings = {k: v for k, v in pyfm.items() if k != "refine"}
                        refines = [None, *pyfm.get("refine", [])]
                        got: list = []
                        pyfm_rows(pair, got, cfg.k, lmk, refines, **settings)
                        rows += [r | info for r in got]
                    report.rows_csv(rows)
                pair.free()
    except KeyboardInterrupt:
        report.add("**Interrupted**: the tables below hold the runs that finished.")
    report.table("Mean normalised geodesic error x100 (means over pairs) and times", summary(rows, sets, cfg))
    if len(cfg.L) > 1:
        report.figure(error_curves, rows, sets, cfg.L)
    return rows


def _methods(rows: list[dict]) -> list[tuple[str, str]]:
    return list(dict.fromkeys((r["method"], r["refine"]) for r in rows))


def summary(rows: list[dict], sets: dict, cfg: Settings) -> list[dict]:
    """Per method and refinement (rows): the mean error x100 for every set and L, the median
    time and its ratio to the ``baseline`` method's (same refinement)."""
    out = []
    for method, refine in _methods(rows):
        line: dict = {"method": method, "refine": refine}
        for set_name, names in sets.items():
            for n in cfg.L:
                line[f"{set_name} L={n}" if len(cfg.L) > 1 or len(sets) > 1 else "err x100"] = mean_of(
                    rows, names, method=method, refine=refine, L=n, set=set_name
                )
        times = [r["time"] for r in rows if (r["method"], r["refine"]) == (method, refine) and "time" in r]
        base = [
            r["time"] for r in rows if (r["method"], r["refine"]) == (cfg.baseline, refine) and "time" in r
        ]
        line["median t [s]"] = float(np.median(times)) if times else float("nan")
        if base and times:
            line[f"t / {cfg.baseline}"] = float(np.median(times) / np.median(base))
        kinds = sorted({r["K"] for r in rows if (r["method"], r["refine"]) == (method, refine) and "K" in r})
        line["K"] = "/".join(str(k) for k in kinds)
        notes = sorted(
            {r["note"] for r in rows if (r["method"], r["refine"]) == (method, refine) and "note" in r}
        )
        if notes:
            line["note"] = "/".join(notes)
        out.append(line)
    return out


def error_curves(plt, rows: list[dict], sets: dict, Ls: list[int]):
    """Mean error x100 against L, one panel per set, a curve per method and refinement."""
    fig, axes = plt.subplots(1, len(sets), figsize=(5.5 * len(sets), 4.2), squeeze=False)
    for ax, (set_name, names) in zip(axes[0], sets.items(), strict=True):
        for method, refine in _methods([r for r in rows if r.get("set") == set_name]):
            ys = [mean_of(rows, names, method=method, refine=refine, L=n, set=set_name) for n in Ls]
            if not np.all(np.isnan(ys)):
                ax.plot(Ls, ys, "--" if refine == "none" else "-", marker="o", label=f"{method} {refine}")
        ax.set(
            title=f"{set_name} ({len(names)} pairs)", xlabel="landmarks L (0: none)", ylabel="mean error x100"
        )
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    return fig


# -- the cases ----------------------------------------------------------------------------------
def bases(cfg: Settings, report: Report) -> None:
    """Every basis kind x refinement (none, ICP, ZoomOut) against pyFM, same landmarks and k."""
    rows = grid(cfg, report)
    per_pair = []
    for pair in dict.fromkeys(r["pair"] for r in rows):
        line = {"pair": pair}
        for method, refine in _methods(rows):
            line[f"{method} {refine}"] = mean_of(rows, [pair], method=method, refine=refine)
        per_pair.append(line)
    report.table("Per pair: mean error x100", per_pair)


def landmark_sweep(cfg: Settings, report: Report) -> None:
    """Mean error against the number of landmarks, every basis and pyFM (unrefined and ICP)."""
    grid(cfg, report)


def weight_sweep(cfg: Settings, report: Report) -> None:
    """Mean error against the Laplacian-commutativity weight w_lap, per basis (how each kind's
    w_lap was chosen)."""
    methods = [{"label": f"{b} w_lap={w:g}", "basis": b, "w_lap": w} for b in cfg.bases for w in cfg.w_lap]
    rows = grid(cfg, report, methods)
    sets = {s: expand(specs) for s, specs in cfg.sets.items()}
    names = [n for specs in sets.values() for n in specs]
    table = [
        {"basis": b, **{f"w_lap={w:g}": mean_of(rows, names, method=f"{b} w_lap={w:g}") for w in cfg.w_lap}}
        for b in cfg.bases
    ]
    report.table("Mean error x100 over all pairs: basis x w_lap (no refinement)", table)


def faust(cfg: Settings, report: Report) -> None:
    """Classical matching on FAUST_r dev pairs (humans), with and without landmarks, vs pyFM."""
    rows = grid(cfg, report)
    sets = {s: expand(specs) for s, specs in cfg.sets.items()}
    out = []
    for method, refine in _methods(rows):
        for n in cfg.L:
            errs = np.array(
                [
                    r["mean"]
                    for r in rows
                    if (r["method"], r["refine"], r["L"]) == (method, refine, n) and "mean" in r
                ]
            )
            if len(errs):
                out.append(
                    {
                        "method": method,
                        "refine": refine,
                        "L": n,
                        "median x100": 100 * np.median(errs),
                        "pairs > 10": f"{int((errs > 0.1).sum())}/{len(errs)}",
                    }
                )
    report.table(f"Medians and failures (error > 10) over the {sum(map(len, sets.values()))} pairs", out)


def feature_accuracy(cfg: Settings, report: Report) -> None:
    """Feature-aware bases against the eigenbasis and pyFM with few landmarks, iso and non-iso pairs."""
    rows = grid(cfg, report)
    sets = {s: expand(specs) for s, specs in cfg.sets.items()}
    out = []
    for n in cfg.L:
        for s, names in sets.items():
            m = {
                (meth, r): mean_of(rows, names, method=meth, refine=r, L=n, set=s)
                for meth, r in _methods(rows)
            }
            t = {
                key: mean_of(rows, names, "time", 1.0, method=key[0], refine=key[1], L=n, set=s) for key in m
            }
            out.append(
                {
                    "L": n,
                    "set": s,
                    "diffusion raw / lap raw": m.get(("diffusion", "none"), np.nan)
                    / m.get(("laplacian", "none"), np.nan),
                    "diffusion ZO / lap ZO": m.get(("diffusion", "zoomout"), np.nan)
                    / m.get(("laplacian", "zoomout"), np.nan),
                    "t diffusion ZO / t lap ZO": t.get(("diffusion", "zoomout"), np.nan)
                    / t.get(("laplacian", "zoomout"), np.nan),
                }
            )
    report.table("Ratios (targets: <= 0.8 at L = 7, 15; no worse at L = 3)", out)


def landmark_default(cfg: Settings, report: Report) -> None:
    """The landmark default of match (it chooses the basis) against each forced kind and pyFM."""
    rows = grid(cfg, report)
    sets = {s: expand(specs) for s, specs in cfg.sets.items()}
    forced = [m["label"] for m in cfg.methods if m.get("basis")]
    out = []
    for n in cfg.L:
        for s, names in sets.items():
            right, errors = [], {"default": [], "laplacian": [], "oracle": []}
            for name in names:
                d = mean_of(rows, [name], method="default", refine="zoomout", L=n, set=s)
                best = [mean_of(rows, [name], method=b, refine="zoomout", L=n, set=s) for b in forced]
                right.append(d <= 1.02 * min(best) if best and not np.isnan([d, *best]).any() else np.nan)
                lap = mean_of(rows, [name], method="laplacian", refine="zoomout", L=n, set=s)
                for key, value in (("default", d), ("laplacian", lap), ("oracle", min(best, default=np.nan))):
                    errors[key].append(value)
            chosen = [
                r["chosen"]
                for r in rows
                if r["pair"] in names and r.get("L") == n and r.get("chosen") and r["refine"] == "zoomout"
            ]
            t = {
                b: mean_of(rows, names, "time", 1.0, method=b, refine="zoomout", L=n, set=s)
                for b in ("default", "laplacian")
            }
            out.append(
                {
                    "L": n,
                    "set": s,
                    "choice right": nanmean_or(right),
                    f"chosen ({'/'.join(b[:3] for b in AUTO_KINDS)})": "/".join(
                        str(chosen.count(b)) for b in AUTO_KINDS
                    ),
                    "default ZO / lap ZO": np.mean(errors["default"]) / np.mean(errors["laplacian"]),
                    "best forced kind per pair / lap ZO": np.mean(errors["oracle"])
                    / np.mean(errors["laplacian"]),
                    "t default / t lap ZO": t["default"] / t["laplacian"],
                }
            )
    report.table(
        "The default's choice",
        out,
        note=f"default: basis=None, chooses among {', '.join(AUTO_KINDS)} by geodesic distortion (eigenbasis "
        f"margin {AUTO_MARGIN:g}), then by held-out landmarks, never more distorted than the eigenbasis. "
        "Choice right: share of pairs whose refined error is within 2 % of the best forced kind's. Best "
        "forced kind per pair: the mean of each pair's least refined error among the forced kinds (what "
        "a chooser that knew the ground truth would reach), over the eigenbasis's mean.",
    )


def nanmean_or(values: list) -> float:
    v = [x for x in values if not (isinstance(x, float) and np.isnan(x))]
    return float(np.mean(v)) if v and len(v) == len(values) else float("nan")


def seeded_refine(cfg: Settings, report: Report) -> None:
    """The classical self-seeded second stage (experimental.seeded.seeded_match) against ZoomOut,
    without landmarks, on shapes prepared once per pair."""
    rows = grid(cfg, report)
    seeds = [r["seeds"] for r in rows if "seeds" in r]
    t = {
        m: sum(r["time"] for r in rows if (r["method"], r["refine"]) == m and "time" in r)
        for m in (("seeded", "seeded"), ("zoomout", "zoomout"))
    }
    ratio = t[("seeded", "seeded")] / t[("zoomout", "zoomout")] if t[("zoomout", "zoomout")] else float("nan")
    report.add(
        f"Seed pairs per pair (mean): {fmt(float(np.mean(seeds)) if seeds else float('nan'))}; "
        f"time of seeded over ZoomOut (sums over pairs): {fmt(ratio)}."
    )


def _partial_pairs(cfg: Settings):
    """``(name, whole, other, gt_whole, gt_other)``: dev pairs whose target is cut; the ground truth
    as corresponding rows (``corres/<name>.vts``; a folder without ``corres/``, such as SCAPE's
    registered poses, has the identity on vertex ids; or the demo pair's map)."""
    from torchfmap.data import demo_pair
    from torchfmap.io import find_file, load_mesh, read_vts

    if cfg.shapes == "demo":
        a, b, gt = demo_pair()
        yield "demo", a, b, gt, np.arange(b.n_vertices)
        return
    folder = require_data(cfg.shapes["folder"])
    for i, j in cfg.shapes["pairs"]:
        a, b = (load_mesh(find_file(folder, f"{n}.off")) for n in (i, j))
        if (folder / "corres").is_dir():
            gt = [read_vts(find_file(folder / "corres", f"{n}.vts")) for n in (i, j)]
        else:  # registered poses: vertex k of every pose is vertex k of the template
            gt = [np.arange(a.n_vertices)] * 2
        yield f"{i}-{j}", a, b, *gt


def partial(cfg: Settings, report: Report) -> None:
    """Partial-to-full: each target cut (plane or holes, ``ratios`` of its area), matched to the
    whole source by the full-shape ``match`` and by ``match(partial=True)``, raw and refined, with
    ``L`` landmarks (ground-truth rows spread by FPS; the full-shape map then in the eigenbasis).
    Errors on the whole shape over the part's ground-truth rows; overlap IoU of ``v > 0.5``
    against the true part (area-weighted). ``learned``: a model matched by
    ``LearnedMatcher(..., partial=True)`` (its features next to SHOT, the model's ``k``; with landmarks,
    the same descriptors in :func:`~torchfmap.matching.partial.match_partial` at ``k``); ``features``: its
    features alone in place of SHOT (null ``learned``: neither is run)."""
    from torchfmap import match
    from torchfmap.data.cuts import cut_holes, cut_plane
    from torchfmap.evaluate.scores import Correspondence, geodesic_errors, landmarks_from_gt
    from torchfmap.matching.partial import match_partial

    rows = []
    learned = None
    if cfg.learned:
        from torchfmap.nn import LearnedMatcher

        learned = LearnedMatcher.from_checkpoint(cfg.learned, device="cpu")
    methods = ("full-shape", "partial", "learned", "features") if learned else ("full-shape", "partial")
    for name, whole, other, gt_w, gt_o in _partial_pairs(cfg):
        shape_w = prepare_shape(whole, 2 * cfg.k + 100)
        vertex_area = shape_w.operators[1].diagonal()  # lumped mass: area weights (any scale)
        for ratio in cfg.ratios:
            for how in cfg.cuts:
                cut = (
                    cut_plane(other, ratio, seed=1) if how == "plane" else cut_holes(other, ratio, 4, seed=1)
                )
                inv = np.full(other.n_vertices, -1)
                inv[cut.vertices] = np.arange(cut.n_vertices)
                keep = inv[gt_o] >= 0
                gt = Correspondence(gt_w[keep], inv[gt_o][keep])
                truth = np.zeros(whole.n_vertices, bool)
                truth[gt.idx_x] = True
                shape_p = prepare_shape(cut.mesh, 2 * cfg.k + 100)
                a = cut.mesh.area / other.area
                feats = None  # the model's features of this cut, computed once when landmarks need them
                for n in cfg.L:
                    lm = landmarks_from_gt(whole, gt, n) if n else None
                    for method in methods:
                        t0 = time.perf_counter()
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore")
                            if method == "learned" and lm is None:  # the model's k, SHOT beside
                                r = learned(
                                    whole, cut.mesh, refine="zoomout", shapes=(shape_w, shape_p),
                                    partial=True,
                                )  # fmt: skip
                            elif method in ("learned", "features"):  # its features computed once
                                r = match_partial(
                                    shape_w, shape_p, landmarks=lm, k=cfg.k, refine="zoomout",
                                    descriptors=feats or (feats := (
                                        learned.features(whole, shape=shape_w),
                                        learned.features(cut.mesh, shape=shape_p, whole=shape_w),
                                    )), with_shot=method == "learned",
                                )  # fmt: skip
                            else:
                                r = match(
                                    whole, cut.mesh, landmarks=lm, k=cfg.k, refine="zoomout",
                                    shapes=(shape_w, shape_p),
                                    **({"partial": True} if method == "partial" else
                                       {"basis": "laplacian"} if n else {}),
                                )  # fmt: skip
                        t = time.perf_counter() - t0
                        for refine, p2p in (("-", r.p2p_yx_initial), ("zoomout", r.p2p_yx)):
                            row = dict(
                                pair=name,
                                cut=how,
                                ratio=round(a, 2),
                                L=n,
                                method=method,
                                refine=refine,
                                time=t,
                            )
                            row["mean"] = float(
                                geodesic_errors(whole, p2p, gt, solver=shape_w.distances).mean()
                            )
                            if method == "partial" and refine == "zoomout":
                                est = r.overlap > 0.5
                                row["iou"] = float(
                                    vertex_area[est & truth].sum() / vertex_area[est | truth].sum()
                                )
                            rows.append(row)
                            log(f"{name} {how} {a:.2f} L={n} {method} {refine}: {100 * row['mean']:.2f}")
    report.rows_csv(rows)
    bands = [(0.0, 0.5), (0.5, 0.7), (0.7, 1.0)]
    out = []
    for lo, hi in bands:
        for n in cfg.L:
            band = [r for r in rows if lo < r["ratio"] <= hi and r["L"] == n]
            if not band:
                continue
            line = {"area ratio": f"({lo}, {hi}]", "L": n, "cuts": len(band) // (2 * len(methods))}
            for method in methods:
                for refine in ("-", "zoomout"):
                    errs = [r["mean"] for r in band if (r["method"], r["refine"]) == (method, refine)]
                    line[f"{method} {refine}"] = 100 * float(np.mean(errs))
            ious = [r["iou"] for r in band if "iou" in r]
            line["IoU"] = float(np.mean(ious)) if ious else float("nan")
            line["t partial / t full"] = float(
                np.median([r["time"] for r in band if r["method"] == "partial"])
                / np.median([r["time"] for r in band if r["method"] == "full-shape"])
            )
            out.append(line)
    report.table(
        "Partial-to-full: mean geodesic error x100 on the whole, over the part's rows",
        out,
        note="full-shape: match(whole, part) (eigenbasis with landmarks); partial: match(whole, part, "
        "partial=True); "
        + (
            f"learned: the partial solve with {cfg.learned} features next to SHOT, features: in place of "
            "SHOT (their time counted); "
            if learned
            else ""
        )
        + "'-': the unrefined map of the same call; IoU (of the partial mode): overlap v > 0.5 against "
        "the true part, area-weighted; times include ZoomOut, same process.",
    )


def _whole_errors(shape_w, images, truth) -> np.ndarray:
    """Geodesic errors on the whole (units of its ``sqrt(area)``) between whole vertices."""
    out = np.empty(len(images))
    for u in np.unique(truth):
        at = truth == u
        out[at] = shape_w.distances.distances(np.array([u]))[0, images[at]]
    return out


def partial_pairs(cfg: Settings, report: Report) -> None:
    """Partial-to-partial: two plane cuts of one whole (``overlapping_cuts``: each part's overlap
    share in ``shares``), matched by ``match(a, b, partial='both')``; overlap IoU on both parts
    (``overlap_iou`` against the true overlap, the part's vertices whose whole vertex is in the
    other part) and the geodesic error on the true overlap (on the whole, x100), against each
    part matched to the whole (``match(whole, part, partial=True)``, same ``k`` and refinement)
    on the same vertices."""
    from torchfmap import match
    from torchfmap.data import demo_pair
    from torchfmap.data.cuts import overlapping_cuts
    from torchfmap.evaluate.partial import overlap_iou
    from torchfmap.io import find_file, load_mesh

    rows = []
    if cfg.shapes == "demo":
        wholes = [("demo", demo_pair()[0])]
    else:
        folder = require_data(cfg.shapes["folder"])
        wholes = [(n, load_mesh(find_file(folder, f"{n}.off"))) for n in cfg.shapes["wholes"]]
    for i, (name, whole) in enumerate(wholes):
        shape_w = prepare_shape(whole, 2 * cfg.k)
        cut_a, cut_b = overlapping_cuts(whole, seed=i, shares=tuple(cfg.shares))
        shape_a, shape_b = (prepare_shape(c.mesh, 2 * cfg.k) for c in (cut_a, cut_b))
        in_a, in_b = np.isin(cut_a.vertices, cut_b.vertices), np.isin(cut_b.vertices, cut_a.vertices)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t0 = time.perf_counter()
            r = match(
                cut_a.mesh, cut_b.mesh, k=cfg.k, refine=cfg.refine, partial="both", shapes=(shape_a, shape_b)
            )
            t = time.perf_counter() - t0
            to_whole = [
                match(whole, c.mesh, k=cfg.k, refine=cfg.refine, partial=True, shapes=(shape_w, s)).p2p_yx
                for c, s in ((cut_a, shape_a), (cut_b, shape_b))
            ]
        err = _whole_errors(shape_w, cut_a.vertices[r.p2p_yx[in_b]], cut_b.vertices[in_b])
        marked = r.overlap_y[in_b] > 0.5
        row = dict(
            whole=name,
            share_a=float(shape_a.operators[1].diagonal() @ in_a / shape_a.area),
            share_b=float(shape_b.operators[1].diagonal() @ in_b / shape_b.area),
            iou_a=overlap_iou(r.overlap, np.flatnonzero(in_a), shape_a.operators[1]),
            iou_b=overlap_iou(r.overlap_y, np.flatnonzero(in_b), shape_b.operators[1]),
            err=100 * float(err.mean()),
            err_marked=100 * float(err[marked].mean()) if marked.any() else float("nan"),
            p2f_a=100 * float(_whole_errors(shape_w, to_whole[0][in_a], cut_a.vertices[in_a]).mean()),
            p2f_b=100 * float(_whole_errors(shape_w, to_whole[1][in_b], cut_b.vertices[in_b]).mean()),
            time=t,
        )
        row["err / p2f"] = row["err"] / max(0.5 * (row["p2f_a"] + row["p2f_b"]), 1e-9)
        rows.append(row)
        log(f"{name}: IoU {row['iou_a']:.3f} {row['iou_b']:.3f}, error x100 {row['err']:.2f}")
        report.rows_csv(rows)
    keys = [k for k in rows[0] if k != "whole"]
    mean = {"whole": "mean"} | {k: float(np.mean([r[k] for r in rows])) for k in keys}
    median = {"whole": "median"} | {k: float(np.median([r[k] for r in rows])) for k in keys}
    report.table(
        "Partial-to-partial: overlap IoU on each part, mean geodesic error x100 on the true overlap",
        [*rows, mean, median],
        note="share_a/b: the true overlap's share of each part's area; iou_a/b: overlap_iou of overlap / "
        "overlap_y; err: b's vertices of the true overlap, their images on a against the truth, geodesic "
        "on the whole; err_marked: those the estimate marks (overlap_y > 0.5); p2f_a/b: each part matched "
        "to the whole (partial=True), error on the same overlap vertices; err / p2f: err over their mean; "
        "time: match(partial='both') alone.",
    )


CASES = {
    "partial": partial,
    "partial_smal": partial,
    "partial_pairs": partial_pairs,
    "bases": bases,
    "landmark_sweep": landmark_sweep,
    "weight_sweep": weight_sweep,
    "faust": faust,
    "feature_accuracy": feature_accuracy,
    "landmark_default": landmark_default,
    "seeded_refine": seeded_refine,
}
