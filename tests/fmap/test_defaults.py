"""One source of defaults (``torchfmap.fmap.defaults``, plain numbers) for the layer and the
classical solver; match passes its kind's weights."""

from __future__ import annotations

import numpy as np
import torch

from torchfmap import laplacian_eigenbasis
from torchfmap.nn import BasisModule, RegularizedFMSolver


def test_defaults_agree_between_the_layer_the_classical_solver_and_match(blob):
    """One source of defaults: with no extra arguments the layer and ``solve_fmap`` give the
    same map in eigenbases (same core, same default ``w_lap``, the eigenbasis kind's, which
    ``match`` passes); ``fmap_to_p2p`` converts by pull-back unless told (valid in any basis);
    ``solve_fmap`` uses landmarks when given."""
    from torchfmap.fmap import fmap_to_p2p, solve_fmap
    from torchfmap.fmap.defaults import W_LAP_SMOOTH
    from torchfmap.kinds import KINDS

    x = blob.normalized()  # unit area: the layers' frame (nn.basis_arrays)
    y = x.copy(x.vertices * np.array([1.0, 1.1, 0.9])).normalized()
    bx, by = laplacian_eigenbasis(x, 10), laplacian_eigenbasis(y, 10)
    rng = np.random.default_rng(0)
    dx = rng.standard_normal((x.n_vertices, 6))
    dy = dx + 0.01 * rng.standard_normal(dx.shape)  # same vertex order: near-identical descriptors
    C = solve_fmap(bx, by, dx, dy)
    layer = RegularizedFMSolver()
    C_t, _ = layer(
        torch.from_numpy(dx)[None],
        torch.from_numpy(dy)[None],
        BasisModule(bx).batch(),
        BasisModule(by).batch(),
    )
    # both solve the same K x K systems in float64; round-off of the frames (eigh of K x K)
    tol = 1e3 * np.finfo(float).eps * np.abs(C).max()
    np.testing.assert_allclose(C_t[0].numpy(), C, atol=tol)
    assert W_LAP_SMOOTH == KINDS["laplacian"].w_lap == layer.w_lap
    np.testing.assert_array_equal(fmap_to_p2p(C, bx, by), fmap_to_p2p(C, bx, by, mode="pullback"))
    from torchfmap.fmap import values_to_p2p  # the same rules on plain arrays (the learned path)

    for mode in ("orthogonal", "pullback"):
        np.testing.assert_array_equal(
            values_to_p2p(C, bx.values, by.values, mode=mode), fmap_to_p2p(C, bx, by, mode=mode)
        )
    lm = np.array([[0, 0], [50, 50], [100, 100]])
    with_lm = solve_fmap(bx, by, dx, dy, landmarks=lm)
    assert not np.allclose(with_lm, C)  # given landmarks are used (w_lmk defaults to W_LMK)
    np.testing.assert_allclose(solve_fmap(bx, by, dx, dy, landmarks=lm, w_lmk=0.0), C, atol=tol)
