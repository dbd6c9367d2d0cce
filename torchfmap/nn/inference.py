"""Inference with a trained network: matching two meshes (:class:`LearnedMatcher`, called like
:func:`torchfmap.match` and returning its :class:`~torchfmap.matching.results.MatchResult`); point maps
of dataset items, adaptation and evaluation are in :mod:`~torchfmap.nn.item_inference`."""

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
from ..fmap.defaults import DEFAULT_K
from ..fmap.refine import Refined, check_k_final
from ..kinds import get_kind
from ..kinds.refiners import ZoomOut, check_refine, pair_samplings
from ..matching.checks import check_meshes, check_unused, warn_if_partial
from ..matching.partial import match_partial, shot_descriptors
from ..matching.results import MatchResult, refine_result
from ..mesh import Mesh, rigid_fit
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
    """``‖C W_x - W_y C‖ / ‖C‖`` of one map ``C (K_y, K_x)`` between the bases of two
    :class:`~torchfmap.nn.functional.BasisBatch` of one shape each (``W = U diag(lam) Uᵀ``, the
    projected Laplacian): 0 for an isometry, large for a map that is far from one."""
    C = C.to(torch.float64)
    W = [(b.U[0] * b.lam[0][None, :]) @ b.U[0].T for b in (basis_x, basis_y)]
    W = [w.to(torch.float64) for w in W]
    return float(torch.linalg.norm(C @ W[0] - W[1] @ C) / torch.linalg.norm(C))


def _zoomout_sizes(k: int, k_final: int | None, n_vertices: tuple[int, int]) -> tuple[int, int]:
    """``(k0, k_final)`` of a learned map's ZoomOut: from the model's ``k`` to ``k_final``
    (None: ``2k``), both capped at ``V - 1`` of the smaller mesh.

    Raises:
        ParameterError: ``k_final < k`` (:func:`~torchfmap.fmap.refine.check_k_final`).
    """
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
    """ZoomOut of ``p2p_yx`` in the shapes' eigenbases, from ``(k0, k0)`` to ``k_final``: the
    eigenbasis kind's refinement (:class:`~torchfmap.kinds.refiners.ZoomOut`), every point-map
    step also matching the network's features ``feats`` ``((V_x, D), (V_y, D))`` as anchors, so the
    refinement keeps what the network learned where the spectral embeddings of non-isometric
    shapes disagree (the one call site of the learned path)."""
    bx, by = (s.eigenbasis.truncated(k0) for s in shapes)
    C_xy = p2p_to_fmap(p2p_yx, bx, by)
    refiner = ZoomOut(k_final=k_final, mode="orthogonal", features=feats)
    return refiner(C_xy, p2p_yx, *shapes, bx, by)


def _solver_batch(basis: Basis, batch: ShapeBatch, simple: Simplification | None) -> BasisBatch:
    """The solver's basis of one side as a batch of one: the item's (``batch.basis``) when the
    network ran on the mesh itself, else ``basis`` (of the dense mesh) in ``batch``'s dtype and
    on its device."""
    if simple is None:
        return batch.basis
    like = batch.inputs
    arrays = basis_arrays(basis)
    t = {key: torch.as_tensor(a, dtype=like.dtype, device=like.device)[None] for key, a in arrays.items()}
    valid = torch.ones(1, t["values"].shape[-1], dtype=like.dtype, device=like.device)
    return BasisBatch(t["values"], t["mass"], t["lam"], t["U"], valid)


def _carried(net, batch: ShapeBatch, simple: Simplification | None) -> torch.Tensor:
    """The network's features ``(1, V, D)`` of one side: on its vertices, or on the
    simplification's and carried to every dense vertex (:meth:`Simplification.carry`)."""
    out = features(net, batch)
    return out if simple is None else simple.carry(out)


class LearnedMatcher:
    """Matches meshes with a trained network, called like :func:`torchfmap.match`.

    ``matcher(mesh_x, mesh_y)`` returns the :class:`~torchfmap.matching.results.MatchResult` of the pair:
    each mesh is prepared once (:func:`~torchfmap.prepare_shape`: one Laplacian and one
    eigendecomposition, float64 on the CPU, serving the network's inputs
    (:func:`~torchfmap.nn.inputs.shape_arrays`), its basis and ZoomOut); the network (adapted to
    the pair first when ``adapt_steps > 0``, :func:`adapt`) and the solver run on ``device``,
    and the point map is the orthogonal rule of :func:`~torchfmap.fmap.fmap_to_p2p` (nearest
    neighbours of the rows of ``Φ_y`` among those of ``Φ_x C_xyᵀ``) in float64 on the CPU, from
    the shapes' float64 basis values, searched locally on dense pairs.

    **Dense meshes** (``coarse``): the network runs on a simplification of a mesh of more than
    :data:`~torchfmap.nn.coarse.DENSE_NETWORK_VERTICES` vertices
    (:func:`~torchfmap.nn.coarse.simplify`, :data:`~torchfmap.nn.coarse.COARSE_VERTICES`
    vertices, prepared once and kept in the dense shape) and its features are carried to every
    vertex; the map is solved in the dense mesh's own basis, so the dense mesh needs only
    ``max(k, k_final)`` eigenpairs and no network input (WKS, gradients) of its own.

    Build it with :meth:`from_checkpoint` (a path or a shipped model's name), or from a network
    and its recipe. It keeps nothing between calls: shapes are reused only when the caller
    passes them (``shapes=``, as :func:`torchfmap.evaluate.collection.evaluate_pairs` does). It pickles
    (for a process pool or a cluster executor): one built from a checkpoint as the checkpoint's
    name and its settings, the network loaded again where it is unpickled.

    Args:
        net: a :class:`~torchfmap.nn.networks.FeatureNetwork` (moved to ``device``).
        config: its :class:`~torchfmap.nn.TrainConfig` (basis kind and size ``k``, inputs,
            solver weights).
        name: what the result's ``model`` names.
        device: ``'auto'`` / ``'cpu'`` / ``'cuda'`` / a :class:`torch.device`
            (:func:`~torchfmap.nn.devices.resolve_device`).
        adapt_steps, adapt_lr: unsupervised test-time adaptation per pair (0: none; on the
            simplifications of dense meshes).
        coarse: where the network runs (:func:`~torchfmap.nn.coarse.coarse_size`): ``'auto'``
            (a simplification of dense meshes, see above), an int ``n`` (a simplification of
            ``n`` vertices of every mesh of more), or None (every mesh itself).

    Raises:
        ParameterError: ``adapt_steps`` not an integer >= 0, an unknown or absent device, a
            network that does not follow the protocol, or a bad ``coarse``.
    """

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
        self.device_setting = device
        self.device = resolve_device(device)
        self.net = net.to(self.device).eval()
        self.config = config
        self.name = str(name)
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
        """The matcher of a checkpoint written by ``torchfmap train`` or of a shipped model's
        name (:func:`~torchfmap.nn.shipped.resolve_checkpoint`), read now (its best weights).

        Raises:
            CorruptFileError, ParameterError: an unreadable checkpoint or an unknown name (as
                :func:`~torchfmap.nn.checkpoints.load_checkpoint`), or as the constructor.
        """
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
        """Yaw angles (radians, about ``y``) at which the target's inputs are tried: for an XYZ
        model trained with ``augment='up'`` (shapes standing alike, facing anywhere) the
        :data:`FACINGS` quarter turns, the functional map kept being the most isometric one
        (:func:`laplacian_defect`: a wrong facing maps head to tail, far from an isometry);
        ``(0,)`` for any other model (WKS is invariant, other XYZ models were trained aligned or
        under any rotation)."""
        cfg = self.config
        return FACINGS if has_coordinates(cfg.inputs) and cfg.augment == "up" else (0.0,)

    def _eigenpairs(self, n_vertices: int, k_final: int = 0, network: bool = True) -> int:
        """Eigenpairs one preparation of a mesh of ``n_vertices`` needs: the solver's basis and
        ZoomOut's ``k_final``, with the network's and the WKS inputs' when the network runs on
        it (``network``), at most ``n_vertices - 1``."""
        cfg = self.config
        need = max(cfg.k, cfg.k_net, K_WKS, k_final) if network else max(cfg.k, k_final)
        return min(need, n_vertices - 1)

    def _runs_on(self, mesh: Mesh) -> bool:
        """Whether the network runs on ``mesh`` itself (not on a simplification)."""
        return coarse_size(self.coarse, mesh.n_vertices) is None

    def _network_shape(self, shape: PreparedShape) -> tuple[PreparedShape, Simplification | None]:
        """The prepared shape the network runs on and the simplification it is of (None: the
        shape itself), built once and kept in ``shape`` (:meth:`~torchfmap.PreparedShape.derive`)."""
        n = coarse_size(self.coarse, shape.mesh.n_vertices)
        if n is None:
            return shape, None
        simple = shape.derive(("simplification", n), lambda: simplify(shape.mesh, n))
        coarse = shape.derive(("simplification shape", n), lambda: prepare_shape(simple.mesh, 0))
        return with_eigenpairs(coarse, self._eigenpairs(simple.mesh.n_vertices)), simple

    def _items(
        self, shape: PreparedShape, index: int, whole: PreparedShape | None = None, motion=None
    ) -> tuple[dict, Basis, Simplification | None]:
        """``(dataset item, solver basis, simplification)`` of one prepared shape: the network's
        arrays (:func:`~torchfmap.nn.inputs.shape_arrays`, in the network's dtype) of the shape
        the network runs on (:meth:`_network_shape`), the float64 basis of ``shape`` the map is
        solved in (the same kind's ``shape_basis`` shape_arrays reads) and the simplification
        (None when the network runs on ``shape``). ``whole``, ``motion``: coordinate inputs in
        that shape's frame (:func:`~torchfmap.nn.inputs.coordinates_on`), not ``shape``'s own."""
        cfg = self.config
        net_shape, simple = self._network_shape(shape)
        shot = has_shot(cfg.inputs)
        arrays = shape_arrays(net_shape, cfg.k, cfg.n_wks, k_net=cfg.k_net, basis=cfg.basis, shot=shot)
        if whole is not None:
            arrays["xyz"] = coordinates_on(net_shape.mesh, whole, motion)
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
        motion: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """``(V, D)`` float64: the network's per-vertex features of ``mesh`` as it lies (no
        adaptation, no facings), e.g. as :func:`~torchfmap.matching.partial.match_partial`'s
        ``descriptors`` or for retrieval.

        Args:
            shape: ``prepare_shape(mesh, n)`` to reuse (its eigenbasis is grown in place when
                the network needs more).
            whole: for a part of a whole (same units, lying where it lies on the whole), the
                whole's prepared shape: coordinate inputs are taken in the whole's frame
                (:func:`~torchfmap.nn.inputs.coordinates_on`), so that they agree with the
                whole's at the same points; no effect on a model without coordinate inputs.
            motion: with ``whole``, ``(R (3, 3), t (3,))``: the part placed at
                ``vertices @ R.T + t`` on the whole first (a part saved turned).

        Raises:
            ParameterError: ``mesh`` is not a mesh, ``shape`` not one of it, ``whole`` not a
                prepared shape, or the mesh is too small for the model's ``k``.
        """
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
        if motion is not None and whole is None:
            raise ParameterError("motion places a part on its whole. Fix: pass whole= with it.")
        item, _, simple = self._items(shape, 0, whole, motion)
        with torch.no_grad():
            batch, _ = pair_batches(item, item, self.device)
            return _carried(self.net, batch, simple)[0].to(torch.float64).cpu().numpy()

    def _prepared(self, meshes: tuple[Mesh, Mesh], shapes, k_final: int) -> tuple[PreparedShape, ...]:
        """The pair's prepared shapes (``shapes`` checked and grown, or new), each with the
        eigenpairs :meth:`_eigenpairs` asks of it (at most ``V - 1`` of the smaller mesh)."""
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
        sizes = (mesh_x.n_vertices, mesh_y.n_vertices)
        k0, k_final = (
            _zoomout_sizes(self.config.k, k_final, sizes)
            if refine
            else (min(self.config.k, min(sizes) - 1), None)
        )
        shapes = self._prepared((mesh_x, mesh_y), shapes, k_final or 0)
        feats_x = self.features(mesh_x, shape=shapes[0])
        placements = (
            self.placements(*shapes, k=k0) if has_coordinates(self.config.inputs) else {"as it lies": None}
        )
        seconds = time.perf_counter() - t0
        tried = {}
        for name, motion in placements.items():
            feats_y = self.features(mesh_y, shape=shapes[1], whole=shapes[0], motion=motion)
            tried[name] = match_partial(
                *shapes, k=k0, refine=refine, k_final=k_final, descriptors=(feats_x, feats_y)
            )
        result = next(iter(tried.values()))
        if len(tried) > 1:  # the map a rigid placement explains best
            residual = {n: rigid_fit(mesh_y.vertices, mesh_x.vertices[r.p2p_yx])[2] for n, r in tried.items()}
            best = min(residual, key=residual.get)
            result = tried[best]
            result.placement, result.candidates = best, tried
        result.timings = {"prepare+network": seconds, **result.timings}
        result.model = self.name
        return result

    def placements(
        self, shape_x: PreparedShape, shape_y: PreparedShape, *, k: int = DEFAULT_K
    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Rigid motions ``(R (3, 3), t (3,))`` of a part ``y`` onto its whole ``x`` that a
        coordinate model's partial map tries (:meth:`__call__`, ``partial=True``), by name:
        ``'as it lies'`` (the identity: a part saved in its whole's frame) and ``'fitted'``
        (:func:`~torchfmap.mesh.rigid_fit` of the part onto the images of the classical partial
        map, SHOT descriptors, ``k`` functions, unrefined: rotation-invariant, so a part saved
        turned is put back). Each placement's map is solved and the one a rigid placement
        explains best is kept (the least trimmed residual of :func:`~torchfmap.mesh.rigid_fit`:
        a map that sends the part onto the wrong region cannot be placed rigidly). Placements
        turned upside down were tried and not kept: that residual does not rank them
        (docs/guide.md, "Partial shapes")."""
        p2p = match_partial(shape_x, shape_y, k=k).p2p_yx
        R, t, _ = rigid_fit(shape_y.mesh.vertices, shape_x.mesh.vertices[p2p])
        return {"as it lies": (np.eye(3), np.zeros(3)), "fitted": (R, t)}

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
        """The map ``y -> x`` of the pair: ``p2p_yx (V_y,)``, ``C_xy`` and the bases it lives in
        (the model's basis of ``k`` columns; with ZoomOut the eigenbases of ``k_final``),
        ``p2p_yx_initial`` (the network's map), ``kind`` (the model's basis kind), ``model``
        (``name``) and ``timings`` (seconds: ``prepare``, ``adapt``, ``network+fmap``, ``p2p``,
        ``refine``).

        Args:
            refine: ``'zoomout'`` (from the network's map, in the eigenbases, from the model's
                ``k`` eigenfunctions to ``k_final``; default ``2k``; both capped at ``V - 1`` of
                the smaller mesh; every point-map step also matches the network's features) or
                None.
            shapes: ``(prepare_shape(mesh_x, n), prepare_shape(mesh_y, n))`` to reuse across
                pairs (their eigenbases are grown in place when the call needs more).
            partial: ``y`` is a part of ``x`` (same units): the partial functional map of
                :func:`~torchfmap.matching.partial.match_partial` of the model's ``k`` (ZoomOut to
                ``k_final``, default ``2k``) with the network's features
                (:meth:`features`, as each shape lies: no facings; the part's coordinate inputs
                in the whole's frame, ``whole=``) as its descriptors. The features of a part
                agree with the whole's only where the network's inputs do: coordinate inputs
                (``--inputs xyz``) do near the part's vertices when the part lies as it lies
                on the whole, WKS (global) does not; a coordinate model tries the part at each
                of its :meth:`placements` (a part saved turned) and keeps one (``placement``).
                The result has ``overlap`` and ``partial_rank`` as ``match``'s.

        Raises:
            ParameterError: inputs that are not meshes, another refinement, ``k_final`` without
                ZoomOut or below ``k``,
                ``shapes`` not of these meshes, or meshes too small for the model's ``k``;
                ``partial`` with test-time adaptation, or with a part larger than the whole.
        """
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
                turned = (
                    sy._replace(
                        inputs=move_xyz(
                            sy.inputs, lambda xyz, a=angle: xyz @ yaw_matrices(xyz.new_tensor([a]))
                        )
                    )
                    if angle
                    else sy
                )
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
