"""The check switch of the torch code (``torchfmap._util.torch_checks``): data checks run by default on
CPU and not with ``check=False``, which then reads no tensor value on the host."""

from __future__ import annotations

import pytest
import torch

from torchfmap import ParameterError
from torchfmap.fmap import solve_rowwise
from torchfmap.nn import RegularizedFMSolver, UnsupervisedFMLoss, collate_shapes
from torchfmap.nn import functional as F

from ..conftest import as_batch, bumpy_blob


def test_data_checks_follow_the_switch_in_function_and_layer(nn_setting):
    """Data checks run by default on CPU tensors and are skipped with check=False, in the
    function and in its layer alike; shape checks run either way."""
    x, y, dx, dy, eig, stack = nn_setting
    tx, ty = as_batch(*eig)
    fx, fy = torch.tensor(dx)[None], torch.tensor(dy)[None]
    bad = fx.clone()
    bad[0, 3, 1] = float("inf")
    for solve in (
        lambda **kw: F.solve_fmap_batch(bad, fy, tx, ty, **kw),
        lambda **kw: RegularizedFMSolver(**kw)(bad, fy, tx, ty),
    ):
        with pytest.raises(ParameterError, match="NaN or inf"):
            solve()
        with pytest.raises(ParameterError, match="NaN or inf"):
            solve(check=True)
        assert not torch.isfinite(solve(check=False).C_xy).all()  # unchecked: non-finite, no error
        with pytest.raises(ParameterError, match=r"features must be \(B, V, D\)"):
            F.solve_fmap_batch(fx[:, :10], fy, tx, ty, check=False)
    with pytest.raises(ParameterError, match="check must be"):
        F.solve_fmap_batch(fx, fy, tx, ty, check="yes")
    # singular systems (no descriptor information, w_lap = 0): the LU's info is read under check
    zeros, mask = torch.zeros(1, 4, 3, dtype=torch.float64), torch.ones(1, 4, 4, dtype=torch.float64)
    with pytest.raises(ParameterError, match="singular: the descriptor term is zero"):
        solve_rowwise(zeros, zeros, mask, 1.0, 0.0)
    low_rank = torch.zeros(1, 4, 3, dtype=torch.float64)
    low_rank[0, 0, 0] = 1.0  # one descriptor direction for four columns
    with pytest.raises(ParameterError, match=r"Laplacian term is off \(w_lap = 0\)"):
        solve_rowwise(low_rank, low_rank, mask, 1.0, 0.0)
    solve_rowwise(zeros, zeros, mask, 1.0, 0.0, check=False)  # unchecked: no error


class _NoHostReads:
    """Tensor methods that copy a value to the host (a sync on an accelerator) raise inside."""

    NAMES = ("__bool__", "__int__", "__float__", "__index__", "item", "tolist", "numpy")

    def __enter__(self):
        self.saved = {name: getattr(torch.Tensor, name) for name in self.NAMES}

        def refuse(*args, **kwargs):
            raise AssertionError("a tensor value was read on the host")

        for name in self.NAMES:
            setattr(torch.Tensor, name, refuse)
        self.bincount, torch.bincount = torch.bincount, refuse
        return self

    def __exit__(self, *exc):
        for name, method in self.saved.items():
            setattr(torch.Tensor, name, method)
        torch.bincount = self.bincount
        return False


def test_unchecked_training_step_reads_no_tensor_value_on_the_host():
    """With check=False a whole step (DiffusionNet with gradient features on a padded batch,
    both maps, the loss with sampled coupling, backward) never reads a tensor value on the host:
    no bool()/int()/.item() on tensors, so no host sync on an accelerator. With the default
    (check=None on CPU) the data checks do read values."""
    from torchfmap.nn import DiffusionNet
    from torchfmap.nn.inputs import shape_arrays, shape_item
    from torchfmap.nn.networks import features

    items = [shape_item(shape_arrays(bumpy_blob(n), 6, 6, 20, k_net=8), dtype=torch.float64) for n in (1, 2)]
    x = collate_shapes(items)
    y = collate_shapes(items[::-1])
    assert x.basis.lengths.tolist() == [42, 162]

    def step(check):
        torch.manual_seed(0)
        net = DiffusionNet(6, 5, width=8, n_blocks=2, dropout=0.0, check=check).double()
        solver = RegularizedFMSolver(check=check)
        loss = UnsupervisedFMLoss(n_samples=30, check=check)
        gen = torch.Generator().manual_seed(0)
        fx, fy = features(net, x), features(net, y)
        C_xy, C_yx = solver(fx, fy, x.basis, y.basis)
        total = loss(C_xy, C_yx, fx, fy, x.basis, y.basis, generator=gen)["total"]
        total.backward()
        return total.detach()

    with _NoHostReads():
        unchecked = step(False)
    with pytest.raises(AssertionError, match="host"), _NoHostReads():
        step(None)
    assert torch.equal(unchecked, step(None))  # the checks change nothing but the errors
