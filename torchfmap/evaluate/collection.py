"""Evaluating a collection of pairs: each mesh prepared once, pairs matched and scored against
ground truth, in one process, a local process pool or any ``concurrent.futures`` executor.

Any *matcher* matches the pairs: a callable ``matcher(mesh_x, mesh_y, *, shapes=(shape_x,
shape_y), **settings)`` returning a result with ``p2p_yx (V_y,)``: :func:`torchfmap.match`
(the default) and :class:`torchfmap.nn.LearnedMatcher` (both return a
:class:`~torchfmap.matching.results.MatchResult`), or :class:`MapFiles` (saved maps). Each mesh is
prepared once (:func:`~torchfmap.prepare_shape`) and its prepared shape handed to the matcher.

The pool's workers keep the shapes they prepared for their next chunks (a store set by the
pool's initializer in the worker only, gone with the pool).
"""

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
    """One evaluated pair of :func:`evaluate_pairs`: names, the report of
    :func:`~torchfmap.evaluate.scores.evaluate_map`, its per-point errors and the match time (s)."""

    source: str
    target: str
    report: object
    errors: np.ndarray
    seconds: float
    iou: float | None = None  # partial pairs: overlap IoU (torchfmap.evaluate.partial.overlap_iou)


#: Distance rows :func:`evaluate_pairs` keeps for the current source mesh (bytes).
EVAL_ROWS_BYTES = 512 * 2**20
#: Cost of a source's scoring rows in units of one pair's match, for balancing a pool's chunks.
SOURCE_COST = 5.0

# The prepared shapes of a local pool's worker process, kept across the chunks it runs (so a
# worker prepares each mesh once); set by the pool's initializer in the worker, never in the
# calling process, and gone with the pool when evaluate_pairs returns.
_POOL_SHAPES: dict | None = None


class _PairFiles:
    """Files of a folder named per pair, ``folder/<name_x>-<name_y>.txt`` (or ``.gz``); holds the
    folder only, so it pickles."""

    what = "file"  # what each file is, for messages

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
    """A matcher for :func:`evaluate_pairs` that reads saved maps instead of matching: the map of
    ``(x, y)`` is ``folder/<name_x>-<name_y>.txt`` (or ``.txt.gz``; the names are the meshes'
    ``name``, as :func:`~torchfmap.io.load_mesh` sets them), as ``torchfmap match --out``
    writes it (line i: the source vertex of target vertex i; :func:`~torchfmap.io.read_map`).
    Picklable (it holds the folder only).

    Raises (when called):
        ParameterError: an unnamed mesh, no map file for a pair (the expected name is given), or
            a map that does not fit the meshes (:func:`~torchfmap.io.read_map` and the
            evaluation's checks).
    """

    what = "saved map"

    def __call__(self, mesh_x: Mesh, mesh_y: Mesh, *, shapes=None) -> SavedMap:
        if not (mesh_x.name and mesh_y.name):
            raise ParameterError(
                "saved maps are found by the meshes' names, and a mesh has none. Fix: load the meshes "
                "with load_mesh (named after their files), or set Mesh(..., name=...)."
            )
        path = self.path(
            mesh_x.name,
            mesh_y.name,
            "write it with `torchfmap match SOURCE TARGET --out` there, or drop --maps to match here.",
        )
        p2p = read_map(path)
        if len(p2p) != mesh_y.n_vertices:
            raise ParameterError(
                f"{path.name} has {len(p2p)} lines but {mesh_y.name} has {mesh_y.n_vertices} "
                "vertices. Fix: one line per target vertex (the map target -> source)."
            )
        return SavedMap(p2p, path)


class LandmarkFiles(_PairFiles):
    """Landmarks of each pair read from a folder instead of the ground truth: the pairs of
    ``(x, y)`` are ``folder/<name_x>-<name_y>.txt`` (or ``.gz``), one ``source_vertex
    target_vertex`` pair per line, as ``torchfmap match --landmarks`` reads them. Pass it as
    :func:`evaluate_pairs`'s ``gt_landmarks``. Picklable (it holds the folder only).

    Raises (when called): ParameterError for a missing file (its expected name is given); the
    file's own errors as :func:`~torchfmap.io.read_landmark_pairs`.
    """

    what = "landmark file"

    def __call__(self, path_x, path_y) -> np.ndarray:
        return read_landmark_pairs(self.path(path_x, path_y, "add it."))


def pool_threads(workers: int) -> int:
    """Threads per worker of a local pool when none are given: the CPUs shared out."""
    return max(1, (os.cpu_count() or 1) // workers)


def _init_pool_worker() -> None:
    global _POOL_SHAPES
    _POOL_SHAPES = {}
    # Ctrl-C reaches the whole process group: the parent alone answers it (it stops the pool
    # and keeps the finished rows), so a worker does not die mid-pair with a traceback
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _stop_pool(pool: ProcessPoolExecutor) -> None:
    """End a local pool now: pending chunks cancelled, running workers terminated (a chunk in
    flight is lost; the pairs scored so far are kept by the caller)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    for process in processes:
        process.terminate()
    pool.shutdown(wait=False, cancel_futures=True)
    deadline = time.monotonic() + 2.0
    for process in processes:  # bounded: SIGTERM ends a worker at once
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
    """Match and score ``pairs`` in order with ``threads`` threads (BLAS and torch:
    :func:`~torchfmap._util.threads.thread_limit`); each mesh is loaded and prepared once
    (``shapes``: path -> (mesh, PreparedShape), filled here) and handed to
    ``matcher(x, y, shapes=(sx, sy), **match_kwargs)`` (None: :func:`~torchfmap.match`), with
    ``landmarks=`` when ``gt_landmarks`` gives them; ``on_pair()`` is called after each pair,
    ``progress``: a bar over its scoring. Results are appended to ``results`` (new when None)."""
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
            if overlap is not None:  # the true part as a region of the whole, whatever the meshings
                radius = part_radius(sy.mesh.vertices, sy.mesh.faces)
                iou = overlap_iou(overlap, gt.idx_x, sx.operators[1], points=sx.mesh.vertices, radius=radius)
            # errors are geodesic on x, from its ground-truth points: pairs with the same source
            # reuse its prefactored solver and the rows already solved (kept for one source at a time)
            if rows is None or rows.solver is not sx.distances.solver:
                rows = DistanceRows(x, sx.distances.solver, max_bytes=EVAL_ROWS_BYTES)
            scored = {"max_points": max_points, "solver": rows, "progress": progress}
            report, errors = evaluate_map(x, y, p2p, gt, **scored)
            out.append(PairResult(a, b, report, errors, seconds, iou))
            if on_pair is not None:
                on_pair()
        return out


def _evaluate_chunk_to_file(folder: str, index: int, pairs, *args, **kwargs) -> str:
    """A process pool's chunk: :func:`_evaluate_chunk`, its results pickled to a file in
    ``folder`` (:func:`~torchfmap._util.files.atomic_write`: a full disk is a ``FileWriteError``
    naming the file), whose path (a short message) is returned. A pool's results otherwise come
    back through one pipe, and a worker killed while writing a long result leaves half a message
    there that Python's pool waits for forever (it never reports the pool broken); a message
    shorter than the pipe's atomic write (``PIPE_BUF``) is written whole or not at all."""
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
    except (TypeError, ValueError):  # a callable without a signature: its own errors will do
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
    """Estimated cost of each pair in a run of ``pairs``: one match, plus :data:`SOURCE_COST`
    where the source mesh changes (its scoring rows are solved there)."""
    new_source = [i == 0 or pairs[i][2] != pairs[i - 1][2] for i in range(len(pairs))]
    return 1.0 + SOURCE_COST * np.asarray(new_source, dtype=float)


def _source_chunks(pairs: list, n_chunks: int) -> list[list]:
    """``pairs`` cut into at most ``n_chunks`` contiguous chunks of similar estimated cost
    (:func:`_chunk_costs`), cutting only where the source mesh changes (so a source's rows are
    solved in one chunk) when possible."""
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
    """Match and score every pair ``(name_x, name_y, path_x, path_y, gt)`` (as yielded by
    :func:`~torchfmap.evaluate.scores.discover_pairs`), in the given order.

    Each mesh is loaded and prepared (:func:`~torchfmap.bases.prepared.prepare_shape`:
    operators, eigenpairs, geodesic rows, heat kernels) once per chunk of pairs and reused by
    every pair it takes part in. With
    ``workers > 1`` the pairs are split into contiguous chunks, cut where the source mesh
    changes when possible (its scoring rows are then solved once), run by a local process
    pool (spawned processes);
    ``executor`` runs them on any :class:`concurrent.futures.Executor` instead (e.g.
    ``dask.distributed.Client(...).get_executor()`` for a cluster).

    Every chunk runs with ``threads`` BLAS / OpenMP / torch threads. The thread count fixes
    the order of BLAS's and torch's parallel sums, and so the last bits of eigenvectors and
    maps (near-tied points may then match differently). For the same ``threads``, the results
    do not depend on ``workers`` or ``executor``: every map is computed from the same inputs
    by the same deterministic steps.

    Args:
        gt_landmarks: use this many ground-truth pairs per pair as landmarks, or a
            :class:`LandmarkFiles` to read each pair's landmarks from its file
            (:func:`~torchfmap.evaluate.scores.landmarks_from_gt`; 0: none).
        max_points: the points scored per pair (:func:`~torchfmap.evaluate.scores.evaluated_rows`; None: all).
        workers: local worker processes (1: this process). Their chunks' results come back
            through files in a temporary folder (``TMPDIR``; removed when the run ends, left
            behind only if this process is killed), as those of a ``ProcessPoolExecutor``
            given as ``executor`` do.
        threads: threads per worker. ``None``: this process's threads as they are when
            ``workers == 1`` and no ``executor`` is given, else ``max(1, cpu_count // workers)``
            (:func:`pool_threads`; no oversubscription) or the executor's own setting. Pass it to
            compare runs with different ``workers`` bit for bit.
        matcher: ``matcher(mesh_x, mesh_y, *, shapes=(shape_x, shape_y), **match_kwargs)``
            returning a result with ``p2p_yx`` matches each pair (None: :func:`~torchfmap.match`;
            e.g. a trained network, :class:`torchfmap.nn.LearnedMatcher`, or saved maps,
            :class:`MapFiles`); with workers or an executor it must pickle.
        match_kwargs: passed to the matcher (for :func:`~torchfmap.match`: ``basis``, ``k``,
            ``refine``, ...; for a learned matcher: ``refine``, ``k_final``).
        on_results: called in this process with the list of :class:`PairResult` of each pair (one
            process) or chunk (a pool or an executor) as it finishes, e.g. to save them as they
            come (``torchfmap eval --out``); its exceptions stop the run.

    Raises:
        ParameterError: ``workers < 1`` or ``threads < 1``; ``match_kwargs`` (or landmarks,
            with ``gt_landmarks``) that the matcher does not take.
        EvaluationInterrupted: Ctrl-C (a ``KeyboardInterrupt``): a local pool is stopped at once
            (its workers ignore the signal and are terminated) and the exception's ``finished``
            holds the pairs scored until then.
        WorkerLost: a worker process died (a broken local pool, Dask's ``KilledWorker``); its
            ``finished`` holds the pairs scored until then.
    """
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
    # a few chunks per worker, balanced as they complete; a local pool's worker keeps the
    # meshes it prepared for its next chunks (an executor's chunks prepare them again)
    chunks = _source_chunks(pairs, min(len(pairs), 4 * workers))
    # spawned, not forked: a child forked after this process used torch's or BLAS's thread
    # pool waits forever on that pool's locks (torch.linalg.eigh hung this way)
    spawn = multiprocessing.get_context("spawn")
    pool = (
        ProcessPoolExecutor(max_workers=workers, mp_context=spawn, initializer=_init_pool_worker)
        if own
        else executor
    )
    # costliest chunks first (longest-processing-time order): the last ones to finish are short
    order = sorted(range(len(chunks)), key=lambda i: -float(_chunk_costs(chunks[i]).sum()))
    futures: dict = {}
    done: dict[int, list[PairResult]] = {}
    # a process pool on this machine (ours or the caller's) gets results through files: see
    # _evaluate_chunk_to_file; a cluster's executor keeps its own transport
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
    """``(N, N)`` symmetric shape distances from the functional maps between all pairs.

    Each ordered pair is matched (:func:`match`, eigenbasis by default) and the map's
    shape difference (``form`` ``'area'`` or ``'conformal'``) is compared with the identity
    (:func:`~torchfmap.evaluate.scores.shape_distance`);
    the two directions are averaged. Feed the result to
    :func:`~torchfmap.evaluate.scores.retrieval_accuracy` with class labels.
    """
    n = len(meshes)
    D = np.zeros((n, n))
    pairs = [(i, j) for i in range(n) for j in range(n) if i != j]
    shapes = [prepare_shape(m, 0) for m in meshes]  # each shape's work done once, not per pair
    for i, j in tqdm(pairs, desc="shape pairs", disable=not progress):
        result = match(meshes[i], meshes[j], k=k, shapes=(shapes[i], shapes[j]), **match_kwargs)
        W_x, W_y = result.basis_x.projected_laplacian(), result.basis_y.projected_laplacian()
        D[i, j] = shape_distance(result.C_xy, W_x, W_y, form=form)
    return 0.5 * (D + D.T)
