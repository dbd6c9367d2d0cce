"""Matching two meshes with a trained network (:class:`LearnedMatcher`)."""

from __future__ import annotations

import copy
import os
import time

import numpy as np
import torch

from ..bases.basis import Basis
from ..bases.prepared import PreparedShape, check_prepared, prepare_shape, with_eigenpairs
from ..errors import ParameterError
from ..fmap.convert import fmap_to_p2p, p2p_to_fmap
from ..fmap.refine import Refined, check_k_final
from ..kinds import get_kind
from ..kinds.refiners import ZoomOut, check_refine, pair_samplings
from ..matching.checks import check_meshes, check_unused, warn_if_partial
from ..matching.partial import match_partial, shot_descriptors
from ..matching.results import MatchResult, refine_result
from ..mesh import Mesh
from .augment import move_xyz, yaw_matrices
from .checkpoints import load_checkpoint
from .coarse import Simplification, check_coarse, coarse_size, simplify
from .config import TrainConfig, build_solver
from .data import ShapeBatch
from .devices import resolve_device
from .functional import BasisBatch
from .inputs import K_WKS, SEED_TIMES, coordinates_on, has_coordinates, has_shot, shape_arrays, shape_item
from .item_inference import adapt, pair_batches, solve_xy
from .modules import basis_arrays
from .networks import check_network, features

#: Yaw angles (radians) tried by :meth:`LearnedMatcher.facings` for models trained facing anywhere.
FACINGS = (0.0, np.pi / 2, np.pi, 3 * np.pi / 2)


def laplacian_defect(C: torch.Tensor, basis_x, basis_y) -> float:
    """``‖C W_x - W_y C‖ / ‖C‖`` of ``C (K_y, K_x)`` between one-shape bases: 0 if isometric."""
    C = C.to(torch.float64)
    W = [(b.U[0] * b.lam[0][None, :]) @ b.U[0].T for b in (basis_x, basis_y)]
    W = [w.to(torch.float64) for w in W]
    return float(torch.linalg.norm(C @ W[0] - W[1] @ C) / torch.linalg.norm(C))


def _zoomout_sizes(k: int, k_final: int | None, n_vertices: tuple[int, int]) -> tuple[int, int]:
    """``(k0, k_final)``: ``k`` to ``k_final`` (None: ``2k``), capped at ``V - 1`` of the smaller mesh."""
    check_k_final(k, k_final)
    cap = min(n_vertices) - 1
    return min(k, cap), min(2 * k if k_final is None else k_final, cap)


def _zoomout(
    p2p_yx: np.ndarray,
    shapes: tuple[PreparedShape, ...],
    k0: int,
    k_final: int,
    feats: tuple[np.ndarray, np.ndarray],
) -> Refined:
    """ZoomOut of ``p2p_yx`` from ``k0`` to ``k_final``, each step also matching the features ``feats``."""
    bx, by = (s.eigenbasis.truncated(k0) for s in shapes)
    C_xy = p2p_to_fmap(p2p_yx, bx, by)
    refiner = ZoomOut(k_final=k_final, mode="orthogonal", features=feats)
    return refiner(C_xy, p2p_yx, *shapes, bx, by)


def _solver_batch(basis: Basis, batch: ShapeBatch, simple: Simplification | None) -> BasisBatch:
    """The solver's one-side basis batch: ``batch.basis``, or with ``simple`` the dense ``basis``."""
    if simple is None:
        return batch.basis
    like, arrays = batch.inputs, basis_arrays(basis)
    t = {key: torch.as_tensor(a, dtype=like.dtype, device=like.device)[None] for key, a in arrays.items()}
    valid = torch.ones(1, t["values"].shape[-1], dtype=like.dtype, device=like.device)
    return BasisBatch(t["values"], t["mass"], t["lam"], t["U"], valid)


def _carried(net, batch: ShapeBatch, simple: Simplification | None) -> torch.Tensor:
    """The network's features ``(1, V, D)`` of one side, carried from a simplification to every vertex."""
    out = features(net, batch)
    return out if simple is None else simple.carry(out)


class LearnedMatcher:
    """Matches meshes with a trained network: ``matcher(mesh_x, mesh_y)`` returns a
    :class:`~torchfmap.matching.results.MatchResult` like :func:`torchfmap.match`.

    Each mesh is prepared once (:func:`~torchfmap.prepare_shape`, float64 on the CPU); the network (adapted to
    the pair first when ``adapt_steps > 0``, :func:`adapt`) and the solver run on ``device``; the point map is
    the orthogonal rule of :func:`~torchfmap.fmap.fmap_to_p2p`, float64 on the CPU. On a mesh of more vertices
    than ``coarse`` allows, the network runs on a :func:`~torchfmap.nn.coarse.simplify` of it and its features
    are carried to every vertex; the map is solved in the dense mesh's basis. Build it from a network and its
    recipe or with :meth:`from_checkpoint`; it keeps nothing between calls and pickles.

    Args:
        net, config: a :class:`~torchfmap.nn.networks.FeatureNetwork` (moved to ``device``) and its
            :class:`~torchfmap.nn.TrainConfig`.
        name: the result's ``model``.
        device: ``'auto'``, ``'cpu'``, ``'cuda'`` or a :class:`torch.device`.
        adapt_steps, adapt_lr: unsupervised test-time adaptation per pair (0: none).
        coarse: ``'auto'``, an int ``n`` or None (:func:`~torchfmap.nn.coarse.coarse_size`).

    Raises:
        ParameterError: ``adapt_steps`` not an integer >= 0, an unknown or absent device, a network that
            does not follow the protocol, or a bad ``coarse``."""

    def __init__(
        self,
        net: torch.nn.Module,
        config: TrainConfig,
        *,
        name: str = "network",
        device: str | torch.device | None = "auto",
        adapt_steps: int = 0,
        adapt_lr: float = 1e-4,
        coarse: str | int | None = "auto",
    ) -> None:
        self.coarse = check_coarse(coarse)
        if isinstance(adapt_steps, bool) or not isinstance(adapt_steps, (int, np.integer)) or adapt_steps < 0:
            raise ParameterError(f"adapt_steps must be an integer >= 0, got {adapt_steps!r}.")
        check_network(net)
        self.device_setting, self.device = device, resolve_device(device)
        self.net = net.to(self.device).eval()
        self.config, self.name = config, str(name)
        self.adapt_steps, self.adapt_lr = int(adapt_steps), float(adapt_lr)
        self.checkpoint: str | os.PathLike | None = None
        self.solver, self.loss_fn = build_solver(config)

    @classmethod
    def from_checkpoint(
        cls,
        name_or_path: str | os.PathLike,
        *,
        device: str | torch.device | None = "auto",
        adapt_steps: int = 0,
        adapt_lr: float = 1e-4,
        coarse: str | int | None = "auto",
    ) -> LearnedMatcher:
        """The matcher of a checkpoint path or shipped name (best weights); raises
        (:class:`CorruptFileError`, :class:`ParameterError`) as
        :func:`~torchfmap.nn.checkpoints.load_checkpoint` and ``__init__``."""
        net, config, _ = load_checkpoint(name_or_path)
        settings = dict(device=device, adapt_steps=adapt_steps, adapt_lr=adapt_lr, coarse=coarse)
        matcher = cls(net, config, name=os.fspath(name_or_path), **settings)
        matcher.checkpoint = name_or_path
        return matcher

    def __getstate__(self) -> dict:
        settings = {"device": self.device_setting, "adapt_steps": self.adapt_steps, "adapt_lr": self.adapt_lr,
                    "coarse": self.coarse}  # fmt: skip
        if self.checkpoint is not None:  # loaded again where it is unpickled
            return {"checkpoint": self.checkpoint, "settings": settings}
        net = copy.deepcopy(self.net).cpu()  # a CPU copy: it may be unpickled where there is no GPU
        return {"net": net, "config": self.config, "settings": {**settings, "name": self.name}}

    def __setstate__(self, state: dict) -> None:
        if "checkpoint" in state:
            loaded = LearnedMatcher.from_checkpoint(state["checkpoint"], **state["settings"])
            self.__dict__.update(loaded.__dict__)
        else:
            self.__init__(state["net"], state["config"], **state["settings"])

    def __repr__(self) -> str:
        return (
            f"LearnedMatcher({self.name!r}, k={self.config.k}, basis={self.config.basis!r}, "
            f"device={str(self.device)!r}, adapt_steps={self.adapt_steps}, coarse={self.coarse!r})"
        )

    def facings(self) -> tuple[float, ...]:
        """Yaw angles (radians, about ``y``) the target's inputs are tried at: :data:`FACINGS` for an XYZ
        model trained with ``augment='up'`` (least :func:`laplacian_defect` kept), else ``(0,)``."""
        cfg = self.config
        return FACINGS if has_coordinates(cfg.inputs) and cfg.augment == "up" else (0.0,)

    def _eigenpairs(self, n_vertices: int, k_final: int = 0, network: bool = True) -> int:
        """Eigenpairs a mesh of ``n_vertices`` needs (more if the ``network`` runs on it), below
        ``n_vertices``."""
        cfg = self.config
        need = max(cfg.k, cfg.k_net, K_WKS, k_final) if network else max(cfg.k, k_final)
        return min(need, n_vertices - 1)

    def _runs_on(self, mesh: Mesh) -> bool:
        """Whether the network runs on ``mesh`` itself (not on a simplification)."""
        return coarse_size(self.coarse, mesh.n_vertices) is None

    def _network_shape(self, shape: PreparedShape) -> tuple[PreparedShape, Simplification | None]:
        """``(prepared shape the network runs on, its simplification or None)``, kept in ``shape``."""
        n = coarse_size(self.coarse, shape.mesh.n_vertices)
        if n is None:
            return shape, None
        simple = shape.derive(("simplification", n), lambda: simplify(shape.mesh, n))
        coarse = shape.derive(("simplification shape", n), lambda: prepare_shape(simple.mesh, 0))
        return with_eigenpairs(coarse, self._eigenpairs(simple.mesh.n_vertices)), simple

    def _items(
        self, shape: PreparedShape, index: int, whole: PreparedShape | None = None
    ) -> tuple[dict, Basis, Simplification | None]:
        """``(item, float64 solver basis, simplification)``; ``whole`` as in :meth:`features`."""
        cfg = self.config
        net_shape, simple = self._network_shape(shape)
        shot = has_shot(cfg.inputs)
        own = shot and whole is None  # a part's SHOT is computed once, at its whole's radius
        arrays = shape_arrays(net_shape, cfg.k, cfg.n_wks, k_net=cfg.k_net, basis=cfg.basis, shot=own)
        if whole is not None:
            arrays["xyz"] = coordinates_on(net_shape.mesh, whole)
            if shot:
                arrays["shot"] = shot_descriptors(net_shape, whole)
        dtype = next(self.net.parameters()).dtype
        item = shape_item(arrays, cfg.inputs, dtype=dtype, name=shape.mesh.name or "", index=index)
        return item, get_kind(cfg.basis).shape_basis(shape, cfg.k, times=SEED_TIMES), simple

    def features(
        self,
        mesh: Mesh,
        *,
        shape: PreparedShape | None = None,
        whole: PreparedShape | None = None,
    ) -> np.ndarray:
        """``(V, D)`` float64: the network's features of ``mesh`` as it lies (no adaptation, no facings).

        Args:
            shape: ``prepare_shape(mesh, n)`` to reuse (grown in place when needed).
            whole: for a part (same units), its whole's prepared shape: coordinate inputs are taken in
                the whole's frame, SHOT at the whole's radius.

        Raises:
            ParameterError: ``mesh`` is not a mesh, ``shape`` not one of it, ``whole`` not a prepared
                shape, or the mesh is too small for ``k``."""
        check_meshes(mesh, mesh)
        need = self._eigenpairs(mesh.n_vertices, network=self._runs_on(mesh))
        if shape is None:
            shape = prepare_shape(mesh, need)
        elif not isinstance(shape, PreparedShape) or shape.mesh is not mesh:
            raise ParameterError("shape must be prepare_shape(mesh, n) of this mesh.")
        else:
            shape = with_eigenpairs(shape, need)
        if whole is not None and not isinstance(whole, PreparedShape):
            raise ParameterError(
                f"whole must be the whole's prepare_shape(mesh, n), got {type(whole).__name__}."
            )
        item, _, simple = self._items(shape, 0, whole)
        with torch.no_grad():
            batch, _ = pair_batches(item, item, self.device)
            return _carried(self.net, batch, simple)[0].to(torch.float64).cpu().numpy()

    def _prepared(self, meshes: tuple[Mesh, Mesh], shapes, k_final: int) -> tuple[PreparedShape, ...]:
        """The pair's prepared shapes (``shapes`` checked and grown, or new) with their eigenpairs."""
        n = min(m.n_vertices for m in meshes)
        need = [self._eigenpairs(n, k_final, self._runs_on(m)) for m in meshes]
        if shapes is None:
            return tuple(prepare_shape(m, k) for m, k in zip(meshes, need, strict=True))
        shapes = check_prepared(shapes, meshes)
        return tuple(with_eigenpairs(s, k) for s, k in zip(shapes, need, strict=True))

    def _partial(self, mesh_x: Mesh, mesh_y: Mesh, refine, k_final, shapes) -> MatchResult:
        """The partial map of :meth:`__call__` (``partial=True``)."""
        if self.adapt_steps:
            raise ParameterError(
                "test-time adaptation tunes the network by the whole-shape loss, which a part "
                "breaks. Fix: adapt_steps=0 (CLI: no --adapt) with partial=True."
            )
        t0 = time.perf_counter()
        k, sizes = self.config.k, (mesh_x.n_vertices, mesh_y.n_vertices)
        k0, k_final = _zoomout_sizes(k, k_final, sizes) if refine else (min(k, min(sizes) - 1), None)
        shapes = self._prepared((mesh_x, mesh_y), shapes, k_final or 0)
        feats_y = self.features(mesh_y, shape=shapes[1], whole=shapes[0])
        feats = self.features(mesh_x, shape=shapes[0]), feats_y
        seconds = time.perf_counter() - t0
        result = match_partial(
            *shapes, k=k0, refine=refine, k_final=k_final, descriptors=feats, with_shot=True
        )
        result.timings, result.model = {"prepare+network": seconds, **result.timings}, self.name
        return result

    def __call__(
        self,
        mesh_x: Mesh,
        mesh_y: Mesh,
        *,
        refine: str | None = None,
        k_final: int | None = None,
        shapes: tuple[PreparedShape, PreparedShape] | None = None,
        partial: bool = False,
    ) -> MatchResult:
        """The map ``y -> x``: ``p2p_yx (V_y,)``, ``C_xy`` and its bases, ``p2p_yx_initial``, ``kind``,
        ``model``, ``timings`` (s).

        Args:
            refine: ``'zoomout'`` (from the network's map, ``k`` to ``k_final``, default ``2k``, capped at
                ``V - 1``; each step also matches the network's features) or None.
            shapes: ``(prepare_shape(mesh_x, n), prepare_shape(mesh_y, n))`` to reuse (grown in place).
            partial: ``y`` is a part of ``x`` (same units): :func:`~torchfmap.matching.partial.match_partial`
                with the network's :meth:`features` next to SHOT (``with_shot``; the part's inputs taken as it
                lies on the whole: a coordinate model needs the part in its whole's frame, a SHOT model does
                not); with ``overlap`` and ``partial_rank``.

        Raises:
            ParameterError: inputs that are not meshes, another refinement, ``k_final`` without ZoomOut or
                below ``k``, ``shapes`` not of these meshes, meshes too small for ``k``; ``partial`` with
                adaptation or a part larger than the whole."""
        check_meshes(mesh_x, mesh_y)
        if not partial:
            warn_if_partial(mesh_x, mesh_y)
        check_refine(refine, allowed=("zoomout",), what="the learned path")
        check_unused(get_kind("laplacian"), refine, k_final, None)
        if partial:
            return self._partial(mesh_x, mesh_y, refine, k_final, shapes)
        cfg = self.config
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        sizes = (mesh_x.n_vertices, mesh_y.n_vertices)
        k0, k_final = _zoomout_sizes(cfg.k, k_final, sizes) if refine else (cfg.k, None)
        shapes = self._prepared((mesh_x, mesh_y), shapes, k_final or 0)  # one eigendecomposition each
        (ix, bx, simple_x), (iy, by, simple_y) = (self._items(s, i) for i, s in enumerate(shapes))
        timings["prepare"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        net = self.net
        if self.adapt_steps:
            net = adapt(net, self.solver, self.loss_fn, ix, iy, steps=self.adapt_steps, lr=self.adapt_lr,
                        device=self.device)  # fmt: skip
        timings["adapt"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        with torch.no_grad():
            sx, sy = pair_batches(ix, iy, self.device)
            solver = self.solver.to(self.device)
            basis_x, basis_y = _solver_batch(bx, sx, simple_x), _solver_batch(by, sy, simple_y)
            fx = _carried(net, sx, simple_x)
            C, fy, least = None, None, float("inf")
            for angle in self.facings():  # one facing, or the most isometric of several

                def turn(xyz, a=angle):
                    return xyz @ yaw_matrices(xyz.new_tensor([a]))

                turned = sy._replace(inputs=move_xyz(sy.inputs, turn)) if angle else sy
                fy_a = _carried(net, turned, simple_y)
                C_a = solve_xy(solver, fx, fy_a, basis_x, basis_y)[0]
                defect = laplacian_defect(C_a, basis_x, basis_y)
                if C is None or defect < least:
                    C, fy, least = C_a, fy_a, defect
        timings["network+fmap"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        C_xy = C.to(torch.float64).cpu().numpy()
        samplings = pair_samplings(*shapes)  # dense pairs: searched locally
        p2p = fmap_to_p2p(C_xy, bx, by, mode="orthogonal", precision="double", samplings=samplings)
        timings["p2p"] = time.perf_counter() - t0
        result = MatchResult(p2p, C_xy, bx, by, p2p, timings, kind=cfg.basis, model=self.name)
        if refine is None:
            return result
        feats = tuple(f[0].to(torch.float64).cpu().numpy() for f in (fx, fy))

        def refiner(C_xy, p2p_yx, shape_x, shape_y, basis_x, basis_y, seeds=None):
            return _zoomout(p2p_yx, (shape_x, shape_y), k0, k_final, feats)

        return refine_result(result, refiner, *shapes)  # the one guard
