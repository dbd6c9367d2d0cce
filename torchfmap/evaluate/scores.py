"""Evaluation against ground truth (re-exported from :mod:`torchfmap.evaluate.ground_truth`): geodesic errors
on the source ``x`` over ``sqrt(area_x)``, PCK, coverage, smoothness, shape distances, pair discovery."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .._util.checks import check_p2p
from ..errors import ParameterError
from ..io import find_file, mesh_files, read_arrays, read_test_pairs, shape_name
from ..mesh import Mesh
from ..operators.geodesic import DistanceRows, GeodesicSolver
from .ground_truth import Correspondence, as_correspondence, gt_identity, vts_ground_truth
from .ground_truth import gt_from_map as gt_from_map
from .ground_truth import gt_from_vts as gt_from_vts
from .ground_truth import landmarks_from_gt as landmarks_from_gt

#: ``max_points='auto'`` scores every ground-truth point on source meshes of at most this many vertices ...
FULL_EVAL_VERTICES = 10_000
#: ... and on larger ones this many, drawn uniformly without replacement (seeded).
SAMPLED_EVAL_POINTS = 500
#: Distance rows solved at once (bounds the memory).
ROWS_PER_BATCH = 256


def evaluated_rows(n_rows: int, n_source: int, max_points="auto", seed: int = 0) -> np.ndarray | None:
    """Sorted indices of the ``n_rows`` ground-truth rows :func:`geodesic_errors` scores, or None for all.
    ``max_points``: ``'auto'`` (all if ``n_source`` <= :data:`FULL_EVAL_VERTICES`, else
    :data:`SAMPLED_EVAL_POINTS`), None, or an int >= 1 (a sample by ``numpy.random.default_rng(seed)``).

    Raises:
        ParameterError: ``max_points`` none of these."""
    if isinstance(max_points, str) and max_points == "auto":
        max_points = None if n_source <= FULL_EVAL_VERTICES else SAMPLED_EVAL_POINTS
    integer = isinstance(max_points, (int, np.integer)) and not isinstance(max_points, bool)
    if max_points is not None and not (integer and max_points >= 1):
        raise ParameterError(
            f"max_points must be 'auto', None (every point) or an int >= 1, got {max_points!r}. Fix: "
            "e.g. max_points=None to score every ground-truth point (CLI: --max-points all)."
        )
    if max_points is None or n_rows <= max_points:
        return None
    return np.sort(np.random.default_rng(seed).choice(n_rows, int(max_points), replace=False))


def geodesic_errors(
    mesh_x: Mesh,
    p2p_yx: np.ndarray,
    gt: Correspondence,
    *,
    solver: GeodesicSolver | DistanceRows | None = None,
    normalize: bool = True,
    max_points="auto",
    seed: int = 0,
    progress: bool = False,
) -> np.ndarray:
    """Geodesic errors on ``mesh_x`` of ``p2p_yx`` ``(V_y,)`` at the pairs of ``gt`` (a
    :class:`Correspondence`): ``(P,)``, or ``(n,)`` for a sample (:func:`evaluated_rows`). ``solver``: a
    :class:`GeodesicSolver` or :class:`~torchfmap.operators.DistanceRows` of ``mesh_x``; ``normalize``: over
    ``sqrt(area_x)``.

    Raises:
        ParameterError: a map or ground truth that does not fit the meshes, or a bad ``max_points``."""
    idx_x, idx_y = as_correspondence(gt, mesh_x.n_vertices)
    p2p_yx = check_p2p(p2p_yx, None, mesh_x.n_vertices, "p2p_yx")
    if idx_y.size and (idx_y.max() >= len(p2p_yx) or idx_y.min() < 0):
        raise ParameterError("ground truth refers to target vertices outside the map. Fix: check the files.")
    pick = evaluated_rows(len(idx_y), mesh_x.n_vertices, max_points, seed)
    if pick is not None:
        idx_y, idx_x = idx_y[pick], idx_x[pick]
    pred = p2p_yx[idx_y]
    solver = solver or GeodesicSolver(mesh_x)
    errors = np.empty(len(idx_x))
    uniq, inverse = np.unique(idx_x, return_inverse=True)
    step = ROWS_PER_BATCH
    with tqdm(total=len(uniq), desc="scoring", unit="row", leave=False, disable=not progress) as bar:
        for start in range(0, len(uniq), step):
            rows = solver.distances(uniq[start : start + step])
            sel = np.flatnonzero((inverse >= start) & (inverse < start + step))
            errors[sel] = rows[inverse[sel] - start, pred[sel]]
            bar.update(len(rows))
    errors = np.maximum(errors, 0.0)
    errors[pred == idx_x] = 0.0
    return errors / np.sqrt(mesh_x.area) if normalize else errors


def error_floor(
    mesh_x: Mesh,
    gt: Correspondence,
    *,
    solver: GeodesicSolver | DistanceRows | None = None,
    normalize: bool = True,
) -> np.ndarray:
    """``(P,)`` the error no vertex-to-vertex map avoids against ``gt`` (rows sharing a target vertex:
    distance to their best common source; an upper bound). ``solver``, ``normalize`` as
    :func:`geodesic_errors`."""
    idx_x, idx_y = as_correspondence(gt, mesh_x.n_vertices)
    floor = np.zeros(len(idx_x))
    order = np.argsort(idx_y, kind="stable")
    groups = [
        g for g in np.split(order, np.flatnonzero(np.diff(idx_y[order])) + 1) if len(np.unique(idx_x[g])) > 1
    ]  # fmt: skip
    cands = [np.unique(idx_x[g]) for g in groups]
    table = [np.zeros((len(g), len(c))) for g, c in zip(groups, cands, strict=True)]
    wanted: dict[int, list[int]] = {}  # source vertex -> the groups whose rows it is
    for n in range(len(groups)):
        for c in cands[n].tolist():
            wanted.setdefault(c, []).append(n)
    solver = solver or GeodesicSolver(mesh_x)
    sources = np.fromiter(wanted, dtype=np.int64, count=len(wanted))
    for start in range(0, len(sources), ROWS_PER_BATCH):
        batch = sources[start : start + ROWS_PER_BATCH]
        for row, x in zip(np.maximum(solver.distances(batch), 0.0), batch.tolist(), strict=True):
            for n in wanted[x]:
                at = idx_x[groups[n]] == x
                table[n][at] = row[cands[n]]
                table[n][at, cands[n] == x] = 0.0
    for g, t in zip(groups, table, strict=True):
        floor[g] = t[:, np.argmin(t.mean(axis=0))]
    return floor / np.sqrt(mesh_x.area) if normalize else floor


def pck_curve(errors: np.ndarray, thresholds=None) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative accuracy: fraction of errors ``<= thr`` for each threshold ``(T,)``."""
    errors = np.asarray(errors, dtype=np.float64)
    thresholds = np.linspace(0, 0.25, 101) if thresholds is None else np.asarray(thresholds, dtype=np.float64)
    return thresholds, (errors[None, :] <= thresholds[:, None]).mean(axis=1)


def auc(errors: np.ndarray, max_threshold: float = 0.25) -> float:
    """Area under the PCK curve on ``[0, max_threshold]``, normalised to ``[0, 1]``."""
    thr, acc = pck_curve(errors, np.linspace(0, max_threshold, 201))
    return float(np.trapezoid(acc, thr) / max_threshold)


def coverage(p2p_yx: np.ndarray, n_x: int) -> float:
    """Fraction of source vertices hit by the map (1 for a surjective map)."""
    return float(len(np.unique(p2p_yx)) / n_x)


def bijectivity_error(
    mesh_y: Mesh, p2p_yx: np.ndarray, p2p_xy: np.ndarray, *, max_points: int | None = 2000, seed: int = 0
) -> float:
    """Mean normalised geodesic distance on ``y`` between ``v`` and ``p2p_xy[p2p_yx[v]]``."""
    back = np.asarray(p2p_xy)[np.asarray(p2p_yx)]
    gt = Correspondence(np.arange(mesh_y.n_vertices), back)
    errs = geodesic_errors(mesh_y, np.arange(mesh_y.n_vertices), gt, max_points=max_points, seed=seed)
    return float(errs.mean())


def smoothness(mesh_x: Mesh, mesh_y: Mesh, p2p_yx: np.ndarray) -> float:
    """Mean edge stretch of ``p2p_yx`` over ``y``'s edges, lengths over ``sqrt(area)`` (1: an isometry)."""
    e = mesh_y.edges
    p = np.asarray(p2p_yx)
    src = np.linalg.norm(mesh_x.vertices[p[e[:, 0]]] - mesh_x.vertices[p[e[:, 1]]], axis=1)
    dst = mesh_y.edge_lengths
    return float(np.mean((src / np.sqrt(mesh_x.area)) / (dst / np.sqrt(mesh_y.area))))


@dataclass
class MapReport:
    """Summary numbers of one map; ``n_points`` of ``n_total`` points scored, ``mean_error_se``: its SE."""

    mean_error: float
    median_error: float
    auc: float
    coverage: float
    smoothness: float
    n_points: int = 0
    n_total: int = 0
    mean_error_se: float = 0.0

    def sampling(self) -> str:
        """The points scored, in words, e.g. ``'500 of 69474 points (mean ± 0.0009)'``."""
        if not 0 < self.n_points < self.n_total:
            return f"all {self.n_total} points" if self.n_total else "all points"
        return f"{self.n_points} of {self.n_total} points (mean ± {self.mean_error_se:.4f})"

    def row(self) -> str:
        return (
            f"{self.mean_error:.4f}  {self.median_error:.4f}  {self.auc:.3f}  {self.coverage:.3f}  "
            f"{self.smoothness:.2f}"
        )


def evaluate_map(mesh_x: Mesh, mesh_y: Mesh, p2p_yx, gt, **kwargs) -> tuple[MapReport, np.ndarray]:
    """``(MapReport, errors)`` of ``p2p_yx`` against ``gt``; ``kwargs``: those of :func:`geodesic_errors`.

    Raises:
        ParameterError: ``p2p_yx`` not one vertex of ``mesh_x`` per vertex of ``mesh_y``."""
    p2p_yx = np.asarray(p2p_yx)
    if p2p_yx.shape != (mesh_y.n_vertices,):
        raise ParameterError(
            f"p2p_yx must have one entry per vertex of mesh_y ({mesh_y.n_vertices}), got shape "
            f"{p2p_yx.shape}. Fix: p2p_yx[v] is the vertex of x matched to vertex v of y"
            + (" (this looks like a map x -> y)." if p2p_yx.shape == (mesh_x.n_vertices,) else ".")
        )
    errors = geodesic_errors(mesh_x, p2p_yx, gt, **kwargs)
    n, total = len(errors), len(gt[0])  # the standard error of n drawn without replacement
    se = float(np.std(errors, ddof=1) / np.sqrt(n) * np.sqrt(1 - n / total)) if 1 < n < total else 0.0
    report = MapReport(
        float(errors.mean()),
        float(np.median(errors)),
        auc(errors),
        coverage(p2p_yx, mesh_x.n_vertices),
        smoothness(mesh_x, mesh_y, p2p_yx),
        n,
        total,
        se,
    )
    return report, errors


def shape_difference(C_xy: np.ndarray, W_x=None, W_y=None, form: str = "area") -> np.ndarray:
    """``(K_x, K_x)`` shape difference (Rustamov et al. 2013): ``'area'`` ``C_xyᵀ C_xy``, ``'conformal'``
    ``W_x⁺ C_xyᵀ W_y C_xy``.

    Raises:
        ParameterError: an unknown ``form``, or ``'conformal'`` without ``W_x`` and ``W_y``."""
    C = np.asarray(C_xy, dtype=np.float64)
    if form == "area":
        return C.T @ C
    if form == "conformal":
        if W_x is None or W_y is None:
            raise ParameterError("the conformal shape difference needs W_x and W_y (projected Laplacians).")
        return np.linalg.pinv(W_x, rcond=1e-10, hermitian=True) @ C.T @ W_y @ C
    raise ParameterError(f"unknown shape difference form {form!r}. Fix: 'area' or 'conformal'.")


def shape_distance(C_xy: np.ndarray, W_x=None, W_y=None, form: str = "area") -> float:
    """``‖D - I‖_F / sqrt(K)`` of :func:`shape_difference` ``D``: 0 for isometric shapes."""
    D = shape_difference(C_xy, W_x, W_y, form)
    return float(np.linalg.norm(D - np.eye(len(D))) / np.sqrt(len(D)))


def retrieval_accuracy(distances: np.ndarray, labels) -> float:
    """Leave-one-out nearest-neighbour class accuracy of a ``(N, N)`` distance matrix.

    Raises:
        ParameterError: ``distances`` not ``(N, N)``."""
    D = np.array(distances, dtype=np.float64)
    labels = np.asarray(labels)
    if D.shape != (len(labels), len(labels)):
        raise ParameterError(f"distances must be (N, N) with N={len(labels)}, got {D.shape}.")
    np.fill_diagonal(D, np.inf)
    return float(np.mean(labels[np.argmin(D, axis=1)] == labels))


#: The pair protocols of :func:`discover_pairs` (or a test-pairs file's path).
PAIR_PROTOCOLS = ("auto", "consecutive", "all")
#: Sub-folders of a data set that hold its meshes (beside ``corres/``).
MESH_SUBFOLDERS = ("shapes_test", "shapes_train", "off", "shapes")


def _data_set_places(folder: Path) -> tuple[Path, ...]:
    """Where ``corres/`` and ``test_pairs.txt`` may be: the folder (and its parent, for a sub-folder)."""
    return (folder, folder.parent) if folder.name in MESH_SUBFOLDERS else (folder,)


def select_pairs(folder: str | os.PathLike, pairs="auto") -> tuple[list[tuple[str, str]], str]:
    """``(pairs, protocol)``: the ordered ``(name_x, name_y)`` pairs of a folder's meshes and a sentence
    saying which. ``pairs``: ``'auto'`` (a ``test_pairs.txt`` in or beside the folder, else consecutive),
    ``'consecutive'``, ``'all'``, or a test-pairs file.

    Raises:
        ParameterError: fewer than two meshes, an unknown protocol, or a pairs file naming absent meshes."""
    folder = Path(folder)
    names = [shape_name(p) for p in mesh_files(folder)]
    if len(names) < 2:
        subs = [d.name for d in (folder / n for n in MESH_SUBFOLDERS) if d.is_dir() and mesh_files(d)]
        fix = (
            f"this is a data set whose meshes are in {', '.join(subs)}: point to one, e.g. "
            f"{folder / subs[0]} (its corres/ beside it is read)"
            if subs
            else "point to a folder of meshes (.off/.ply/.obj/.stl, optionally .gz)"
        )
        raise ParameterError(f"{folder} holds {len(names)} meshes, at least two are needed. Fix: {fix}.")
    if pairs == "auto":
        found = (find_file(place, "test_pairs.txt") for place in _data_set_places(folder))
        pairs = next((f for f in found if f is not None), "consecutive")
    n = len(names)
    if pairs == "consecutive":
        chosen = list(zip(names[:-1], names[1:], strict=True))
        return chosen, (
            f"{len(chosen)} consecutive pairs of {n} meshes in name order (of {n * (n - 1)} ordered "
            "pairs: --pairs all for every one, or a test_pairs.txt)"
        )
    if pairs == "all":
        chosen = [(a, b) for a in names for b in names if a != b]
        return chosen, f"all {len(chosen)} ordered pairs of {n} meshes"
    if isinstance(pairs, str) and pairs in PAIR_PROTOCOLS or not isinstance(pairs, (str, os.PathLike)):
        raise ParameterError(f"unknown pairs {pairs!r}. Fix: 'auto', 'consecutive', 'all' or a pairs file.")
    path = Path(pairs)
    if not path.exists():
        raise ParameterError(
            f"pairs={str(pairs)!r} is neither a protocol nor an existing file. Fix: 'auto', 'consecutive', "
            "'all', or the path of a test-pairs file ('source target' per line)."
        )
    chosen = read_test_pairs(path)
    missing = sorted({m for pair in chosen for m in pair} - set(names))
    if missing:
        raise ParameterError(
            f"{path.name} names {missing[:5]}, which {folder} does not hold. Fix: add the meshes or remove "
            "those lines."
        )
    return chosen, f"the {len(chosen)} pairs listed in {path.name}"


def discover_pairs(folder: str | os.PathLike, identity: bool | None = None, pairs="auto"):
    """Yields ``(name_x, name_y, path_x, path_y, gt)`` of a data folder (pairs: :func:`select_pairs`); ``gt``
    from ``corres/<name>.vts`` in or beside it, else the identity where vertex counts match and ``identity``
    is True, or (None) the face lists match too.

    Raises:
        ParameterError: as :func:`select_pairs`, or a pair without ground truth."""
    folder = Path(folder)
    meshes = {shape_name(p): p for p in mesh_files(folder)}
    chosen, _ = select_pairs(folder, pairs)
    corres = next((p / "corres" for p in _data_set_places(folder) if (p / "corres").is_dir()), None)
    for a, b in chosen:
        if corres is not None:
            gt = vts_ground_truth(corres, a, b)
        else:
            (va, fa), (vb, fb) = read_arrays(meshes[a]), read_arrays(meshes[b])
            same = len(va) == len(vb) and (identity or (identity is None and np.array_equal(fa, fb)))
            if not same:
                if len(va) != len(vb):
                    why, fix = "their vertex counts differ", "."
                else:
                    why = "their face lists differ"
                    fix = (
                        ", or, if the meshes do share vertex order, pass identity=True (CLI: --gt identity)."
                    )
                raise ParameterError(
                    f"no ground truth for {a}/{b}: no corres/ folder, and {why}, so vertex i of one need "
                    f"not be vertex i of the other. Fix: add corres/<name>.vts files{fix}"
                )
            gt = gt_identity(len(va))
        yield a, b, meshes[a], meshes[b], gt
