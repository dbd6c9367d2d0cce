"""Basis kinds (``torchfmap.kinds``): every registered kind builds exactly k B-orthonormal columns
and is recognised, seeded pair bases of a permuted copy are the same functions, each kind
refines its own maps, and a kind defined outside the package is one class and one registry line."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from torchfmap import ParameterError, match
from torchfmap.bases import Basis, Column, prepare_shape
from torchfmap.evaluate.scores import Correspondence, evaluate_map, geodesic_errors, landmarks_from_gt
from torchfmap.kinds import ICP, KINDS, SeededKind, kind_of

from ..conftest import bumpy_blob

#: MGS with re-orthogonalisation: orthogonality to a few eps per column (``K`` columns).
ORTHO_EPS = 100 * np.finfo(float).eps


@pytest.mark.parametrize("name", list(KINDS))
def test_every_kind_builds_exactly_k_b_orthonormal_columns_and_is_recognised(small_blob, name):
    k = 16
    basis = KINDS[name].shape_basis(prepare_shape(small_blob, 0), k)
    assert basis.k == k and basis.n_vertices == small_blob.n_vertices
    blocks = KINDS[name].block_bases(basis)
    assert sum(b.k for b in blocks) == k
    for block in blocks:  # B-orthonormal (block by block for a block kind such as 'hybrid')
        np.testing.assert_allclose(block.gram(), np.eye(block.k), atol=ORTHO_EPS * block.k)
    assert kind_of(basis) == name


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
        if set(block_x.families()) == {"laplacian"}:  # eigenfunctions: each up to its sign
            vy = vy * np.sign(np.sum(vx * vy, axis=0))
        # heat kernels are solved to a relative 1e-4 (SEED_HEAT_TOL), eigenvectors to ARPACK_TOL,
        # on each shape independently
        np.testing.assert_allclose(vy, vx, atol=1e-3 * np.abs(vx).max())


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
    hat = HatKind(name="hat", summary="tent functions", w_lap=0.1, column_families=frozenset({"hat"}))
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


@pytest.mark.parametrize("name", ["laplacian", "hybrid", "diffusion", "eigen_diffusion"])
def test_each_kind_returns_its_own_refiner(bent_pair, name):
    """``kind.refiner``: ICP keeps the bases; ZoomOut grows them to ``k_final`` in kinds that grow
    (``grows``; eigenpairs computed in place when the shapes hold fewer) and keeps their size
    otherwise; a refined map of a bent pair is no worse than its start (for the eigenbasis,
    ZoomOut's guard makes that a property); the point-map rule is the kind's unless given."""
    x, y, gt = bent_pair
    lm = landmarks_from_gt(x, gt, 6)
    kind = KINDS[name]
    start = match(x, y, landmarks=None if name == "laplacian" else lm, k=16, basis=name)
    shapes = (prepare_shape(x, 16), prepare_shape(y, 16))  # fewer eigenpairs than ZoomOut needs
    args = (start.C_xy, start.p2p_yx, *shapes, start.basis_x, start.basis_y, start.seeds)
    icp = kind.refiner("icp")
    assert icp == ICP(kind.p2p_mode) and kind.refiner("icp", mode="pullback").mode == "pullback"
    refined = icp(*args)
    assert (refined.basis_x.k, refined.basis_y.k) == (16, 16)
    zo = kind.refiner("zoomout", k_final=24, n_fixed=len(lm), times=None)(*args)
    assert zo.basis_x.k == (24 if kind.grows else 16)
    assert zo.p2p_yx.shape == (y.n_vertices,) and zo.p2p_yx.min() >= 0 and zo.p2p_yx.max() < x.n_vertices
    if name == "laplacian":  # ZoomOut's guard keeps the lowest-energy map, never a worse start
        assert shapes[0].n_eigen >= 24
        errors = [geodesic_errors(x, p, gt, max_points=200).mean() for p in (start.p2p_yx, zo.p2p_yx)]
        assert errors[1] <= errors[0] * 1.05
        default = kind.refiner("zoomout")(*args)  # k_final: twice the start
        assert default.C_xy.shape == (32, 32)
    for bad in ("nearest", "seeded", None):
        fix = r"match refines by 'icp', 'zoomout'; got refine=.*Fix: 'icp', 'zoomout'\.$"
        with pytest.raises(ParameterError, match=fix):
            kind.refiner(bad)


def test_eigenbasis_zoomout_keeps_the_distances_to_the_landmarks(bent_pair):
    """With the match's landmarks, the eigenbasis refiner matches every vertex's geodesic
    distances to them as well (``landmark_coordinates``: zero at the landmark itself, one
    column per pair), and match() hands them over: its refined map is ZoomOut's with those
    anchors (the accuracy is the bench's: ``python -m bench accuracy --case landmark_default``)."""
    from torchfmap.fmap import zoomout
    from torchfmap.kinds.refiners import ZoomOut, landmark_coordinates

    x, y, gt = bent_pair
    lm = landmarks_from_gt(x, gt, 6)
    shapes = (prepare_shape(x, 32), prepare_shape(y, 32))
    ax, ay = landmark_coordinates(*shapes, lm)
    assert ax.shape == (x.n_vertices, 6) and ay.shape == (y.n_vertices, 6)
    np.testing.assert_array_equal(ax[lm[:, 0], np.arange(6)], 0.0)
    np.testing.assert_array_equal(ay[lm[:, 1], np.arange(6)], 0.0)
    refiner = KINDS["laplacian"].refiner("zoomout", landmarks=lm)
    assert isinstance(refiner, ZoomOut) and refiner.landmarks is lm
    start = match(x, y, landmarks=lm, k=16, basis="laplacian", shapes=shapes)
    refined = match(x, y, landmarks=lm, k=16, basis="laplacian", refine="zoomout", shapes=shapes)
    bx, by = shapes[0].eigenbasis, shapes[1].eigenbasis
    anchored = zoomout(start.C_xy, bx, by, 32, anchors=(ax, ay))[1]
    plain = zoomout(start.C_xy, bx, by, 32)[1]
    assert not np.array_equal(anchored, plain)  # the anchors changed the map
    np.testing.assert_array_equal(refined.p2p_yx, anchored if refined.refined else start.p2p_yx)
