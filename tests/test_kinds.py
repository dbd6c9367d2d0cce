"""The basis-kind registry: every kind builds what it promises, and the pipeline, the command
line, the solver defaults and the datasets read the registry (a new kind needs no other edit)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from torchfmap import ParameterError, match
from torchfmap.bases import KINDS, Basis, Column, get_kind, kind_of, prepare_shape
from torchfmap.bases.prepared import with_eigenpairs
from torchfmap.cli import build_parser
from torchfmap.eval import Correspondence, evaluate_map, geodesic_errors, landmarks_from_gt
from torchfmap.fmap.defaults import W_LAP, basis_kind, default_p2p_mode, default_w_lap, default_w_orient
from torchfmap.kinds import BasisKind, SeededKind

from .conftest import bumpy_blob

#: MGS with re-orthogonalisation: orthogonality to a few eps per column (``K`` columns).
ORTHO_EPS = 100 * np.finfo(float).eps


@pytest.fixture(scope="module")
def blob():
    return bumpy_blob(2)  # 162 vertices


@pytest.mark.parametrize("name", list(KINDS))
def test_every_kind_builds_exactly_k_b_orthonormal_columns_and_is_recognised(blob, name):
    k = 16
    basis = KINDS[name].shape_basis(prepare_shape(blob, 0), k)
    assert basis.k == k and basis.n_vertices == blob.n_vertices
    blocks = KINDS[name].block_bases(basis)
    assert sum(b.k for b in blocks) == k
    for block in blocks:  # B-orthonormal (block by block for a block kind such as 'hybrid')
        np.testing.assert_allclose(block.gram(), np.eye(block.k), atol=ORTHO_EPS * block.k)
    assert kind_of(basis) == name == basis_kind(basis)
    assert default_w_lap(basis, basis) == KINDS[name].w_lap == W_LAP[name]
    assert default_w_orient(basis, basis) == KINDS[name].w_orient
    assert default_p2p_mode(basis, basis) == KINDS[name].p2p_mode


@pytest.mark.parametrize("name", [n for n, kind in KINDS.items() if kind.needs_landmarks])
def test_seeded_pair_bases_of_a_permuted_copy_are_the_same_functions(name):
    """On an exact copy with permuted vertices, the seeds are placed exactly, so the two bases
    hold the same functions: Φ_y = Φ_x[perm] to the kernels' solve tolerance."""
    x = bumpy_blob(2)
    perm = np.random.default_rng(1).permutation(x.n_vertices)
    inverse = np.argsort(perm)
    y = x.permuted(perm)
    lm = np.array([[v, inverse[v]] for v in (3, 60, 120)])
    bx, by, seeds = KINDS[name].pair_bases(prepare_shape(x, 0), prepare_shape(y, 0), 12, lm)
    np.testing.assert_array_equal(seeds[:, 1], inverse[seeds[:, 0]])
    kind = KINDS[name]
    for block_x, block_y in zip(kind.block_bases(bx), kind.block_bases(by), strict=True):
        vx, vy = block_x.values[perm], block_y.values
        if set(block_x.kinds()) == {"laplacian"}:  # eigenfunctions: each up to its sign
            vy = vy * np.sign(np.sum(vx * vy, axis=0))
        # heat kernels are solved to a relative 1e-4 (SEED_HEAT_TOL), eigenvectors to ARPACK_TOL,
        # on each shape independently
        np.testing.assert_allclose(vy, vx, atol=1e-3 * np.abs(vx).max())


def test_unknown_kind_is_refused_with_the_choices():
    with pytest.raises(ParameterError, match="unknown basis kind 'eigen'.*laplacian, hybrid, diffusion"):
        get_kind("eigen")
    assert get_kind(KINDS["stack"]) is KINDS["stack"]
    assert all(isinstance(kind, BasisKind) and KINDS[kind.name] is kind for kind in KINDS.values())
    assert kind_of(Basis(np.ones((4, 1)), np.ones(4), [Column("custom")])) is None


def test_every_kind_is_offered_by_the_commands_that_take_a_basis():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices
    for command, flag in (
        ("match", "--basis"),
        ("eval", "--basis"),
        ("train", "--basis"),
        ("basis", "--basis"),
    ):
        action = next(a for a in sub[command]._actions if flag in a.option_strings)
        offered = [n for n, kind in KINDS.items() if kind.learned or command != "train"]
        choose = ["auto"] if command in ("match", "eval") else []  # the landmark default's choice
        assert list(action.choices) == choose + offered, command


@dataclass(frozen=True, kw_only=True)
class HatKind(SeededKind):
    """A kind defined outside the package: one tent function per seed (1 at the seed, falling
    linearly to 0 at the covering radius)."""

    def columns_per_seed(self, times) -> int:
        return 1

    def functions(self, shape, seeds, times=None):
        radius = 2.0 / np.sqrt(len(seeds))
        values = np.stack([np.maximum(0.0, 1.0 - shape.distances(int(s)) / radius) for s in seeds], 1)
        L, B = shape.operators
        return Basis(values, B, [Column("hat", int(s)) for s in seeds], stiffness=L)


def test_a_new_kind_is_one_class_and_one_registry_line(monkeypatch):
    """Registering a kind is all ``match`` (raw and refined), its defaults and the datasets need."""
    hat = HatKind(name="hat", summary="tent functions", w_lap=0.1, column_kinds=frozenset({"hat"}))
    monkeypatch.setitem(KINDS, "hat", hat)
    x = bumpy_blob(3)
    perm = np.random.default_rng(3).permutation(x.n_vertices)
    inverse = np.argsort(perm)
    y = x.permuted(perm)
    lm = np.array([[v, inverse[v]] for v in (3, 200, 450, 600)])
    gt = Correspondence(idx_x=perm, idx_y=np.arange(y.n_vertices))
    for refine in (None, "zoomout"):
        result = match(x, y, landmarks=lm, basis="hat", k=30, refine=refine)
        assert result.kind == "hat" and result.basis_x.k == 30
        assert evaluate_map(x, y, result.p2p_yx, gt, max_points=300)[0].mean_error < 0.02
    assert kind_of(result.basis_x) == "hat"
    with pytest.raises(ParameterError, match="hat basis is built from corresponding landmarks"):
        match(x, y, basis="hat")


LEARNED = [name for name, kind in KINDS.items() if kind.learned]


@pytest.mark.parametrize("name", LEARNED)
def test_shape_dataset_accepts_every_kind(tmp_path, blob, name):
    from torchfmap import save_mesh
    from torchfmap.nn.data import ShapeDataset

    paths = [save_mesh(blob, tmp_path / "a.off"), save_mesh(blob.scaled(2.0), tmp_path / "b.off")]
    data = ShapeDataset(paths, cache_dir=False, k=16, basis=name, progress=False)
    item = data[0]
    values, mass = np.asarray(item["values"], dtype=float), np.asarray(item["mass"], dtype=float)
    assert values.shape == (blob.n_vertices, 16)
    # float32 storage: the Gram matrix of the unit-area basis is I to single precision
    np.testing.assert_allclose(values.T @ (mass[:, None] * values), np.eye(16), atol=1e-4)


def test_the_learned_path_refuses_a_classical_only_kind_by_name(tmp_path, blob):
    from torchfmap import save_mesh
    from torchfmap.nn import BasisModule
    from torchfmap.nn.data import ShapeDataset

    classical = [name for name, kind in KINDS.items() if not kind.learned]
    assert classical == ["hybrid"]
    path = save_mesh(blob, tmp_path / "a.off")
    with pytest.raises(ParameterError, match="hybrid basis is solved block-wise.*Fix: one of laplacian"):
        ShapeDataset([path], cache_dir=False, k=16, basis="hybrid", progress=False)
    with pytest.raises(ParameterError, match="hybrid basis is solved block-wise"):
        BasisModule.from_mesh(blob, k=12, kind="hybrid")


@pytest.mark.parametrize("name", LEARNED)
def test_basis_module_from_mesh_builds_every_kind(blob, name):
    import torch

    from torchfmap.nn import BasisModule

    layer = BasisModule.from_mesh(blob, k=12, kind=name, seeds=[4, 90], dtype=torch.float32)
    assert layer.k == 12 and layer.values.dtype == torch.float32
    reference = KINDS[name].shape_basis(prepare_shape(blob, 0), 12, seeds=[4, 90])
    np.testing.assert_allclose(layer.values.numpy(), reference.values, atol=1e-6)


def test_hybrid_map_is_block_diagonal_and_zoomout_grows_only_the_eigen_block():
    from torchfmap.kinds.hybrid import split_blocks

    from .conftest import bend

    x = bumpy_blob(2)
    y = x.copy(bend(x.vertices, 0.3))  # same connectivity: the true map is the identity
    lm = np.array([[v, v] for v in (3, 60, 120)])
    kind = KINDS["hybrid"]
    k_e, k_f = kind.blocks(20)
    raw = match(x, y, landmarks=lm, basis="hybrid", k=20)
    assert raw.kind == "hybrid" and raw.C_xy.shape == (20, 20)
    np.testing.assert_array_equal(raw.C_xy[:k_e, k_e:], 0.0)
    np.testing.assert_array_equal(raw.C_xy[k_e:, :k_e], 0.0)
    np.testing.assert_array_equal(raw.C_xy[k_e:, k_e:], np.eye(k_f))  # same kernels at the same seeds
    refined = match(x, y, landmarks=lm, basis="hybrid", k=20, refine="zoomout", k_final=30)
    eigen, feature = split_blocks(refined.basis_x)
    assert (eigen.k, feature.k) == (30 - k_f, k_f)
    gt = Correspondence(np.arange(x.n_vertices), np.arange(y.n_vertices))
    errors = [evaluate_map(x, y, r.p2p_yx, gt)[0].mean_error for r in (raw, refined)]
    eigen_map = match(x, y, landmarks=lm, basis="laplacian", k=20, refine="zoomout", k_final=30).p2p_yx
    lap = evaluate_map(x, y, eigen_map, gt)[0].mean_error
    # a near-isometric bend: the hybrid map is as good as the eigenbasis's (within a vertex spacing)
    spacing = np.sqrt(x.area / x.n_vertices) / np.sqrt(x.area)
    assert errors[1] <= lap + spacing
    with pytest.raises(ParameterError, match="k >= 2"):
        kind.blocks(1)


def test_hybrid_zoomout_never_ends_worse_than_its_start_by_the_eigen_energy():
    """From bad starts (random point maps), guarded hybrid ZoomOut returns a point map whose
    eigen-block energy (Σ_k ‖C_kᵀC_k - I‖²/k over its sizes) is at most the start's, and its C
    is the refit of that map (block-diagonal, eigen block of the final size); the identity of a
    shape onto itself stays exact."""
    from torchfmap.fmap.refine import zoomout_energy
    from torchfmap.kinds.hybrid import hybrid_zoomout

    from .conftest import bend

    x = bumpy_blob(2)
    y = x.copy(bend(x.vertices, 0.3))
    sx, sy = prepare_shape(x, 40), prepare_shape(y, 40)
    kind = KINDS["hybrid"]
    seeds = np.array([[v, v] for v in (3, 60, 120)])
    bx, by, _ = kind.pair_bases(sx, sy, 20, seeds)
    k_e, k_f = kind.blocks(20)
    sizes = list(range(k_e, 30 - k_f, 5)) + [30 - k_f]
    rng = np.random.default_rng(0)
    for _ in range(3):
        start = rng.integers(0, x.n_vertices, y.n_vertices)
        e_start = zoomout_energy(start, sx.eigenbasis, sy.eigenbasis, sizes)
        C, p2p, gx, _ = hybrid_zoomout(start, sx, sy, bx, by, kind, 30, step=5)
        assert zoomout_energy(p2p, sx.eigenbasis, sy.eigenbasis, sizes) <= e_start + 1e-12
        assert C.shape == (30, 30) and gx.k == 30
        np.testing.assert_array_equal(C[: 30 - k_f, 30 - k_f :], 0.0)
    # a shape onto itself: the identity has zero energy, so the guard keeps it exactly
    bxx, bxx2, _ = kind.pair_bases(sx, sx, 20, seeds)
    exact = np.arange(x.n_vertices)
    np.testing.assert_array_equal(hybrid_zoomout(exact, sx, sx, bxx, bxx2, kind, 30, step=5)[1], exact)


@pytest.mark.parametrize("name", ["laplacian", "hybrid", "diffusion", "eigen_diffusion"])
def test_each_kind_refines_its_own_maps(bent_pair, name):
    """``kind.refine``: ICP keeps the bases; ZoomOut grows them to ``k_final`` in kinds that grow
    (``grows``) and keeps their size otherwise; a refined map of a bent pair is no worse than
    its start (for the eigenbasis, ZoomOut's guard makes that a property)."""
    x, y, gt = bent_pair
    lm = landmarks_from_gt(x, gt, 6)
    start = match(x, y, landmarks=None if name == "laplacian" else lm, k=16, basis=name)
    ctx, kind = start._context, KINDS[name]
    if kind.grows:
        for shape in (ctx.shape_x, ctx.shape_y):
            with_eigenpairs(shape, 24)
    args = (start.C_xy, start.p2p_yx, ctx.shape_x, ctx.shape_y, start.basis_x, start.basis_y)
    icp = kind.refine(*args, "icp", k_final=24, mode=ctx.mode, seeds=start.seeds)
    assert (icp.basis_x.k, icp.basis_y.k) == (16, 16)
    zo = kind.refine(*args, "zoomout", k_final=24, mode=ctx.mode, seeds=start.seeds, times=ctx.times)
    assert zo.basis_x.k == (24 if kind.grows else 16)
    assert zo.p2p_yx.shape == (y.n_vertices,) and zo.p2p_yx.min() >= 0 and zo.p2p_yx.max() < x.n_vertices
    if name == "laplacian":  # ZoomOut's guard keeps the lowest-energy map, never a worse start
        errors = [geodesic_errors(x, p, gt, max_points=200).mean() for p in (start.p2p_yx, zo.p2p_yx)]
        assert errors[1] <= errors[0] * 1.05
    with pytest.raises(ParameterError, match="unknown refinement"):
        kind.refine(*args, "nearest", k_final=24, mode=ctx.mode)


def test_refine_map_is_a_deprecated_alias_and_the_fmap_layer_points_to_the_kinds(bent_pair):
    import torchfmap.fmap
    from torchfmap.pipeline import refine_map

    x, y, _ = bent_pair
    r = match(x, y, k=12)
    ctx = r._context
    args = (r.C_xy, r.p2p_yx, ctx.shape_x, ctx.shape_y, r.basis_x, r.basis_y, "icp")
    with pytest.warns(DeprecationWarning, match="refine"):
        old = refine_map(*args, kind="laplacian", k_final=12, mode="orthogonal")
    new = KINDS["laplacian"].refine(*args, k_final=12, mode="orthogonal")
    np.testing.assert_array_equal(old.p2p_yx, new.p2p_yx)
    with pytest.raises(AttributeError, match="get_kind"):
        torchfmap.fmap.refine_map  # noqa: B018
