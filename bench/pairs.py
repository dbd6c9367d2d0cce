"""The one pair loader of every suite: real and synthetic pairs with ground truth and landmarks,
named sets of pairs, geodesic errors, result rows, and pyFM's pipeline (the classical baseline).

Pair specs (``x`` the source, ``y`` the target; every map is ``p2p_yx``):

- ``demo``: the shipped demo pair (``torchfmap.data.demo_pair``: blob_a, blob_b, ground truth);
- ``A-B``: ``tosca5k_dev/A.off`` and ``B.off`` with the rows of ``corres/A.vts`` and ``B.vts``;
  ``A~B``: the same with ``B`` deformed non-isometrically by ``torchfmap.data.stretch_deform(B,
  seed=crc32(B), strength=1)`` (vertex ids kept, same ground truth);
- ``faust:A-B``: ``faust_r_train/tr_reg_A.off`` and ``tr_reg_B.off`` (``corres/*.vts``);
- ``smal:A+B``: ``smal_r_train/A.off.gz`` and ``B.off.gz`` (``corres/*.vts``);
- ``faust_a:A+B``, ``faust_h:A+B``, ``scape_r:A+B``, ``scape_a:A+B``, ``scape_h:A+B``: the
  remeshed dev sets of ``bench/data`` (``python -m tools.remesh``);
- ``cat-lion``: ``pyfm_cat_lion`` cat-00 (x) and lion-00 (y), ground truth ``lion2cat``, its 20
  given landmark pairs.

Named sets, ``@name`` in a configuration's pair list (``@name:N``: its first N): see :data:`SETS`.

Landmarks: ``L`` ground-truth rows spread over x by Euclidean farthest-point sampling
(``torchfmap.evaluate.scores.landmarks_from_gt``, deterministic), the same for every method of a pair;
cat-lion's given pairs where a case asks for them. Errors: normalised geodesic error on x (heat
method, divided by ``sqrt(area_x)``) at the ground-truth rows (all, every n-th or a seeded random
subset), distance rows computed once per pair; the first map of a pair is also scored by
``torchfmap.evaluate.scores.evaluate_map`` and any difference logged (it must be ~0).
"""

from __future__ import annotations

import importlib.util
import time
import traceback
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import torchfmap
from torchfmap.data import demo_pair_paths, stretch_deform
from torchfmap.errors import ParameterError
from torchfmap.evaluate.ground_truth import vts_ground_truth
from torchfmap.evaluate.scores import (
    Correspondence,
    auc,
    error_floor,
    evaluate_map,
    gt_from_map,
    landmarks_from_gt,
)  # fmt: skip
from torchfmap.io import (
    load_mesh,
    mesh_files,
    read_landmark_pairs,
    read_map,
    read_test_pairs,
    read_vts,
    shape_name,
)

from .common import LOCAL_DATA_DIR, Skip, load1, log, require_data

FAUST_DEV = [f"tr_reg_{i:03d}" for i in range(60, 80)]  # people 6 and 7: never the test split
FAUST_VAL = [f"tr_reg_{i:03d}" for i in range(70, 80)]  # never trained on by the shipped models
SCAPE_VAL = [f"mesh{i:03d}" for i in range(41, 51)]
TOSCA_ISO = ["cat0-cat1", "cat2-cat8", "cat10-cat4", "cat5-cat9", "wolf0-wolf1", "wolf1-wolf2"]
TOSCA_NONISO = ["cat-lion", "cat0~cat1", "cat5~cat9", "cat2~cat8", "wolf0~wolf1"]
#: Remeshed dev sets (``python -m tools.remesh``) and the shape names they validate on.
LOCAL_SETS = {
    "faust_a": FAUST_VAL, "faust_h": FAUST_VAL,
    "scape_r": SCAPE_VAL, "scape_a": SCAPE_VAL, "scape_h": SCAPE_VAL,
}  # fmt: skip


def drawn_pairs(names: list[str], n: int, seed: int = 0) -> list[tuple[str, str]]:
    """``n`` ordered pairs drawn with ``seed`` among ``names`` (all of them if fewer)."""
    every = [(a, b) for a in names for b in names if a != b]
    pick = np.random.default_rng(seed).choice(len(every), min(n, len(every)), replace=False)
    return [every[i] for i in pick]


def smal_split() -> tuple[list[str], list[str]]:
    """``(train, val)`` names of the ``smal_r_train`` animals of the learned recipes: every 4th of
    the sorted names validates (8 of 32), the other 24 train; SMAL_r's test split stays held out."""
    names = sorted(shape_name(p) for p in mesh_files(require_data("smal_r_train")))
    val = names[::4]
    return [n for n in names if n not in val], val


#: Ordered pairs of the species split's validation set (``@smal_fval``, ``bench/data/smal_fval``).
SMAL_FVAL_PAIRS = 40
#: Rows of the SMAL template whose geodesic distances make an animal's shape signature.
N_SIGNATURE_ROWS = 40


def smal_families(n_families: int = 5) -> list[list[str]]:
    """The 32 ``smal_r_train`` animals grouped into ``n_families`` shape families, sorted names in
    each, families ordered by size then first name.

    The folder names no species, so they are found from the shapes: each animal's signature is the
    matrix of geodesic distances, divided by ``sqrt(area)``, between ``N_SIGNATURE_ROWS`` template
    vertices (farthest-point sampled on the first animal, the same rows on every animal through
    ``corres/*.vts``); geodesic distances change little with pose and much with proportions (legs,
    neck, body length). Ward clustering of the signatures into 5 families recovers SMAL's five
    (felids, canids, horses, cows, hippos) up to a few animals of ambiguous proportions."""
    from scipy.cluster.hierarchy import fcluster, linkage

    from torchfmap.operators.geodesic import GeodesicSolver

    folder = require_data("smal_r_train")
    names = sorted(shape_name(p) for p in mesh_files(folder))
    signatures, rows = [], None
    for name in names:
        mesh = load_mesh(folder / f"{name}.off.gz")
        vts = read_vts(folder / "corres" / f"{name}.vts")
        if rows is None:
            rows = _farthest_rows(np.asarray(mesh.vertices)[vts], N_SIGNATURE_ROWS)
        solver = GeodesicSolver(mesh)
        d = np.stack([solver.distance(int(vts[r]))[vts[rows]] for r in rows]) / np.sqrt(mesh.area)
        d = 0.5 * (d + d.T)
        signatures.append(d[np.triu_indices(len(rows), 1)])
    labels = fcluster(linkage(np.asarray(signatures), "ward"), n_families, "maxclust")
    families = [
        sorted(n for n, lab in zip(names, labels, strict=True) if lab == c) for c in sorted(set(labels))
    ]
    return sorted(families, key=lambda f: (len(f), f[0]))


def _farthest_rows(points: np.ndarray, n: int) -> np.ndarray:
    """``n`` row indices of ``points`` (V, 3) by Euclidean farthest-point sampling from row 0."""
    rows = [0]
    d = np.linalg.norm(points - points[0], axis=1)
    for _ in range(n - 1):
        rows.append(int(d.argmax()))
        d = np.minimum(d, np.linalg.norm(points - points[rows[-1]], axis=1))
    return np.asarray(rows)


def smal_family_split(families: list[list[str]] | None = None) -> tuple[list[str], list[str]]:
    """``(train, val)`` names for a split by species: the two smallest of ``families`` (default
    :func:`smal_families`) validate (animals whose proportions no training animal shares), the
    other three train."""
    families = smal_families() if families is None else families
    val = sorted(n for f in families[:2] for n in f)
    return sorted(n for f in families[2:] for n in f), val


def _smal_cross() -> list[str]:
    """SMAL_r training animals paired across names (``names[i]``, ``names[(i + 11) % 32]`` for
    ``i = 0, 3, ...``; pairs sharing a name stem skipped): real pairs of different animals."""
    names = sorted(shape_name(p) for p in mesh_files(require_data("smal_r_train")))

    def stem(n: str) -> str:
        return n.rstrip("0123456789").rstrip("_-").split("_")[0].lower()

    pairs = [(names[i], names[(i + 11) % len(names)]) for i in range(0, len(names), 3)]
    return [f"smal:{a}+{b}" for a, b in pairs if stem(a) != stem(b)]


def _tosca_test() -> list[str]:
    return [f"{a}-{b}" for a, b in read_test_pairs(require_data("tosca5k_dev") / "test_pairs.txt")]


def _faust(names: list[str]) -> list[str]:
    return [f"faust:{a[7:]}-{b[7:]}" for a, b in drawn_pairs(names, 40)]


#: ``@name`` -> the pair specs of a named set.
SETS = {
    "tosca_iso": lambda: list(TOSCA_ISO),  # 6 TOSCA test pairs within a class
    "tosca_noniso": lambda: list(TOSCA_NONISO),  # cat-lion and stretched TOSCA pairs
    "tosca_test": _tosca_test,  # tosca5k_dev/test_pairs.txt
    "faust_dev": lambda: _faust(FAUST_DEV),  # 40 pairs among tr_reg_060..079 (seed 0)
    "faust_val": lambda: _faust(FAUST_VAL),  # 40 pairs among tr_reg_070..079 (seed 0)
    "smal_cross": _smal_cross,
    "smal_val": lambda: [f"smal:{a}+{b}" for a, b in drawn_pairs(smal_split()[1], 10**6)],
    # 40 pairs among the animals of the two families no training animal of the split shares
    "smal_fval": lambda: [f"smal:{a}+{b}" for a, b in drawn_pairs(smal_family_split()[1], SMAL_FVAL_PAIRS)],
    **{
        name: (lambda name=name, val=val: [f"{name}:{a}+{b}" for a, b in drawn_pairs(val, 40)])
        for name, val in LOCAL_SETS.items()
    },
}


def expand(specs: list[str] | str) -> list[str]:
    """Pair specs with every ``@set`` / ``@set:N`` replaced by its pairs (:class:`Skip` where the
    set's data is absent)."""
    out: list[str] = []
    for spec in [specs] if isinstance(specs, str) else specs:
        if not spec.startswith("@"):
            out.append(spec)
            continue
        name, _, n = spec[1:].partition(":")
        if name not in SETS:
            raise SystemExit(f"unknown pair set {spec!r}: one of {', '.join('@' + s for s in SETS)}")
        out += SETS[name]()[: int(n) if n else None]
    return out


class Pair:
    """Source ``x``, target ``y``, their files (``path_x``, ``path_y``; None for a deformed copy),
    ground truth ``gt`` (a ``Correspondence``) and given landmarks (``fixed``, or None)."""

    def __init__(self, spec: str) -> None:
        self.name, self.fixed = spec, None
        self.path_y_deformed = False
        if spec == "demo":
            pa, pb, pgt = demo_pair_paths()
            self._load(pa, pb, gt_from_map(read_map(pgt)))
        elif spec == "cat-lion":
            folder = require_data("pyfm_cat_lion")
            self._load(
                folder / "cat-00.off", folder / "lion-00.off", gt_from_map(read_map(folder / "lion2cat"))
            )
            self.fixed = read_landmark_pairs(folder / "landmarks.txt")  # (cat, lion)
        elif ":" in spec:
            kind, names = spec.split(":", 1)
            if kind == "faust":
                a, b = (f"tr_reg_{n}" for n in names.split("-"))
                self._load_vts(require_data("faust_r_train"), a, b, ".off")
            elif kind == "smal":
                self._load_vts(require_data("smal_r_train"), *names.split("+"), ".off.gz")
            elif kind in LOCAL_SETS:
                folder = LOCAL_DATA_DIR / kind
                if not folder.exists():
                    raise Skip(f"{folder} not found (python -m tools.remesh --sets {kind} makes it)")
                self._load_vts(folder, *names.split("+"), ".off")
            else:
                raise SystemExit(f"unknown pair spec {spec!r} (see bench/pairs.py)")
        else:
            stretched = "~" in spec
            a, b = spec.replace("~", "-").split("-")
            self._load_vts(require_data("tosca5k_dev"), a, b, ".off")
            if stretched:
                self.y = stretch_deform(self.y, seed=zlib.crc32(b.encode()), strength=1.0)
                self.path_y = None
        self._rows: np.ndarray | None = None
        self._inverse: np.ndarray | None = None
        self.checked = False

    def _load(self, path_x: Path, path_y: Path, gt: Correspondence) -> None:
        self.path_x, self.path_y = Path(path_x), Path(path_y)
        self.x, self.y = torchfmap.load_mesh(path_x), torchfmap.load_mesh(path_y)
        self.gt = self.gt_all = gt

    def _load_vts(self, folder: Path, a: str, b: str, suffix: str) -> None:
        gt = vts_ground_truth(folder / "corres", a, b)
        self._load(folder / f"{a}{suffix}", folder / f"{b}{suffix}", gt)

    def subsample(self, every: int = 1, max_points: int | None = None) -> Pair:
        """Score only every ``every``-th ground-truth row, or a seeded random ``max_points`` of them."""
        idx_x, idx_y = self.gt
        idx_x, idx_y = idx_x[::every], idx_y[::every]
        if max_points and len(idx_y) > max_points:
            pick = np.sort(np.random.default_rng(0).choice(len(idx_y), max_points, replace=False))
            idx_x, idx_y = idx_x[pick], idx_y[pick]
        self.gt, self._rows = Correspondence(idx_x, idx_y), None
        return self

    def landmarks(self, n: int, use_fixed: bool = False) -> np.ndarray | None:
        """``(n, 2)`` pairs ``(x vertex, y vertex)``: the first ``n`` given ones when there are
        (cat-lion; all of them if ``use_fixed``), else ``n`` ground-truth rows spread by FPS;
        None for ``n = 0``."""
        if self.fixed is not None:
            return self.fixed if use_fixed else self.fixed[:n]
        return landmarks_from_gt(self.x, self.gt, n) if n else None

    def _distance_rows(self) -> None:
        t0 = time.perf_counter()
        uniq, self._inverse = np.unique(self.gt.idx_x, return_inverse=True)
        solver = torchfmap.GeodesicSolver(self.x)
        self._rows = np.vstack([solver.distances(uniq[s : s + 256]) for s in range(0, len(uniq), 256)])
        log(f"  {self.name}: {len(uniq)} geodesic distance rows in {time.perf_counter() - t0:.1f} s")

    def errors(self, p2p_yx: np.ndarray) -> np.ndarray:
        """Normalised geodesic errors at the ground-truth rows (distance rows computed once)."""
        idx_x, idx_y = self.gt
        p2p_yx = np.asarray(p2p_yx, dtype=np.int64)
        if p2p_yx.shape != (self.y.n_vertices,):
            raise RuntimeError(f"map of shape {p2p_yx.shape} is not p2p_yx ({self.y.n_vertices},)")
        if self._rows is None:
            self._distance_rows()
        pred = p2p_yx[idx_y]
        err = np.maximum(self._rows[self._inverse, pred], 0.0)
        err[pred == idx_x] = 0.0
        err /= np.sqrt(self.x.area)
        if not self.checked:  # the package's evaluation must agree
            report, ref = evaluate_map(self.x, self.y, p2p_yx, self.gt, max_points=None)
            log(f"  {self.name}: evaluate_map check: max |diff| {np.abs(ref - err).max():.2e}")
            self.checked = True
        return err

    def floor(self) -> float:
        """Mean :func:`torchfmap.evaluate.scores.error_floor` (normalised) of all the pair's ground truth, not
        the subsample scored (a subsample rarely holds the rows that share a vertex): what the best
        vertex-to-vertex map scores."""
        return float(error_floor(self.x, self.gt_all).mean())

    def free(self) -> None:
        """Drop the distance rows (memory)."""
        self._rows = None


# -- result rows ---------------------------------------------------------------------------------
def record(pair: Pair, method: str, refine: str | None, p2p, seconds: float, **extra) -> dict[str, Any]:
    """A result row: errors of ``p2p`` (mean, median, AUC on [0, 0.25]), time and the load."""
    err = pair.errors(p2p)
    row = {"pair": pair.name, "method": method, "refine": refine or "none", **extra}
    row |= {"mean": float(err.mean()), "median": float(np.median(err)), "auc": auc(err)}
    row |= {"time": seconds, "load": load1()}
    log(f"    {method:10s} {row['refine']:8s} mean {row['mean']:.4f}  AUC {row['auc']:.3f}  {seconds:6.2f} s")
    return row


ERRORS: list[str] = []  # tracebacks of unexpected exceptions, added to the report


def crash(label: str) -> None:
    """Log the current exception and keep it for the report's last section."""
    tb = traceback.format_exc()
    ERRORS.append(f"{label}:\n{tb}")
    log(tb)


def errors_section() -> str:
    return "### Unexpected exceptions\n\n" + "\n".join(f"```\n{e}```" for e in ERRORS) if ERRORS else ""


def run_match(
    pair: Pair, rows: list, method: str, refine: str | None, info: dict | None = None, **kwargs
) -> Any:
    """``torchfmap.match(pair.x, pair.y, refine=refine, **kwargs)``: appends the unrefined row
    (``p2p_yx_initial``; its time the wall time minus ``timings['refine']``) and, with a
    refinement, the refined row (``info``: more columns of both); ``K`` is the size ``match``
    used. A ParameterError is a ``'n/a'`` row, any other exception an ``'error'`` row (traceback
    kept). Returns the result, or None."""
    info = dict(info or {})
    try:
        t0 = time.perf_counter()
        res = torchfmap.match(pair.x, pair.y, refine=refine, **kwargs)
        wall = time.perf_counter() - t0
    except ParameterError as exc:
        log(f"    {method} n/a: {exc}")
        rows.append({"pair": pair.name, "method": method, "refine": refine or "none", **info, "note": "n/a"})
        return None
    except Exception:  # a crash: report it, keep benchmarking
        crash(f"{pair.name} {method} refine={refine}")
        rows.append(
            {"pair": pair.name, "method": method, "refine": refine or "none", **info, "note": "error"}
        )
        return None
    info |= {"K": res.basis_x.k, "kind": res.kind}
    rows.append(record(pair, method, None, res.p2p_yx_initial, wall - res.timings.get("refine", 0.0), **info))
    if refine:
        rows.append(record(pair, method, refine, res.p2p_yx, wall, **info))
    return res


def mean_of(rows: list[dict], pairs: list[str], key: str = "mean", scale: float = 100.0, **match) -> float:
    """Mean of ``key`` (x ``scale``) over the rows of ``pairs`` matching ``match``; NaN unless
    every pair has such a row."""
    got = [
        r[key]
        for r in rows
        if r["pair"] in pairs and key in r and all(r.get(k) == v for k, v in match.items())
    ]
    return float(np.mean(got)) * scale if got and len(got) == len(pairs) else float("nan")


# -- pyFM ---------------------------------------------------------------------------------------
#: Energy weights of pyFM's README example (cat -> lion with 20 landmarks, WKS descriptors).
PYFM_FIT = {"w_descr": 1e0, "w_lap": 1e-2, "w_dcomm": 1e-1, "w_orient": 0.0}
#: pyFM's quick-start pipeline: 100 WKS energies on 128 eigenpairs, every 2nd kept, descriptor,
#: Laplacian, descriptor-commutativity and orientation terms (far stronger on humans).
PYFM_QUICKSTART = dict(
    n_descr=100, k_descr=128, subsample_step=2, fit=dict(w_descr=1, w_lap=0.1, w_dcomm=1, w_orient=1)
)


def pyfm_missing() -> str:
    """``''`` when pyFM (PyPI ``pyfmaps``) is importable, else the note a report prints."""
    try:
        found = importlib.util.find_spec("pyFM") is not None
    except (ImportError, ValueError):  # blocked (sys.modules entry None) or broken
        found = False
    if not found:
        return "pyFM (PyPI pyfmaps) is not installed: its rows are left out (pip install pyfmaps)."
    return ""


@dataclass
class PyfmRun:
    """Point maps (``p2p_yx``) and wall times of one pyFM pipeline, per refinement."""

    p2p: dict[str | None, np.ndarray] = field(default_factory=dict)
    #: total seconds of the pipeline ending with each refinement (None: no refinement).
    times: dict[str | None, float] = field(default_factory=dict)
    #: seconds of the phases: preprocess (eigenpairs + descriptors), fit, p2p, icp, zoomout.
    phases: dict[str, float] = field(default_factory=dict)
    n_descr: int = 0
    k_process: int = 0


def run_pyfm(
    mesh_x,
    mesh_y,
    *,
    k: int,
    landmarks=None,
    refine: tuple[str, ...] = ("icp", "zoomout"),
    n_descr: int = 50,
    k_descr: int = 50,
    subsample_step: int = 1,
    zoomout_samples: int = 2000,
    fit: dict | None = None,
) -> PyfmRun:
    """pyFM's whole pipeline: ``TriMesh`` -> ``preprocess`` (WKS) -> ``fit`` -> ``get_p2p`` [-> refine].

    Direction: pyFM's ``mesh1`` is our ``x``, its ``FM_12`` is ``(k2, k1)`` like our ``C_xy`` and
    ``get_p2p()`` returns our ``p2p_yx``; landmarks ``(L, 2)`` go to ``preprocess(landmarks=)``
    with column 0 on ``mesh1``. Refinements, each from the fitted ``FM_12``: ``'icp'``
    (``icp_refine(nit=10)``), ``'zoomout'`` (``zoomout_refine(nit=10, step=k // 10)``: k -> 2k
    like ``match``), ``'zoomout-sub'`` (the same on ``zoomout_samples`` FPS samples). One
    preprocess serves all (``k_process``: the eigenpairs ZoomOut needs, at least ``k_descr``).
    """
    from pyFM.functional import FunctionalMapping
    from pyFM.mesh import TriMesh

    step = max(1, k // 10)
    k_process = max(k + 10 * step if any(r.startswith("zoomout") for r in refine) else k, k_descr)
    run = PyfmRun(k_process=k_process)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        t0 = time.perf_counter()
        m1 = TriMesh(np.array(mesh_x.vertices), np.array(mesh_x.faces))
        m2 = TriMesh(np.array(mesh_y.vertices), np.array(mesh_y.faces))
        model = FunctionalMapping(m1, m2)
        model.preprocess(
            n_descr=n_descr,
            descr_type="WKS",
            landmarks=None if landmarks is None else np.asarray(landmarks),
            subsample_step=subsample_step,
            k_process=k_process,
            k_descr=k_descr,
        )
        t1 = time.perf_counter()
        model.fit(K=(k, k), **(PYFM_FIT if fit is None else fit))
        t2 = time.perf_counter()
        run.p2p[None] = np.asarray(model.get_p2p(), dtype=np.int64)
        t3 = time.perf_counter()
        run.phases = {"preprocess": t1 - t0, "fit": t2 - t1, "p2p": t3 - t2}
        run.times[None] = t3 - t0
        run.n_descr = model.descr1.shape[1]
        for r in refine:
            t0 = time.perf_counter()
            if r == "icp":
                fm = model.icp_refine(nit=10)
            elif r == "zoomout":
                fm = model.zoomout_refine(nit=10, step=step)
            else:  # zoomout-sub
                fm = model.zoomout_refine(nit=10, step=step, subsample=zoomout_samples)
            run.p2p[r] = np.asarray(model.get_p2p(fm), dtype=np.int64)
            run.phases[r] = time.perf_counter() - t0
            run.times[r] = run.times[None] + run.phases[r]
    for p2p in run.p2p.values():
        if p2p.shape != (mesh_y.n_vertices,) or p2p.max() >= mesh_x.n_vertices:
            raise RuntimeError(f"pyFM returned a map of shape {p2p.shape}: not p2p_yx (direction?)")
    return run


def pyfm_rows(pair: Pair, rows: list, k: int, landmarks, refines, method: str = "pyFM", **settings) -> None:
    """Append the rows of one pyFM pipeline (preprocess + fit, then each refinement)."""
    extra = tuple(r for r in refines if r is not None)
    try:
        run = run_pyfm(pair.x, pair.y, k=k, landmarks=landmarks, refine=extra, **settings)
    except Exception:
        crash(f"{pair.name} pyFM")
        rows += [
            {"pair": pair.name, "method": method, "refine": r or "none", "note": "error"} for r in refines
        ]
        return
    info = {"K": k, "n_descr": run.n_descr, "k_process": run.k_process}
    info |= {f"t_{key}": val for key, val in run.phases.items()}
    rows += [record(pair, method, r, run.p2p[r], run.times[r], **info) for r in refines]
