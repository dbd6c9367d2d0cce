"""The hybrid kind (``torchfmap.kinds.hybrid``): a block-diagonal map whose ZoomOut grows only the
eigen block, never ending worse than its start."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, match
from torchfmap.bases import prepare_shape
from torchfmap.evaluate.scores import Correspondence, evaluate_map
from torchfmap.kinds import KINDS

from ..conftest import bumpy_blob


def test_hybrid_map_is_block_diagonal_and_zoomout_grows_only_the_eigen_block():
    from torchfmap.kinds.hybrid import split_blocks

    from ..conftest import bend

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
    shapes = prepare_shape(x, 30), prepare_shape(y, 30)
    start = match(x, y, landmarks=lm, basis="hybrid", k=20, shapes=shapes)
    refiner = kind.refiner("zoomout", k_final=30, n_fixed=len(lm), landmarks=lm)  # unguarded: the mechanism
    refined = refiner(start.C_xy, start.p2p_yx, *shapes, start.basis_x, start.basis_y, start.seeds)
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

    from ..conftest import bend

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
