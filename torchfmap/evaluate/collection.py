"""Evaluating a collection of pairs: each mesh prepared once, pairs matched by a *matcher*
(:func:`torchfmap.match`, :class:`torchfmap.nn.LearnedMatcher`, :class:`MapFiles`) and scored, in one process,
a local process pool or any ``concurrent.futures`` executor."""

from __future__ import annotations

import inspect
import multiprocessing
import os
import pickle
import shutil
import signal
import tempfile
import time
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import NamedTuple

import numpy as np
from tqdm import tqdm

from .._util.checks import check_count
from .._util.files import atomic_write
from .._util.threads import thread_limit
from ..bases.prepared import prepare_shape
from ..errors import EvaluationInterrupted, ParameterError, WorkerLost
from ..io import find_file, load_mesh, read_landmark_pairs, read_map, shape_name
from ..matching.pipeline import match
from ..mesh import Mesh
from ..operators.geodesic import DistanceRows
from .partial import overlap_iou, part_radius
from .scores import evaluate_map, landmarks_from_gt, shape_distance


class PairResult(NamedTuple):
    """One scored pair: names, the :func:`~.scores.evaluate_map` report, errors, seconds, overlap IoU."""

    source: str
    target: str
    report: object
    errors: np.ndarray
    seconds: float
    iou: float | None = None


#: Distance rows :func:`evaluate_pairs` keeps for the current source mesh (bytes).
EVAL_ROWS_BYTES = 512 * 2**20
#: Cost of a source's scoring rows in units of one pair's match, for balancing a pool's chunks.
SOURCE_COST = 5.0

# A local pool worker's prepared shapes, kept across its chunks (set by the pool's initializer).
_POOL_SHAPES: dict | None = None


class _PairFiles:
    """Files of a folder named per pair, ``folder/<name_x>-<name_y>.txt`` (or ``.gz``); picklable."""

    what = "file"

    def __init__(self, folder) -> None:
        self.folder = Path(folder).resolve()
        if not self.folder.is_dir():
            raise ParameterError(
                f"{self.what} folder {str(folder)!r} is not a folder. Fix: the folder of "
                "<source>-<target>.txt files."
            )

    def path(self, path_x, path_y, fix: str) -> Path:
        """The file of the pair, or :class:`ParameterError` naming the expected file and ``fix``."""
        name = f"{shape_name(path_x)}-{shape_name(path_y)}.txt"
        found = find_file(self.folder, name)
        if found is None:
            raise ParameterError(f"no {self.what} {name} (or {name}.gz) in {self.folder}. Fix: {fix}")
        return found


class SavedMap(NamedTuple):
    """What :class:`MapFiles` returns for a pair: the map ``p2p_yx (V_y,)`` read from ``path``."""

    p2p_yx: np.ndarray
    path: Path


class MapFiles(_PairFiles):
    """A matcher reading saved maps ``folder/<name_x>-<name_y>.txt`` (or ``.txt.gz``; the meshes' ``name``),
    as ``torchfmap match --out`` writes them. Picklable.

    Raises (when called):
        ParameterError: an unnamed mesh, no map file for a pair, or a map that does not fit."""

    what = "saved map"

    def __call__(self, mesh_x: Mesh, mesh_y: Mesh, *, shapes=None) -> SavedMap:
        if not (mesh_x.name and mesh_y.name):
            raise ParameterError(
                "saved maps are found by the meshes' names, and a mesh has none. Fix: load the meshes "
                "with load_mesh (named after their files), or set Mesh(..., name=...)."
            )
        fix = "write it with `torchfmap match SOURCE TARGET --out` there, or drop --maps to match here."
        path = self.path(mesh_x.name, mesh_y.name, fix)
        p2p = read_map(path)
        if len(p2p) != mesh_y.n_vertices:
            raise ParameterError(
                f"{path.name} has {len(p2p)} lines but {mesh_y.name} has {mesh_y.n_vertices} "
                "vertices. Fix: one line per target vertex (the map target -> source)."
            )
        return SavedMap(p2p, path)


class LandmarkFiles(_PairFiles):
    """:func:`evaluate_pairs`'s ``gt_landmarks`` read from ``folder/<name_x>-<name_y>.txt`` (or ``.gz``), one
    ``source target`` vertex pair per line. Picklable.

    Raises (when called): ParameterError (a missing file), or as :func:`~torchfmap.io.read_landmark_pairs`."""

    what = "landmark file"

    def __call__(self, path_x, path_y) -> np.ndarray:
        return read_landmark_pairs(self.path(path_x, path_y, "add it."))


def pool_threads(workers: int) -> int:
    """Threads per worker of a local pool when none are given: the CPUs shared out."""
    return max(1, (os.cpu_count() or 1) // workers)


def _init_pool_worker() -> None:
    global _POOL_SHAPES
    _POOL_SHAPES = {}
    # Ctrl-C reaches the whole process group: the parent alone answers it
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _stop_pool(pool: ProcessPoolExecutor) -> None:
    """End a local pool now: pending chunks cancelled, running workers terminated."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    for process in processes:
        process.terminate()
    pool.shutdown(wait=False, cancel_futures=True)
    deadline = time.monotonic() + 2.0
    for process in processes:
        process.join(timeout=max(0.0, deadline - time.monotonic()))


def _evaluate_chunk(
    pairs,
    gt_landmarks: int,
    max_points,
    match_kwargs: dict,
    shapes=None,
    on_pair=None,
    threads=None,
    matcher=None,
    results: list | None = None,
    progress: bool = False,
) -> list[PairResult]:
    """Match and score ``pairs`` in order, each mesh prepared once; results appended to ``results``."""
    if shapes is None:
        shapes = _POOL_SHAPES if _POOL_SHAPES is not None else {}
    matcher = match if matcher is None else matcher
    with thread_limit(threads):
        out = [] if results is None else results
        rows = None  # distance rows of the current source mesh, shared by its consecutive pairs
        for a, b, pa, pb, gt in pairs:
            for path in (pa, pb):
                if path not in shapes:
                    mesh = load_mesh(path)
                    shapes[path] = (mesh, prepare_shape(mesh, 0))
            (x, sx), (y, sy) = shapes[pa], shapes[pb]
            settings = match_kwargs
            if isinstance(gt_landmarks, LandmarkFiles):
                settings = {**settings, "landmarks": gt_landmarks(pa, pb)}
            elif gt_landmarks:
                settings = {**settings, "landmarks": landmarks_from_gt(x, gt, gt_landmarks)}
            t0 = time.perf_counter()
            result = matcher(x, y, shapes=(sx, sy), **settings)
            seconds = time.perf_counter() - t0
            p2p, overlap = result.p2p_yx, getattr(result, "overlap", None)
            iou = None
            if overlap is not None:
                radius = part_radius(sy.mesh.vertices, sy.mesh.faces)
                iou = overlap_iou(overlap, gt.idx_x, sx.operators[1], points=sx.mesh.vertices, radius=radius)
            if rows is None or rows.solver is not sx.distances.solver:
                rows = DistanceRows(x, sx.distances.solver, max_bytes=EVAL_ROWS_BYTES)
            scored = {"max_points": max_points, "solver": rows, "progress": progress}
            report, errors = evaluate_map(x, y, p2p, gt, **scored)
            out.append(PairResult(a, b, report, errors, seconds, iou))
            if on_pair is not None:
                on_pair()
        return out


def _evaluate_chunk_to_file(folder: str, index: int, pairs, *args, **kwargs) -> str:
    """A pool's chunk: :func:`_evaluate_chunk`'s results pickled to a file in ``folder``; returns its path."""
    results = _evaluate_chunk(pairs, *args, **kwargs)
    path = os.path.join(folder, f"chunk{index}.pkl")
    atomic_write(path, lambda fh: pickle.dump(results, fh, protocol=pickle.HIGHEST_PROTOCOL))
    return path


def _read_chunk(path: str) -> list[PairResult]:
    with open(path, "rb") as f:
        results = pickle.load(f)
    os.remove(path)
    return results


def _check_matcher(matcher, settings: dict) -> None:
    """Refuse, before any work, settings that ``matcher`` does not take (named, with the fix)."""
    try:
        parameters = inspect.signature(matcher).parameters
    except (TypeError, ValueError):
        return
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        return
    unknown = sorted(set(settings) - set(parameters))
    if unknown:
        name = getattr(matcher, "__name__", type(matcher).__name__)
        raise ParameterError(
            f"the matcher {name} does not take {', '.join(unknown)}. Fix: drop them, or pass the "
            "settings this matcher takes (with no matcher, match()'s)."
        )


def _chunk_costs(pairs: list) -> np.ndarray:
    """Estimated cost of each pair: one match, plus :data:`SOURCE_COST` where the source changes."""
    new_source = [i == 0 or pairs[i][2] != pairs[i - 1][2] for i in range(len(pairs))]
    return 1.0 + SOURCE_COST * np.asarray(new_source, dtype=float)


def _source_chunks(pairs: list, n_chunks: int) -> list[list]:
    """``pairs`` in at most ``n_chunks`` contiguous chunks of similar cost, cut where the source changes."""
    edges = [0] + [i for i in range(1, len(pairs)) if pairs[i][2] != pairs[i - 1][2]] + [len(pairs)]
    cumulative = np.concatenate([[0.0], np.cumsum(_chunk_costs(pairs))])
    target = np.linspace(0.0, cumulative[-1], n_chunks + 1)[1:-1]
    cuts = sorted({min(edges, key=lambda e, t=t: abs(cumulative[e] - t)) for t in target} - {0, len(pairs)})
    bounds = [0, *cuts, len(pairs)]
    return [pairs[lo:hi] for lo, hi in zip(bounds[:-1], bounds[1:], strict=True) if hi > lo]


def evaluate_pairs(
    pairs,
    *,
    gt_landmarks: int = 0,
    max_points="auto",
    workers: int = 1,
    threads: int | None = None,
    executor: Executor | None = None,
    progress: bool = False,
    matcher=None,
    on_results=None,
    **match_kwargs,
) -> list[PairResult]:
    """Match and score every pair ``(name_x, name_y, path_x, path_y, gt)`` (as
    :func:`~torchfmap.evaluate.scores.discover_pairs` yields them), in order. With ``workers > 1`` contiguous
    chunks run on a local spawned process pool, or on ``executor`` (a :class:`concurrent.futures.Executor`);
    results depend on ``threads`` only.

    Args:
        gt_landmarks: this many ground-truth pairs as landmarks
            (:func:`~torchfmap.evaluate.scores.landmarks_from_gt`; 0: none), or a :class:`LandmarkFiles`.
        max_points: the points scored per pair (:func:`~torchfmap.evaluate.scores.evaluated_rows`).
        workers: local worker processes (1: this process).
        threads: threads per worker (None: as is for one worker, else :func:`pool_threads` or the executor's).
        matcher: ``matcher(mesh_x, mesh_y, *, shapes=(shape_x, shape_y), **match_kwargs)`` returning a result
            with ``p2p_yx`` (None: :func:`~torchfmap.match`); it must pickle for a pool.
        on_results: called with each finished pair's or chunk's :class:`PairResult` list (raising stops all).

    Raises:
        ParameterError: ``workers < 1`` or ``threads < 1``, or settings the matcher does not take.
        EvaluationInterrupted: Ctrl-C; ``finished`` holds the pairs scored.
        WorkerLost: a worker process died; ``finished`` holds the pairs scored."""
    pairs = list(pairs)
    _check_matcher(match if matcher is None else matcher, {
        **match_kwargs, **({"landmarks": None} if gt_landmarks else {})
    })  # fmt: skip
    workers = check_count(workers, 1, 4096, "workers")
    if threads is not None:
        threads = check_count(threads, 1, 4096, "threads")
    elif executor is None and workers > 1:
        threads = pool_threads(workers)
    bar = tqdm(total=len(pairs), desc="pairs", unit="pair", disable=not progress)
    if executor is None and workers == 1:
        finished: list[PairResult] = []

        def on_pair() -> None:
            bar.update()
            if on_results is not None:
                on_results(finished[-1:])

        try:
            return _evaluate_chunk(
                pairs, gt_landmarks, max_points, match_kwargs, on_pair=on_pair, threads=threads,
                matcher=matcher, results=finished, progress=progress,
            )  # fmt: skip
        except KeyboardInterrupt:
            raise EvaluationInterrupted(finished, len(pairs)) from None
        finally:
            bar.close()
    own = executor is None
    chunks = _source_chunks(pairs, min(len(pairs), 4 * workers))
    # spawned, not forked: a forked child can deadlock on torch's or BLAS's thread-pool locks
    spawn = multiprocessing.get_context("spawn")
    pool = executor
    if own:
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=spawn, initializer=_init_pool_worker)
    order = sorted(range(len(chunks)), key=lambda i: -float(_chunk_costs(chunks[i]).sum()))
    futures: dict = {}
    done: dict[int, list[PairResult]] = {}
    local = isinstance(pool, ProcessPoolExecutor)
    folder = tempfile.mkdtemp(prefix="torchfmap-chunks-") if local else None
    try:
        args = (gt_landmarks, max_points, match_kwargs)
        for i in order:
            if local:
                task = (_evaluate_chunk_to_file, folder, i, chunks[i], *args)
            else:
                task = (_evaluate_chunk, chunks[i], *args)
            futures[pool.submit(*task, threads=threads, matcher=matcher)] = i
        for future in as_completed(futures):
            i = futures[future]
            done[i] = _read_chunk(future.result()) if folder else future.result()
            bar.update(len(chunks[i]))
            if on_results is not None:
                on_results(done[i])
    except BaseException as err:  # stop the pool at once, whatever ended the run
        if own:
            _stop_pool(pool)
            own = False  # stopped: nothing left to wait for
        else:
            for future in futures:
                future.cancel()
        finished = [r for i in sorted(done) for r in done[i]]
        if isinstance(err, KeyboardInterrupt):
            raise EvaluationInterrupted(finished, len(pairs)) from None
        if isinstance(err, BrokenProcessPool) or type(err).__name__ == "KilledWorker":
            raise WorkerLost(finished, len(pairs), f"{type(err).__name__}: {err}") from None
        raise
    finally:
        bar.close()
        try:
            if own:
                pool.shutdown(cancel_futures=True)
        finally:
            if folder is not None:
                shutil.rmtree(folder, ignore_errors=True)
    return [r for i in range(len(chunks)) for r in done[i]]


def shape_distance_matrix(
    meshes: list[Mesh], *, k: int = 20, form: str = "area", progress: bool = False, **match_kwargs
) -> np.ndarray:
    """``(N, N)`` symmetric :func:`~.scores.shape_distance` of the maps between all pairs."""
    n = len(meshes)
    D = np.zeros((n, n))
    pairs = [(i, j) for i in range(n) for j in range(n) if i != j]
    shapes = [prepare_shape(m, 0) for m in meshes]
    for i, j in tqdm(pairs, desc="shape pairs", disable=not progress):
        result = match(meshes[i], meshes[j], k=k, shapes=(shapes[i], shapes[j]), **match_kwargs)
        W_x, W_y = result.basis_x.projected_laplacian(), result.basis_y.projected_laplacian()
        D[i, j] = shape_distance(result.C_xy, W_x, W_y, form=form)
    return 0.5 * (D + D.T)
