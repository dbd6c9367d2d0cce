"""Inference on dataset items: :func:`predict_p2p`, :func:`adapt` and :func:`evaluate`."""

from __future__ import annotations

import copy

import numpy as np
import torch

from ..errors import ParameterError
from ..evaluate.scores import geodesic_errors
from ..fmap.convert import values_to_p2p
from ..fmap.nearest import nearest_neighbor
from ..mesh import Mesh
from .data import ShapeBatch, ShapeDataset, collate_pairs
from .modules import RegularizedFMSolver
from .networks import check_network, features
from .train import pair_loss


def pair_batches(x: dict, y: dict, device) -> tuple[ShapeBatch, ShapeBatch]:
    """Both items as batches of one, collated once."""
    batch = collate_pairs([(x, y)])
    return batch["x"].to(device), batch["y"].to(device)


def solve_xy(solver, fx, fy, bx, by) -> torch.Tensor:
    """``C_xy (B, K_y, K_x)`` only: the reference solver is asked for one direction."""
    if isinstance(solver, RegularizedFMSolver) and solver.both:
        solver = copy.copy(solver)  # a shallow copy: same settings, one direction
        solver.both = False
    return solver(fx, fy, bx, by)[0]


@torch.no_grad()
def predict_p2p(
    net, solver, x: dict, y: dict, *, mode: str = "fmap", p2p_mode: str = "orthogonal", device="cpu"
) -> np.ndarray:
    """``p2p_yx`` of two dataset items: ``mode='fmap'`` from ``C_xy`` in float64 by ``p2p_mode``
    (``'orthogonal'``: rows of ``Φ_y`` among those of ``Φ_x C_xyᵀ``; ``'pullback'``: rows of ``Φ_y C_xy``
    among those of ``Φ_x``), ``mode='features'`` by nearest normalised features."""
    check_network(net)
    net.eval()
    sx, sy = pair_batches(x, y, device)
    fx, fy = features(net, sx), features(net, sy)
    if mode == "features":
        a, b = (torch.nn.functional.normalize(f[0], dim=-1).double().cpu().numpy() for f in (fy, fx))
        return nearest_neighbor(a, b, precision="single")
    if mode != "fmap":
        raise ParameterError(f"unknown mode {mode!r}. Fix: 'fmap' or 'features'.")
    if p2p_mode not in ("orthogonal", "pullback"):
        raise ParameterError(f"unknown p2p_mode {p2p_mode!r}. Fix: 'orthogonal' or 'pullback'.")
    C = solve_xy(solver, fx, fy, sx.basis, sy.basis)[0].double().cpu().numpy()
    phi_x, phi_y = (item["values"].double().numpy() for item in (x, y))
    return values_to_p2p(C, phi_x, phi_y, mode=p2p_mode, precision="double")


def adapt(
    net,
    solver,
    loss_fn,
    x: dict,
    y: dict,
    *,
    steps: int = 10,
    lr: float = 1e-4,
    device="cpu",
    generator: torch.Generator | None = None,
):
    """A copy of ``net`` after ``steps`` Adam steps of ``loss_fn`` on the pair (``generator``: seed 0)."""
    if steps < 0:
        raise ParameterError(f"steps must be >= 0, got {steps}.")
    check_network(net)
    generator = torch.Generator(device=device).manual_seed(0) if generator is None else generator
    tuned = copy.deepcopy(net).to(device).train()
    opt = torch.optim.Adam(tuned.parameters(), lr=lr)
    batch = collate_pairs([(x, y), (y, x)])
    batch = {**batch, "x": batch["x"].to(device), "y": batch["y"].to(device)}
    for _ in range(steps):
        terms = pair_loss(tuned, solver, loss_fn, batch, generator)
        opt.zero_grad(set_to_none=True)
        terms["total"].backward()
        opt.step()
    return tuned.eval()


def evaluate(
    net, shapes: ShapeDataset, pairs, gts, solver, *, mode: str = "fmap", max_points=500, device="cpu"
) -> float:
    """Mean normalised geodesic error of :func:`predict_p2p` over ``pairs`` against ``gts``. Raises
    :class:`ParameterError`: no solver."""
    if solver is None:
        raise ParameterError(
            "evaluate needs the model's solver. Fix: build_solver(config)[0] with the model's recipe "
            "(load_checkpoint returns it)."
        )
    errors = []
    for (a, b), gt in zip(pairs, gts, strict=True):
        x, y = shapes[a], shapes[b]
        p2p = predict_p2p(net, solver, x, y, mode=mode, device=device)
        mesh_x = Mesh(x["vertices"].numpy(), x["faces"].numpy(), validate=False)
        errors.append(geodesic_errors(mesh_x, p2p, gt, max_points=max_points).mean())
    return float(np.mean(errors))
