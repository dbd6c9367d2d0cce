"""Inference on dataset items (:class:`~torchfmap.nn.data.ShapeDataset`): a pair collated as
batches of one (:func:`pair_batches`), the learned map of one direction (:func:`solve_xy`), point
maps (:func:`predict_p2p`), unsupervised test-time adaptation (:func:`adapt`) and the mean
geodesic error of a dataset's pairs (:func:`evaluate`). :class:`~torchfmap.nn.LearnedMatcher`
matches meshes with them."""

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
    """``p2p_yx`` of one pair of dataset items (:class:`~torchfmap.nn.data.ShapeDataset`).

    ``mode='fmap'``: learned features -> ``C_xy`` -> point map by ``p2p_mode``:
    ``'orthogonal'`` (default: nearest neighbour of each row of ``Φ_y`` among the rows of
    ``Φ_x C_xyᵀ``; the recipe's orthogonality loss makes ``C_xy`` near-orthogonal, and this is
    the rule :func:`torchfmap.fmap.fmap_to_p2p` uses for such maps) or ``'pullback'``
    (rows of ``Φ_y C_xy`` among those of ``Φ_x``), searched in float64 as
    :class:`~torchfmap.nn.LearnedMatcher` does (one point-map rule for both). ``mode='features'``:
    nearest neighbours in the (normalised) feature space.
    """
    check_network(net)
    net.eval()
    sx, sy = pair_batches(x, y, device)
    fx, fy = features(net, sx), features(net, sy)
    if mode == "features":
        a = torch.nn.functional.normalize(fy[0], dim=-1).double().cpu().numpy()
        b = torch.nn.functional.normalize(fx[0], dim=-1).double().cpu().numpy()
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
    """Unsupervised test-time adaptation: a copy of ``net`` after ``steps`` Adam steps of
    ``loss_fn`` on the pair ``(x, y)`` itself (no ground truth). ``net`` is left unchanged.
    The loss's random draws come from ``generator`` (None: a new one on ``device`` seeded 0, so
    the same call gives the same network)."""
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
    """Mean normalised geodesic error over ``pairs`` (index pairs) with ground truths ``gts``,
    the maps of :func:`predict_p2p` with ``solver``: the model's own
    (:func:`~torchfmap.nn.build_solver` of its recipe, e.g. the checkpoint's
    :class:`~torchfmap.nn.TrainConfig`), since the regularisation weights change the maps.

    Raises:
        ParameterError: no solver.
    """
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
