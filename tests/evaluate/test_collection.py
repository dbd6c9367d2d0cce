"""Collection evaluation (``torchfmap.evaluate.collection``, behind ``torchfmap eval``): shapes prepared
once, pools, executors, landmark files per pair, shape-distance matrices."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, match
from torchfmap.cli import main
from torchfmap.data import icosphere
from torchfmap.evaluate.scores import gt_identity, retrieval_accuracy

from ..conftest import _err, _identity_folder, bend, bumpy_blob


@pytest.mark.slow
def test_evaluate_pairs_prepares_each_mesh_once_and_workers_give_the_same_results(tmp_path, monkeypatch):
    """``evaluate_pairs`` (behind ``torchfmap eval``) prepares every mesh once per process, and a
    pool of 2 processes returns exactly the single-process maps' errors, in the pairs' order."""
    import torchfmap.evaluate.collection as collection
    from torchfmap import save_mesh
    from torchfmap.evaluate.scores import discover_pairs

    from ..conftest import bend, bumpy_blob

    x = bumpy_blob(2)
    for i, amount in enumerate((0.05, 0.2, 0.35, 0.5)):  # same vertex ids: identity ground truth
        save_mesh(x.copy(bend(x.vertices, amount)), tmp_path / f"m{i}.off")
    pairs = list(discover_pairs(tmp_path))
    assert len(pairs) == 3  # consecutive meshes: m0-m1, m1-m2, m2-m3
    prepared = []
    real = collection.prepare_shape
    monkeypatch.setattr(collection, "prepare_shape", lambda mesh, n: prepared.append(mesh) or real(mesh, n))
    one = collection.evaluate_pairs(pairs, gt_landmarks=4, k=20, threads=1)
    assert len(prepared) == 4  # 4 meshes in 3 pairs
    monkeypatch.undo()
    # the same thread count per process: the pool's maps are the one-process maps, bit for bit
    two = collection.evaluate_pairs(pairs, gt_landmarks=4, k=20, workers=2, threads=1)
    assert [(r.source, r.target) for r in two] == [(a, b) for a, b, *_ in pairs]
    for r1, r2 in zip(one, two, strict=True):
        np.testing.assert_array_equal(r1.errors, r2.errors)
    with pytest.raises(ParameterError, match="workers"):
        collection.evaluate_pairs(pairs, workers=0)
    with pytest.raises(ParameterError, match="threads"):
        collection.evaluate_pairs(pairs, threads=0)


def test_evaluate_pairs_hands_its_prepared_shapes_to_any_matcher(tmp_path):
    """One matcher protocol: ``matcher(mesh_x, mesh_y, shapes=(sx, sy), **settings)`` returning a
    result with ``p2p_yx``. Every mesh is prepared once and the same prepared shape is handed to
    each pair it takes part in; the settings reach the matcher; settings (or landmarks) the
    matcher does not take are refused before any work; ``match`` is the default."""
    from torchfmap import PreparedShape, save_mesh
    from torchfmap.evaluate.collection import evaluate_pairs
    from torchfmap.evaluate.scores import discover_pairs

    x = bumpy_blob(2)
    for i, amount in enumerate((0.05, 0.2, 0.35)):
        save_mesh(x.copy(bend(x.vertices, amount)), tmp_path / f"m{i}.off")
    pairs = list(discover_pairs(tmp_path))
    calls = []

    def matcher(mesh_x, mesh_y, *, shapes, k):
        assert all(isinstance(s, PreparedShape) for s in shapes)
        assert shapes[0].mesh is mesh_x and shapes[1].mesh is mesh_y
        calls.append((mesh_x.name, mesh_y.name, shapes, k))
        return match(mesh_x, mesh_y, k=k, shapes=shapes)

    results = evaluate_pairs(pairs, matcher=matcher, k=12, threads=1)
    assert [(a, b, k) for a, b, _, k in calls] == [("m0", "m1", 12), ("m1", "m2", 12)]
    assert calls[0][2][1] is calls[1][2][0]  # m1: one prepared shape for both of its pairs
    default = evaluate_pairs(pairs, k=12, threads=1)
    for r1, r2 in zip(results, default, strict=True):
        np.testing.assert_array_equal(r1.errors, r2.errors)
    with pytest.raises(ParameterError, match="does not take landmarks, w_lap"):
        evaluate_pairs(pairs, matcher=matcher, k=12, w_lap=1.0, gt_landmarks=3)
    with pytest.raises(ParameterError, match="does not take kk"):
        evaluate_pairs(pairs, kk=3)


def test_saved_maps_are_found_by_the_meshes_names(tmp_path):
    from torchfmap import Mesh
    from torchfmap.evaluate.collection import MapFiles, SavedMap

    x = bumpy_blob(1)
    (tmp_path / "a-b.txt").write_text("\n".join(map(str, range(x.n_vertices))) + "\n")
    a, b = Mesh(x.vertices, x.faces, name="a"), Mesh(x.vertices, x.faces, name="b")
    saved = MapFiles(tmp_path)(a, b)
    assert isinstance(saved, SavedMap) and saved.path.name == "a-b.txt"
    np.testing.assert_array_equal(saved.p2p_yx, np.arange(x.n_vertices))
    with pytest.raises(ParameterError, match="found by the meshes' names"):
        MapFiles(tmp_path)(a, Mesh(x.vertices, x.faces))


def test_evaluate_pairs_runs_with_the_given_threads_and_restores_them(tmp_path, monkeypatch):
    """``threads`` limits BLAS (threadpoolctl) and torch while the pairs run, and the caller's
    settings come back afterwards, also when a pair raises."""
    import torch
    from threadpoolctl import threadpool_info

    import torchfmap.evaluate.collection as collection
    from torchfmap import save_mesh
    from torchfmap.evaluate.scores import discover_pairs

    from ..conftest import bend, bumpy_blob

    x = bumpy_blob(2)
    for i, amount in enumerate((0.05, 0.3)):
        save_mesh(x.copy(bend(x.vertices, amount)), tmp_path / f"m{i}.off")
    pairs = list(discover_pairs(tmp_path))
    seen = []
    real = collection.match

    def recording(*args, **kwargs):
        blas = [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]
        seen.append((torch.get_num_threads(), blas))
        return real(*args, **kwargs)

    monkeypatch.setattr(collection, "match", recording)
    torch_before = torch.get_num_threads()
    blas_before = [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]
    collection.evaluate_pairs(pairs, k=20, threads=1)
    assert seen and all(t == 1 and all(b == 1 for b in blas) for t, blas in seen)
    assert torch.get_num_threads() == torch_before
    assert [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"] == blas_before

    def failing(*args, **kwargs):
        raise RuntimeError("pair failed")

    monkeypatch.setattr(collection, "match", failing)
    with pytest.raises(RuntimeError, match="pair failed"):
        collection.evaluate_pairs(pairs, k=20, threads=1)
    assert torch.get_num_threads() == torch_before


def test_evaluate_pairs_solves_each_scoring_row_once_per_source(tmp_path, monkeypatch):
    """Pairs listed by source share its ground-truth distance rows: three pairs from one source
    with the same ground-truth points solve each row once; the chunks of a pool are cut where
    the source changes."""
    import torchfmap.evaluate.collection as collection
    import torchfmap.operators.geodesic as geodesic
    from torchfmap import save_mesh

    from ..conftest import bend, bumpy_blob

    x = bumpy_blob(2)
    paths = []
    for i, amount in enumerate((0.05, 0.2, 0.35, 0.5)):
        paths.append(save_mesh(x.copy(bend(x.vertices, amount)), tmp_path / f"m{i}.off"))
    gt = gt_identity(x.n_vertices)
    pairs = [("m0", f"m{i}", paths[0], paths[i], gt) for i in (1, 2, 3)]
    solved = []
    real = geodesic.GeodesicSolver.distances
    counted = lambda self, s: solved.extend(s) or real(self, s)  # noqa: E731
    monkeypatch.setattr(geodesic.GeodesicSolver, "distances", counted)
    built = []
    init = geodesic.GeodesicSolver.__init__
    monkeypatch.setattr(
        geodesic.GeodesicSolver, "__init__", lambda self, m, **kw: built.append(m) or init(self, m, **kw)
    )
    results = collection.evaluate_pairs(pairs, k=20)
    assert len(results) == 3 and len(solved) == x.n_vertices  # every vertex is a gt point, once
    assert len(built) == 1  # only the source's geodesic solver is factorised (targets: lazily never)
    other = [("m1", "m2", paths[1], paths[2], gt)]
    chunks = collection._source_chunks(pairs + other + pairs, 3)
    assert [len(c) for c in chunks] == [3, 1, 3]


def test_a_pool_worker_prepares_each_mesh_once_across_its_chunks(tmp_path, monkeypatch):
    """A local pool's worker keeps the shapes it prepared for its next chunks (the pool's
    initializer gives it the store); the calling process keeps nothing between calls."""
    import torchfmap.evaluate.collection as collection
    from torchfmap import save_mesh
    from torchfmap.evaluate.scores import discover_pairs

    from ..conftest import bend, bumpy_blob

    x = bumpy_blob(2)
    for i, amount in enumerate((0.05, 0.3, 0.5)):
        save_mesh(x.copy(bend(x.vertices, amount)), tmp_path / f"m{i}.off")
    pairs = list(discover_pairs(tmp_path))  # m0-m1, m1-m2: m1 in both
    prepared = []
    real = collection.prepare_shape
    monkeypatch.setattr(collection, "prepare_shape", lambda mesh, n: prepared.append(mesh) or real(mesh, n))
    for chunk in ([pairs[0]], [pairs[1]]):  # in this process: each chunk prepares its own meshes
        collection._evaluate_chunk(chunk, 0, 200, {"k": 20})
    assert len(prepared) == 4 and collection._POOL_SHAPES is None
    prepared.clear()
    monkeypatch.setattr(collection, "_POOL_SHAPES", None)  # restored after the test
    monkeypatch.setattr(collection.signal, "signal", lambda *args: None)  # this process keeps Ctrl-C
    collection._init_pool_worker()  # as in a pool's worker process
    for chunk in ([pairs[0]], [pairs[1]]):
        collection._evaluate_chunk(chunk, 0, 200, {"k": 20})
    assert len(prepared) == 3  # m1 prepared once


@pytest.mark.slow
def test_evaluate_pairs_pool_after_threaded_torch_work_in_the_parent_does_not_hang(tmp_path):
    """A pool forked after the parent used torch's thread pool hung in the workers' first
    torch.linalg.eigh; workers are spawned. Run in a subprocess with a deadline, so a
    regression fails instead of hanging the suite."""
    import subprocess
    import sys

    from torchfmap import save_mesh

    from ..conftest import bend, bumpy_blob

    x = bumpy_blob(2)
    for i, amount in enumerate((0.05, 0.3, 0.5)):
        save_mesh(x.copy(bend(x.vertices, amount)), tmp_path / f"m{i}.off")
    script = (
        "import torch\n"
        "from torchfmap.evaluate.scores import discover_pairs\n"
        "from torchfmap.evaluate.collection import evaluate_pairs\n"
        "torch.set_num_threads(2)\n"
        "a = torch.randn(400, 400, dtype=torch.float64)\n"
        "torch.linalg.eigh(a @ a.T)  # the parent's intra-op thread pool is up\n"
        "for _ in range(3):\n"
        "    a = a @ a / 400\n"
        f"pairs = list(discover_pairs({str(tmp_path)!r}))\n"
        "one = evaluate_pairs(pairs, k=30, threads=1)\n"
        "two = evaluate_pairs(pairs, k=30, workers=2, threads=1)\n"
        "assert all((p.errors == q.errors).all() for p, q in zip(one, two))\n"
        "print('ok')\n"
    )
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=180)
    assert res.returncode == 0 and res.stdout.strip().endswith("ok"), res.stderr[-2000:]


@pytest.mark.slow
def test_evaluate_pairs_on_a_local_dask_cluster_of_two_workers(tmp_path):
    """The same pairs through Dask distributed's executor (2 worker processes) give exactly the
    single-process results, in order."""
    distributed = pytest.importorskip("distributed")
    import torchfmap.evaluate.collection as collection
    from torchfmap import save_mesh
    from torchfmap.evaluate.scores import discover_pairs

    x = bumpy_blob(2)
    for i, amount in enumerate((0.05, 0.3, 0.5)):
        save_mesh(x.copy(bend(x.vertices, amount)), tmp_path / f"m{i}.off")
    pairs = list(discover_pairs(tmp_path))
    one = collection.evaluate_pairs(pairs, gt_landmarks=4, k=20, threads=1)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        with distributed.Client(cluster) as client:
            on_cluster = collection.evaluate_pairs(
                pairs, gt_landmarks=4, k=20, threads=1, executor=client.get_executor()
            )
    assert [(r.source, r.target) for r in on_cluster] == [(r.source, r.target) for r in one]
    for r1, r2 in zip(one, on_cluster, strict=True):
        np.testing.assert_array_equal(r1.errors, r2.errors)


def test_eval_reads_landmark_pairs_per_pair_from_a_folder(tmp_path, capsys):
    """``eval --landmarks DIR``: each pair's landmarks come from DIR/<source>-<target>.txt; the
    result equals passing the same pairs to match() directly."""
    from torchfmap import load_mesh
    from torchfmap.evaluate.collection import LandmarkFiles, evaluate_pairs
    from torchfmap.evaluate.scores import discover_pairs, evaluate_map

    folder = _identity_folder(tmp_path)
    lms = tmp_path / "lm"
    lms.mkdir()
    pairs = list(discover_pairs(folder))
    for a, b, *_ in pairs:
        (lms / f"{a}-{b}.txt").write_text("3 3\n60 60\n120 120\n")
    results = evaluate_pairs(pairs, gt_landmarks=LandmarkFiles(lms), k=12, threads=1)
    for (_, _, pa, pb, gt), r in zip(pairs, results, strict=True):
        x, y = load_mesh(pa), load_mesh(pb)
        p2p = match(x, y, landmarks=np.array([[3, 3], [60, 60], [120, 120]]), k=12).p2p_yx
        np.testing.assert_array_equal(r.errors, evaluate_map(x, y, p2p, gt)[1])
    assert main(["eval", str(folder), "--landmarks", str(lms), "--k", "12", "--quiet"]) == 0
    capsys.readouterr()
    (lms / f"{pairs[0][0]}-{pairs[0][1]}.txt").unlink()
    assert main(["eval", str(folder), "--landmarks", str(lms), "--quiet"]) == 2
    assert "no landmark file" in _err(capsys)
    assert main(["eval", str(folder), "--landmarks", str(lms), "--gt-landmarks", "3"]) == 2
    assert "pass one of them" in _err(capsys)


def test_retrieval_on_two_synthetic_classes():
    """Bent blobs and ellipsoids: shape distances from maps separate the classes."""
    from torchfmap.evaluate.collection import shape_distance_matrix

    blob = bumpy_blob(2)
    sphere = icosphere(2)
    shapes = [blob.copy(bend(blob.vertices, s)) for s in (0.1, 0.2, 0.4)]
    shapes += [sphere.copy(sphere.vertices * np.array([1.6, a, 0.5])) for a in (0.8, 0.9, 1.0)]
    D = shape_distance_matrix(shapes, k=10, k_descriptors=30)
    assert np.allclose(D, D.T) and np.all(np.diag(D) == 0)
    assert retrieval_accuracy(D, ["blob"] * 3 + ["sphere"] * 3) == 1.0


def test_ctrl_c_in_one_process_keeps_the_pairs_scored_before_it(tmp_path):
    from torchfmap.errors import EvaluationInterrupted
    from torchfmap.evaluate.collection import evaluate_pairs
    from torchfmap.evaluate.scores import discover_pairs

    pairs = list(discover_pairs(_identity_folder(tmp_path), pairs="all"))  # 6 pairs
    calls = []

    def interrupted_at_the_third(x, y, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return match(x, y, k=6, **kwargs)

    with pytest.raises(EvaluationInterrupted, match="interrupted after 2 of 6 pairs") as stop:
        evaluate_pairs(pairs, matcher=interrupted_at_the_third)
    assert [(r.source, r.target) for r in stop.value.finished] == [p[:2] for p in pairs[:2]]
    assert isinstance(stop.value, KeyboardInterrupt)  # a caller's Ctrl-C handling still sees it


def test_a_lost_worker_is_worker_lost_with_the_finished_pairs(tmp_path):
    """An executor whose worker dies (BrokenProcessPool; Dask's KilledWorker alike) ends the run
    with WorkerLost holding the pairs finished before, handed to on_results as they came."""
    from concurrent.futures import Future, ThreadPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    from torchfmap import WorkerLost
    from torchfmap.evaluate.collection import evaluate_pairs
    from torchfmap.evaluate.scores import discover_pairs

    folder = _identity_folder(tmp_path)
    pairs = list(discover_pairs(folder, True, "all"))

    class DiesAfterOne(ThreadPoolExecutor):
        submitted = 0

        def submit(self, fn, *args, **kwargs):
            self.submitted += 1
            if self.submitted == 1:
                self.first = super().submit(fn, *args, **kwargs)
                return self.first
            dead = Future()  # the worker dies once the first chunk is in
            broken = BrokenProcessPool("terminated abruptly")
            self.first.add_done_callback(lambda _: dead.set_exception(broken))
            return dead

    seen = []
    with (
        DiesAfterOne(max_workers=1) as executor,
        pytest.raises(WorkerLost, match="BrokenProcessPool") as lost,
    ):
        evaluate_pairs(pairs, executor=executor, k=20, on_results=seen.extend)
    assert 0 < len(lost.value.finished) < len(pairs) and lost.value.total == len(pairs)
    assert [(r.source, r.target) for r in seen] == [(r.source, r.target) for r in lost.value.finished]
    assert "Fix:" in str(lost.value)


def test_a_pool_worker_sends_back_a_message_the_pipe_writes_whole(tmp_path):
    """A local pool's worker hands back a path, not the results: a worker killed while writing a
    longer message to the pool's result pipe leaves half of it there, and Python's pool then
    waits forever instead of reporting itself broken. A message within ``PIPE_BUF`` is written
    whole or not at all; the file holds exactly the chunk's results."""
    import select
    from concurrent.futures.process import _ResultItem
    from multiprocessing.reduction import ForkingPickler

    from torchfmap.evaluate.collection import _evaluate_chunk, _evaluate_chunk_to_file, _read_chunk
    from torchfmap.evaluate.scores import discover_pairs

    pipe_buf = getattr(select, "PIPE_BUF", None)
    if pipe_buf is None:
        pytest.skip("no PIPE_BUF on this platform")
    pairs = list(discover_pairs(_identity_folder(tmp_path), True, "all"))[:3]
    args = (0, 200, {"k": 20})
    path = _evaluate_chunk_to_file(str(tmp_path), 7, pairs, *args, threads=1, shapes={})
    # the pool's message: its result item as the pool pickles it, after a 4-byte length header
    message = bytes(ForkingPickler.dumps(_ResultItem(2**31, result=path)))
    assert 4 + len(message) <= pipe_buf
    back, direct = _read_chunk(path), _evaluate_chunk(pairs, *args, threads=1, shapes={})
    assert [(r.source, r.target) for r in back] == [(r.source, r.target) for r in direct]
    for a, b in zip(back, direct, strict=True):
        np.testing.assert_array_equal(a.errors, b.errors)
    assert not list(tmp_path.glob("chunk*"))  # read once, removed


@pytest.mark.slow
def test_a_callers_process_pool_gets_results_through_files_and_leaves_none(tmp_path, monkeypatch):
    """A ProcessPoolExecutor passed as ``executor`` is on this machine: its chunks come back
    through files as a local pool's do (the same rows as one process), and the run removes them."""
    import multiprocessing
    import tempfile
    from concurrent.futures import ProcessPoolExecutor

    from torchfmap.evaluate.collection import evaluate_pairs
    from torchfmap.evaluate.scores import discover_pairs

    pairs = list(discover_pairs(_identity_folder(tmp_path), True, "all"))
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    made = []
    real = tempfile.mkdtemp
    monkeypatch.setattr(tempfile, "mkdtemp", lambda *a, **k: made.append(real(*a, **k)) or made[-1])
    one = evaluate_pairs(pairs, k=20, threads=1)
    assert not made  # one process: no files
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        pooled = evaluate_pairs(pairs, k=20, threads=1, executor=pool)
    assert len(made) == 1 and made[0].startswith(str(scratch))
    assert [(r.source, r.target) for r in pooled] == [(r.source, r.target) for r in one]
    for a, b in zip(one, pooled, strict=True):
        np.testing.assert_array_equal(a.errors, b.errors)
    assert not list(scratch.iterdir())
