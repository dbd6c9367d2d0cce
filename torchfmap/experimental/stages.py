"""The self-seeded second stage of the learned path (an experiment): the features solved again in bases at
seed pairs of the detached stage-1 maps (:func:`~torchfmap.seeds.consistent_seeds`,
:func:`~torchfmap.bases.prepared.seed_kernels`, :func:`~torchfmap.bases.orthonormalize_pair`); a plug-in
loss (:class:`StageTwoLoss`), :func:`two_stage_p2p`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from ..bases.basis import Basis, Column
from ..bases.orthonormalize import orthonormalize_pair
from ..bases.prepared import PreparedShape, prepare_shape, seed_kernels
from ..bases.stack import concatenate
from ..errors import ParameterError
from ..fmap.convert import values_to_p2p
from ..kinds import seed_time
from ..mesh import Mesh
from ..nn.item_inference import pair_batches
from ..nn.modules import BasisModule
from ..nn.networks import check_network, features
from .seeded import map_seeds

#: Farthest-point seeds of ``x`` offered to the second stage, and the fewest it needs (else skipped).
STAGE2_SEEDS = 40
STAGE2_MIN_SEEDS = 8


@dataclass
class StageTwo:
    """Settings and per-shape state of the second stage: :attr:`n_seeds` farthest points offered, at least
    ``min_seeds`` (>= 2, <= ``n_seeds``, else ParameterError) consistent pairs needed; ``shapes``: the
    :class:`~torchfmap.bases.prepared.PreparedShape` of each key (:meth:`shape`). :meth:`solve` solves."""

    n_seeds: int = STAGE2_SEEDS
    min_seeds: int = STAGE2_MIN_SEEDS
    shapes: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.min_seeds < 2 or self.n_seeds < self.min_seeds:
            raise ParameterError(
                f"the second stage needs 2 <= min_seeds <= n_seeds, got {self.min_seeds}, {self.n_seeds}."
            )

    def shape(self, key, mesh: Mesh) -> PreparedShape:
        """The prepared shape of ``key`` (operators only; eigenpairs are not needed), made once."""
        if key not in self.shapes:
            self.shapes[key] = prepare_shape(mesh, 0)
        return self.shapes[key]

    def seeds(self, shape_x, C_xy, C_yx, values_x, values_y, landmarks=None) -> np.ndarray:
        """Seed pairs ``(S, 2)`` of the stage-1 maps ``C_xy (K_y, K_x)``, ``C_yx (K_x, K_y)`` in the
        eigenbases ``values_x (V_x, K_x)``, ``values_y (V_y, K_y)``, landmarks first
        (:func:`~torchfmap.experimental.seeded.map_seeds`)."""
        return map_seeds(shape_x, C_xy, C_yx, values_x, values_y, self.n_seeds, landmarks)

    def run(self, solver, shape_x, shape_y, feat_x, feat_y, C_xy, C_yx, values_x, values_y, landmarks=None):
        """Stage 2 from numpy stage-1 maps and features ``(1, V, D)``: ``(seeds, basis_x, basis_y, solved)``
        (``solved``: :meth:`solve`'s), or None with fewer than :attr:`min_seeds` seeds."""
        seeds = self.seeds(shape_x, C_xy, C_yx, values_x, values_y, landmarks)
        if len(seeds) < self.min_seeds:
            return None
        bx, by = self.bases(shape_x, shape_y, seeds, values_x, values_y)
        return seeds, bx, by, self.solve(solver, feat_x, feat_y, bx, by)

    @staticmethod
    def bases(
        shape_x: PreparedShape,
        shape_y: PreparedShape,
        seeds: np.ndarray,
        eigen_x: np.ndarray,
        eigen_y: np.ndarray,
    ) -> tuple[Basis, Basis]:
        """Stage-2 bases ``(V, K + S')``: the eigenbasis values ``eigen_* (V, K)``, then heat kernels at
        ``seeds`` ``(S, 2)`` (time :func:`~torchfmap.kinds.seed_time` of ``S``), orthonormalised as a pair."""
        t = seed_time(len(seeds))
        blocks = []
        for shape, eigen, side in ((shape_x, eigen_x, 0), (shape_y, eigen_y, 1)):
            L, B = shape.operators
            cols = [Column("laplacian", index=i) for i in range(eigen.shape[1])]
            eig = Basis(np.asarray(eigen, dtype=np.float64), B, cols, stiffness=L)
            blocks.append(concatenate([eig, seed_kernels(shape, seeds[:, side], [t])]))
        return orthonormalize_pair(*blocks)

    @staticmethod
    def solve(solver, feat_x: torch.Tensor, feat_y: torch.Tensor, basis_x: Basis, basis_y: Basis):
        """``(C_xy (1, K', K'), C_yx, batch_x, batch_y)``: the features ``(1, V, D)`` solved by
        ``solver`` in the stage-2 bases (cast to the features' dtype and device)."""
        bx, by = (BasisModule(b, dtype=feat_x.dtype).to(feat_x.device).batch() for b in (basis_x, basis_y))
        C_xy, C_yx = solver(feat_x, feat_y, bx, by)
        return C_xy, C_yx, bx, by

    @staticmethod
    def p2p(C_xy: torch.Tensor, basis_x: Basis, basis_y: Basis) -> np.ndarray:
        """``p2p_yx (V_y,)`` of a stage-2 map by the orthogonal rule (as stage 1)."""
        C = C_xy[0].detach().double().cpu().numpy()
        return values_to_p2p(C, basis_x.values, basis_y.values, mode="orthogonal")


def _check_both(C_yx) -> None:
    if C_yx is None:
        raise ParameterError(
            "the second stage needs both directions of stage 1. Fix: a solver with both=True."
        )


@torch.no_grad()
def two_stage_p2p(
    net,
    solver,
    x: dict,
    y: dict,
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    stage: StageTwo,
    device="cpu",
    landmarks: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """``(p2p_yx of stage 1, p2p_yx of stage 2, seed pairs used)`` of one pair of
    :class:`~torchfmap.nn.data.ShapeDataset` items prepared as ``shape_x``, ``shape_y`` (too few seeds: stage
    1's map twice, 0); ``landmarks`` ``(L, 2)``: seed pairs placed first."""
    check_network(net)
    net.eval()
    sx, sy = pair_batches(x, y, device)
    fx, fy = features(net, sx), features(net, sy)
    C_xy, C_yx = solver(fx, fy, sx.basis, sy.basis)
    _check_both(C_yx)
    vx, vy = x["values"].double().numpy(), y["values"].double().numpy()
    Cxy, Cyx = (C[0].double().cpu().numpy() for C in (C_xy, C_yx))
    first = values_to_p2p(Cxy, vx, vy, mode="orthogonal")
    second = stage.run(solver, shape_x, shape_y, fx, fy, Cxy, Cyx, vx, vy, landmarks)
    if second is None:
        return first, first, 0
    seeds, bx, by, (C2, *_) = second
    return first, stage.p2p(C2, bx, by), len(seeds)


def stage_two_loss(
    stage: StageTwo, solver, loss_fn, out, batch: dict, mesh_of, generator=None
) -> dict | None:
    """``loss_fn`` of the stage-2 maps of a batch of one pair, from the detached stage-1 maps of ``out``
    (:class:`~torchfmap.nn.train.PairForward`), on shapes ``mesh_of(dataset index) -> Mesh``; None when
    too few seeds are consistent. ParameterError for more than one pair or a solver without ``C_yx``."""
    if len(batch["index"]) != 1:
        raise ParameterError("the second stage trains on batches of one pair. Fix: batch_size=1.")
    _check_both(out.C_yx)
    ix, iy = batch["index"][0]
    shape_x, shape_y = stage.shape(ix, mesh_of(ix)), stage.shape(iy, mesh_of(iy))
    vx = batch["x"].basis.values[0].detach().double().cpu().numpy()
    vy = batch["y"].basis.values[0].detach().double().cpu().numpy()
    Cxy, Cyx = (C[0].detach().double().cpu().numpy() for C in (out.C_xy, out.C_yx))
    second = stage.run(solver, shape_x, shape_y, out.feat_x, out.feat_y, Cxy, Cyx, vx, vy)
    if second is None:
        return None
    C_xy, C_yx, Bx, By = second[3]
    return loss_fn(C_xy, C_yx, out.feat_x, out.feat_y, Bx, By, generator=generator)


@dataclass
class StageTwoLoss:
    """The second stage as a plug-in loss (:class:`~torchfmap.nn.train.ExtraLoss`): :func:`stage_two_loss`
    with the trainer's solver and loss, logged as ``stage2_<term>``, zeros when seeds are too few.
    ``mesh_of``: e.g. :meth:`~torchfmap.nn.data.ShapeDataset.mesh`; batches of one pair."""

    mesh_of: Callable[[int], Mesh]
    stage: StageTwo = field(default_factory=StageTwo)
    name: str = "stage2"

    def __call__(self, out, batch: dict, *, solver, loss_fn, generator=None) -> dict:
        second = stage_two_loss(self.stage, solver, loss_fn, out, batch, self.mesh_of, generator)
        if second is None:
            return {"total": out.C_xy.sum() * 0}  # zeros on the graph's device and dtype
        return second
