"""Your own training loop with the layers of ``torchfmap.nn``, no Trainer and no dataset.

1. Prepare each shape once: ``prepare_shape`` (operators and eigenpairs in the mesh's
   unit-area frame), then ``shape_arrays`` (solver basis, network basis, WKS inputs, gradient
   operator; numpy float64) and ``shape_item`` (the tensors), collated into a batch of pairs.
2. A feature network: ``DiffusionNet``, or your own ``torch.nn.Module`` following the
   ``FeatureNetwork`` protocol (``forward(inputs (B, V, C), basis, grad) -> (B, V, D)``; here
   ``--network own``: learned diffusion in the network's basis and a per-vertex MLP).
3. ``RegularizedFMSolver`` (features -> ``C_xy``, ``C_yx``), ``UnsupervisedFMLoss``
   (bijectivity, orthogonality, coupling; no ground truth), Adam, a few steps.
4. The point map (each vertex of ``y`` takes the vertex of ``x`` whose row of
   ``Phi_x C_xy^T`` is nearest to its row of ``Phi_y``) and its geodesic error, before and after.

Meshes in their files' units are fine: the layers work in the unit-area frame, which
``prepare_shape`` (and ``BasisModule`` / ``nn.basis_arrays`` for a basis of your own) bring
every shape to; ``--scale 1000`` (the demo in other units) gives the same maps::

    python examples/05_custom_loop.py                   # the demo pair, 5 steps
    python examples/05_custom_loop.py X.off Y.off --gt truth.txt --max-steps 200 --network own
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from torch import nn

import torchfmap as tf
from torchfmap.data import demo_pair_paths
from torchfmap.evaluate.scores import evaluate_map, gt_from_map
from torchfmap.fmap import nearest_neighbor
from torchfmap.io import read_map
from torchfmap.nn import (
    BasisModule,
    DiffusionNet,
    RegularizedFMSolver,
    SpectralDiffusion,
    UnsupervisedFMLoss,
    collate_pairs,
    shape_arrays,
    shape_item,
)
from torchfmap.operators import DistanceRows

N_WKS, K_NET = 16, 64  # input channels (WKS) and the network's eigenbasis size


class OwnNet(nn.Module):
    """A network of your own (the ``FeatureNetwork`` protocol): a lift, learned diffusion in the
    network's basis, a per-vertex MLP; it ignores the gradient operator."""

    def __init__(self, c_in: int, c_out: int = 32, width: int = 32) -> None:
        super().__init__()
        self.lift = nn.Linear(c_in, width)
        self.diffusion = SpectralDiffusion(width)
        self.mlp = nn.Sequential(nn.Linear(2 * width, width), nn.ReLU(), nn.Linear(width, c_out))

    def forward(self, inputs: torch.Tensor, basis, grad=None) -> torch.Tensor:
        h = self.lift(inputs)  # (B, V, width)
        return self.mlp(torch.cat([h, self.diffusion(h, basis)], dim=-1))  # (B, V, c_out)


def point_map(net, solver, batch, arrays_x: dict, arrays_y: dict) -> np.ndarray:
    """``p2p_yx (V_y,)`` of the batch's first pair: ``C_xy`` from the features, then the
    nearest row of ``Phi_x C_xy^T`` for each row of ``Phi_y`` (float64)."""
    with torch.no_grad():
        bx, by = batch["x"], batch["y"]
        C_xy = solver(net(bx.inputs, bx.net_basis, bx.grad), net(by.inputs, by.net_basis, by.grad),
                      bx.basis, by.basis)[0][0].double().numpy()  # fmt: skip
    return nearest_neighbor(arrays_y["values"], arrays_x["values"] @ C_xy.T)


def main(argv: list[str] | None = None) -> dict:
    """Run the example; returns ``{'losses': [total per step], 'error_before', 'error_after'}``
    (errors None without a ground truth) and ``'mass'``: the layers' total area (1)."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("x", nargs="?", type=Path, help="source mesh (default: the demo's blob_a)")
    parser.add_argument("y", nargs="?", type=Path, help="target mesh (default: the demo's blob_b)")
    parser.add_argument("--gt", type=Path, help="the true map y -> x (demo: its shipped map)")
    parser.add_argument("--max-steps", type=int, default=5, help="optimiser steps")
    parser.add_argument("--k", type=int, default=30, help="the functional map's basis size")
    parser.add_argument("--network", choices=("diffusionnet", "own"), default="diffusionnet")
    parser.add_argument("--scale", type=float, default=1.0, help="multiply both meshes' coordinates")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    demo_x, demo_y, demo_gt = demo_pair_paths()
    x = tf.load_mesh(args.x or demo_x).scaled(args.scale)  # any units
    y = tf.load_mesh(args.y or demo_y).scaled(args.scale)
    gt_file = args.gt or (demo_gt if args.x is None else None)
    print(f"areas in the meshes' units: x {x.area:.4g}, y {y.area:.4g}")

    # 1. each shape prepared once, in its unit-area frame; its arrays; a batch of both directions
    shapes = [tf.prepare_shape(mesh, K_NET) for mesh in (x, y)]
    arrays = [shape_arrays(s, k=args.k, n_wks=N_WKS, k_net=K_NET) for s in shapes]
    items = [shape_item(a, "wks", index=i) for i, a in enumerate(arrays)]  # float32 tensors
    batch = collate_pairs([(items[0], items[1]), (items[1], items[0])])  # (x, y) and (y, x)
    mass = float(items[0]["mass"].sum())
    print(f"the layers' frame: mass sums to {mass:.4f}; solver basis {tuple(items[0]['values'].shape)}")
    # a basis of your own (here the eigenbasis in file units) enters the layers in the same frame
    own = BasisModule(tf.laplacian_eigenbasis(x, args.k))
    print(f"BasisModule of x's eigenbasis in file units: mass sums to {float(own.mass.sum()):.4f}, "
          f"lam[1] {float(own.lam[1]):.4f} (prepared: {float(batch['x'].basis.lam[0, 1]):.4f})")  # fmt: skip

    # 2. the network, the solver, the loss, the optimiser
    with torch.random.fork_rng(devices=[]):  # the same initial weights every run; global RNG untouched
        torch.manual_seed(args.seed)
        if args.network == "diffusionnet":
            net = DiffusionNet(c_in=N_WKS, c_out=32, width=32, n_blocks=2, dropout=0.0)
        else:
            net = OwnNet(N_WKS)
    solver = RegularizedFMSolver(w_lap=1e-3)
    loss_fn = UnsupervisedFMLoss(w_bij=1.0, w_orth=1.0, w_couple=1.0, n_samples=500)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    draws = torch.Generator().manual_seed(args.seed)  # the coupling term's random vertices

    gt = gt_from_map(read_map(gt_file)) if gt_file else None
    rows = DistanceRows(x) if gt is not None else None

    def error() -> float | None:
        if gt is None:
            return None
        net.eval()
        p2p_yx = point_map(net, solver, batch, arrays[0], arrays[1])
        net.train()
        # units of sqrt(area), on 500 ground-truth points (as torchfmap.nn.evaluate)
        return evaluate_map(x, y, p2p_yx, gt, solver=rows, max_points=500)[0].mean_error

    before = error()
    losses = []
    net.train()
    for step in range(args.max_steps):  # 3. the loop
        bx, by = batch["x"], batch["y"]
        feat_x = net(bx.inputs, bx.net_basis, bx.grad)  # (2, V_x, 32)
        feat_y = net(by.inputs, by.net_basis, by.grad)
        C_xy, C_yx = solver(feat_x, feat_y, bx.basis, by.basis)  # (2, K, K) each
        terms = loss_fn(C_xy, C_yx, feat_x, feat_y, bx.basis, by.basis, generator=draws)
        opt.zero_grad()
        terms["total"].backward()
        opt.step()
        values = {name: v.item() for name, v in terms.items()}
        losses.append(values["total"])
        print(f"step {step + 1}: " + ", ".join(f"{name} {v:.3f}" for name, v in values.items()))
    after = error()  # 4. the map and its error
    if gt is not None:
        print(f"mean geodesic error: untrained {before:.4f} -> after {args.max_steps} steps {after:.4f}")
    return {"losses": losses, "error_before": before, "error_after": after, "mass": mass}


if __name__ == "__main__":
    main()
