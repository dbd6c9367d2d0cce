"""End-to-end matching: every basis, refinements, the CLI commands, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, SeedError
from torchfmap.cli import main
from torchfmap.eval import Correspondence, evaluate_map, gt_identity, landmarks_from_gt
from torchfmap.pipeline import match

from .conftest import bend, bumpy_blob, data_path


@pytest.fixture(scope="module")
def pair():
    x = bumpy_blob(3)
    perm = np.random.default_rng(2).permutation(x.n_vertices)
    y = x.copy(bend(x.vertices, 0.3)).permuted(perm)
    gt = Correspondence(idx_x=perm, idx_y=np.arange(y.n_vertices))
    return x, y, gt


@pytest.mark.parametrize(
    ("basis", "refine"),
    [
        ("laplacian", None),
        ("laplacian", "zoomout"),
        ("laplacian", "icp"),
        ("harmonic", "zoomout"),
        ("diffusion", None),
        ("stack", "zoomout"),
        ("stack", "icp"),
    ],
)
def test_every_basis_gives_a_good_map(pair, basis, refine):
    x, y, gt = pair
    landmarks = landmarks_from_gt(x, gt, 10)
    result = match(
        x, y, landmarks=landmarks if basis != "laplacian" else None, basis=basis, k=30, refine=refine
    )
    assert result.p2p_yx.shape == (y.n_vertices,)
    assert result.C_xy.shape[0] == result.C_xy.shape[1] or refine == "zoomout"
    report, _ = evaluate_map(x, y, result.p2p_yx, gt, max_points=300)
    assert report.mean_error < 0.12, report
    if refine is not None:
        initial, _ = evaluate_map(x, y, result.p2p_yx_initial, gt, max_points=300)
        assert report.mean_error <= initial.mean_error * 1.1


def test_subsampled_zoomout_and_p2p_modes(pair):
    x, y, gt = pair
    errors = {}
    for mode in ("orthogonal", "pullback"):
        result = match(x, y, k=20, refine="zoomout", zoomout_samples=300, p2p_mode=mode)
        assert result.C_xy.shape == (40, 40)
        errors[mode] = evaluate_map(x, y, result.p2p_yx, gt, max_points=300)[0].mean_error
    assert max(errors.values()) < 0.12, errors


def test_match_bad_input(pair):
    x, y, gt = pair
    with pytest.raises(ParameterError, match="corresponding landmarks"):
        match(x, y, basis="harmonic")
    with pytest.raises(SeedError, match="out of range"):
        match(x, y, landmarks=[[0, 10**6]], basis="stack")
    with pytest.raises(ParameterError, match=r"\(L, 2\) pairs"):
        match(x, y, landmarks=[1, 2, 3], basis="stack")
    for bad_k in (0, -5, 20.0, x.n_vertices):
        with pytest.raises(ParameterError, match=r"k \(basis size\) must be an integer"):
            match(x, y, k=bad_k)
    with pytest.raises(ParameterError, match="k_final=10 is below k=20"):
        match(x, y, k=20, refine="zoomout", k_final=10)


def test_cli_match_writes_target_to_source_map(tmp_path, pair, capsys):
    from torchfmap import save_mesh

    x, y, gt = pair
    px, py = save_mesh(x, tmp_path / "x.off"), save_mesh(y, tmp_path / "y.off")
    lm = tmp_path / "lm.txt"
    np.savetxt(lm, landmarks_from_gt(x, gt, 10), fmt="%d")
    out = tmp_path / "map.txt"
    png = tmp_path / "transfer.png"
    assert (
        main(
            [
                "match",
                str(px),
                str(py),
                "--landmarks",
                str(lm),
                "--k",
                "30",
                "--refine",
                "icp",
                "--out",
                str(out),
                "--png",
                str(png),
            ]
        )
        == 0
    )
    p2p = np.loadtxt(out, dtype=int)
    assert p2p.shape == (y.n_vertices,) and p2p.max() < x.n_vertices
    report, _ = evaluate_map(x, y, p2p, gt, max_points=200)
    assert report.mean_error < 0.12
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    bad = tmp_path / "bad.txt"
    bad.write_text("1\n")
    assert main(["match", str(px), str(py), "--landmarks", str(bad), "--out", str(out)]) == 2
    assert "expected 2 integer column" in capsys.readouterr().err


def test_cli_eval_on_identity_folder(tmp_path, capsys):
    folder = data_path("tosca_hires_wolf")
    png = tmp_path / "pck.png"
    args = ["eval", str(folder), "--k", "30", "--max-pairs", "1", "--max-points", "200", "--png", str(png)]
    assert main([*args, "--threads", "1", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "| wolf0 | wolf1 |" in out and png.exists()
    mean = float(out.split("| **all** | | ")[1].split(" ")[0])
    assert mean < 0.1


def test_identity_gt_on_self_match():
    x = bumpy_blob(2)
    result = match(x, x, k=20)
    report, _ = evaluate_map(x, x, result.p2p_yx, gt_identity(x.n_vertices))
    assert report.mean_error < 0.02


def test_match_steps_one_by_one_equal_match(pair):
    """match() is the composition of its public steps: running them by hand gives the same map."""
    from torchfmap import MatchResult
    from torchfmap.fmap import fmap_to_p2p, solve_fmap
    from torchfmap.pipeline import W_LAP, match_bases, match_descriptors, prepare_shape, refine_map

    x, y, gt = pair
    lm = landmarks_from_gt(x, gt, 6)
    result = match(x, y, landmarks=lm, basis="laplacian", k=20, refine="icp", k_descriptors=40)
    assert isinstance(result, MatchResult)
    sx, sy = prepare_shape(x, 40), prepare_shape(y, 40)
    bx, by, seeds = match_bases(sx, sy, "laplacian", 20, lm)
    assert seeds is None
    assert bx.k == by.k == 20 and bx.stiffness is not None
    dx, dy = match_descriptors(sx, sy, lm, k_descriptors=40)
    C = solve_fmap(
        bx, by, dx, dy, w_lap=W_LAP["laplacian"], w_orient=1e-2, meshes=(x, y), landmarks=lm, w_lmk=1.0
    )
    p2p = fmap_to_p2p(C, bx, by, mode="orthogonal")
    np.testing.assert_array_equal(p2p, result.p2p_yx_initial)
    C, p2p, *_ = refine_map(C, p2p, sx, sy, bx, by, "icp", kind="laplacian", k_final=20, mode="orthogonal")
    np.testing.assert_array_equal(p2p, result.p2p_yx)
    np.testing.assert_array_equal(C, result.C_xy)


def test_evaluate_pairs_prepares_each_mesh_once_and_workers_give_the_same_results(tmp_path, monkeypatch):
    """``evaluate_pairs`` (behind ``torchfmap eval``) prepares every mesh once per process, and a
    pool of 2 processes returns exactly the single-process maps' errors, in the pairs' order."""
    import torchfmap.pipeline as pipeline
    from torchfmap import save_mesh
    from torchfmap.eval import discover_pairs

    from .conftest import bend, bumpy_blob

    x = bumpy_blob(2)
    for i, amount in enumerate((0.05, 0.2, 0.35, 0.5)):  # same vertex ids: identity ground truth
        save_mesh(x.copy(bend(x.vertices, amount)), tmp_path / f"m{i}.off")
    pairs = list(discover_pairs(tmp_path))
    assert len(pairs) == 3  # consecutive meshes: m0-m1, m1-m2, m2-m3
    prepared = []
    real = pipeline.prepare_shape
    monkeypatch.setattr(pipeline, "prepare_shape", lambda mesh, n: prepared.append(mesh) or real(mesh, n))
    one = pipeline.evaluate_pairs(pairs, gt_landmarks=4, k=20, threads=1)
    assert len(prepared) == 4  # 4 meshes in 3 pairs
    monkeypatch.undo()
    # the same thread count per process: the pool's maps are the one-process maps, bit for bit
    two = pipeline.evaluate_pairs(pairs, gt_landmarks=4, k=20, workers=2, threads=1)
    assert [(r.source, r.target) for r in two] == [(a, b) for a, b, *_ in pairs]
    for r1, r2 in zip(one, two, strict=True):
        np.testing.assert_array_equal(r1.errors, r2.errors)
    with pytest.raises(ParameterError, match="workers"):
        pipeline.evaluate_pairs(pairs, workers=0)
    with pytest.raises(ParameterError, match="threads"):
        pipeline.evaluate_pairs(pairs, threads=0)


def test_evaluate_pairs_runs_with_the_given_threads_and_restores_them(tmp_path, monkeypatch):
    """``threads`` limits BLAS (threadpoolctl) and torch while the pairs run, and the caller's
    settings come back afterwards, also when a pair raises."""
    import torch
    from threadpoolctl import threadpool_info

    import torchfmap.pipeline as pipeline
    from torchfmap import save_mesh
    from torchfmap.eval import discover_pairs

    from .conftest import bend, bumpy_blob

    x = bumpy_blob(2)
    for i, amount in enumerate((0.05, 0.3)):
        save_mesh(x.copy(bend(x.vertices, amount)), tmp_path / f"m{i}.off")
    pairs = list(discover_pairs(tmp_path))
    seen = []
    real = pipeline.match

    def recording(*args, **kwargs):
        blas = [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]
        seen.append((torch.get_num_threads(), blas))
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline, "match", recording)
    torch_before = torch.get_num_threads()
    blas_before = [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]
    pipeline.evaluate_pairs(pairs, k=20, threads=1)
    assert seen and all(t == 1 and all(b == 1 for b in blas) for t, blas in seen)
    assert torch.get_num_threads() == torch_before
    assert [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"] == blas_before

    def failing(*args, **kwargs):
        raise RuntimeError("pair failed")

    monkeypatch.setattr(pipeline, "match", failing)
    with pytest.raises(RuntimeError, match="pair failed"):
        pipeline.evaluate_pairs(pairs, k=20, threads=1)
    assert torch.get_num_threads() == torch_before


def test_evaluate_pairs_solves_each_scoring_row_once_per_source(tmp_path, monkeypatch):
    """Pairs listed by source share its ground-truth distance rows: three pairs from one source
    with the same ground-truth points solve each row once; the chunks of a pool are cut where
    the source changes."""
    import torchfmap.operators.geodesic as geodesic
    import torchfmap.pipeline as pipeline
    from torchfmap import save_mesh

    from .conftest import bend, bumpy_blob

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
    results = pipeline.evaluate_pairs(pairs, k=20)
    assert len(results) == 3 and len(solved) == x.n_vertices  # every vertex is a gt point, once
    assert len(built) == 1  # only the source's geodesic solver is factorised (targets: lazily never)
    other = [("m1", "m2", paths[1], paths[2], gt)]
    chunks = pipeline._source_chunks(pairs + other + pairs, 3)
    assert [len(c) for c in chunks] == [3, 1, 3]


def test_a_pool_worker_prepares_each_mesh_once_across_its_chunks(tmp_path, monkeypatch):
    """A local pool's worker keeps the shapes it prepared for its next chunks (the pool's
    initializer gives it the store); the calling process keeps nothing between calls."""
    import torchfmap.pipeline as pipeline
    from torchfmap import save_mesh
    from torchfmap.eval import discover_pairs

    from .conftest import bend, bumpy_blob

    x = bumpy_blob(2)
    for i, amount in enumerate((0.05, 0.3, 0.5)):
        save_mesh(x.copy(bend(x.vertices, amount)), tmp_path / f"m{i}.off")
    pairs = list(discover_pairs(tmp_path))  # m0-m1, m1-m2: m1 in both
    prepared = []
    real = pipeline.prepare_shape
    monkeypatch.setattr(pipeline, "prepare_shape", lambda mesh, n: prepared.append(mesh) or real(mesh, n))
    for chunk in ([pairs[0]], [pairs[1]]):  # in this process: each chunk prepares its own meshes
        pipeline._evaluate_chunk(chunk, 0, 200, {"k": 20})
    assert len(prepared) == 4 and pipeline._POOL_SHAPES is None
    prepared.clear()
    monkeypatch.setattr(pipeline, "_POOL_SHAPES", None)  # restored after the test
    pipeline._init_pool_worker()  # as in a pool's worker process
    for chunk in ([pairs[0]], [pairs[1]]):
        pipeline._evaluate_chunk(chunk, 0, 200, {"k": 20})
    assert len(prepared) == 3  # m1 prepared once


def test_evaluate_pairs_pool_after_threaded_torch_work_in_the_parent_does_not_hang(tmp_path):
    """A pool forked after the parent used torch's thread pool hung in the workers' first
    torch.linalg.eigh; workers are spawned. Run in a subprocess with a deadline, so a
    regression fails instead of hanging the suite."""
    import subprocess
    import sys

    from torchfmap import save_mesh

    from .conftest import bend, bumpy_blob

    x = bumpy_blob(2)
    for i, amount in enumerate((0.05, 0.3, 0.5)):
        save_mesh(x.copy(bend(x.vertices, amount)), tmp_path / f"m{i}.off")
    script = (
        "import torch\n"
        "from torchfmap.eval import discover_pairs\n"
        "from torchfmap.pipeline import evaluate_pairs\n"
        "torch.set_num_threads(2)\n"
        "a = torch.randn(400, 400, dtype=torch.float64)\n"
        "torch.linalg.eigh(a @ a.T)  # the parent's intra-op thread pool is up\n"
        "for _ in range(3):\n"
        "    a = a @ a / 400\n"
        f"pairs = list(discover_pairs({str(tmp_path)!r}))\n"
        "one = evaluate_pairs(pairs, k=60, threads=1)\n"
        "two = evaluate_pairs(pairs, k=60, workers=2, threads=1)\n"
        "assert all((p.errors == q.errors).all() for p, q in zip(one, two))\n"
        "print('ok')\n"
    )
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=180)
    assert res.returncode == 0 and res.stdout.strip().endswith("ok"), res.stderr[-2000:]


def test_evaluate_pairs_on_a_local_dask_cluster_of_two_workers(tmp_path):
    """The same pairs through Dask distributed's executor (2 worker processes) give exactly the
    single-process results, in order."""
    distributed = pytest.importorskip("distributed")
    import torchfmap.pipeline as pipeline
    from torchfmap import save_mesh
    from torchfmap.eval import discover_pairs

    x = bumpy_blob(2)
    for i, amount in enumerate((0.05, 0.3, 0.5)):
        save_mesh(x.copy(bend(x.vertices, amount)), tmp_path / f"m{i}.off")
    pairs = list(discover_pairs(tmp_path))
    one = pipeline.evaluate_pairs(pairs, gt_landmarks=4, k=20, threads=1)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        with distributed.Client(cluster) as client:
            on_cluster = pipeline.evaluate_pairs(
                pairs, gt_landmarks=4, k=20, threads=1, executor=client.get_executor()
            )
    assert [(r.source, r.target) for r in on_cluster] == [(r.source, r.target) for r in one]
    for r1, r2 in zip(one, on_cluster, strict=True):
        np.testing.assert_array_equal(r1.errors, r2.errors)
