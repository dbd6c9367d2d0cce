"""Inference with a trained network: matching two meshes (:class:`LearnedMatcher`, called like
:func:`torchfmap.match` and returning its :class:`~torchfmap.results.MatchResult`), point maps
of dataset items (:func:`predict_p2p`), unsupervised test-time adaptation (:func:`adapt`) and
evaluation of a dataset's pairs with the classical metrics (:func:`evaluate`)."""

from __future__ import annotations

import copy
import os
import time

import numpy as np
import torch

from ..bases.basis import Basis
from ..bases.prepared import PreparedShape, check_prepared, prepare_shape, with_eigenpairs
from ..errors import ParameterError
from ..eval import geodesic_errors
from ..fmap.convert import NN_BLOCK_BYTES, nearest_neighbor, p2p_to_fmap, values_to_p2p
from ..fmap.refine import Refined
from ..kinds import get_kind
from ..match_checks import check_meshes, check_unused, warn_if_partial
from ..mesh import Mesh
from ..results import MatchResult
from .augment import move_xyz, yaw_matrices
from .checkpoints import load_checkpoint
from .config import TrainConfig, build_solver
from .data import ShapeBatch, ShapeDataset, collate_pairs
from .devices import resolve_device
from .inputs import K_WKS, SEED_TIMES, has_coordinates, shape_arrays, shape_item
from .modules import RegularizedFMSolver
from .networks import check_network, features
from .train import pair_loss

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


def _pair(x: dict, y: dict, device) -> tuple[ShapeBatch, ShapeBatch]:
    """Both items as batches of one, collated once."""
    batch = collate_pairs([(x, y)])
    return batch["x"].to(device), batch["y"].to(device)


def _solve_xy(solver, fx, fy, bx, by) -> torch.Tensor:
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
    (rows of ``Φ_y C_xy`` among those of ``Φ_x``). ``mode='features'``: nearest neighbours in
    the (normalised) feature space.
    """
    check_network(net)
    net.eval()
    sx, sy = _pair(x, y, device)
    fx, fy = features(net, sx), features(net, sy)
    if mode == "features":
        a = torch.nn.functional.normalize(fy[0], dim=-1).double().cpu().numpy()
        b = torch.nn.functional.normalize(fx[0], dim=-1).double().cpu().numpy()
        return nearest_neighbor(a, b, precision="single")
    if mode != "fmap":
        raise ParameterError(f"unknown mode {mode!r}. Fix: 'fmap' or 'features'.")
    if p2p_mode not in ("orthogonal", "pullback"):
        raise ParameterError(f"unknown p2p_mode {p2p_mode!r}. Fix: 'orthogonal' or 'pullback'.")
    C = _solve_xy(solver, fx, fy, sx.basis, sy.basis)[0].double().cpu().numpy()
    return values_to_p2p(C, x["values"].double().numpy(), y["values"].double().numpy(), mode=p2p_mode)


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
    net, shapes: ShapeDataset, pairs, gts, solver=None, *, mode: str = "fmap", max_points=500, device="cpu"
) -> float:
    """Mean normalised geodesic error over ``pairs`` (index pairs) with ground truths ``gts``
    (``solver=None``: the recipe's, :func:`~torchfmap.nn.build_solver` of a default
    :class:`~torchfmap.nn.TrainConfig`, as :func:`~torchfmap.nn.train` trains with)."""
    solver = solver if solver is not None else build_solver(TrainConfig())[0]
    errors = []
    for (a, b), gt in zip(pairs, gts, strict=True):
        x, y = shapes[a], shapes[b]
        p2p = predict_p2p(net, solver, x, y, mode=mode, device=device)
        mesh_x = Mesh(x["vertices"].numpy(), x["faces"].numpy(), validate=False)
        errors.append(geodesic_errors(mesh_x, p2p, gt, max_points=max_points).mean())
    return float(np.mean(errors))


def _nearest_rows(
    query: torch.Tensor, reference: torch.Tensor, *, block_bytes: int = NN_BLOCK_BYTES
) -> torch.Tensor:
    """Index ``(M,)`` (int64) of the nearest row of ``reference (N, D)`` for each row of
    ``query (M, D)``, on their device and in their dtype: :func:`~torchfmap.fmap.nearest_neighbor`'s
    brute force (``|r|² - 2 q·r``, ties to the lowest index) in blocks of at most ``block_bytes``
    of distances, so memory is bounded whatever ``M`` and ``N``.

    Raises:
        ParameterError: not ``(M, D)`` and ``(N, D)`` tensors of one dtype and device.
    """
    if (
        query.dim() != 2 or reference.dim() != 2 or query.shape[1] != reference.shape[1]
        or query.dtype != reference.dtype or query.device != reference.device
    ):  # fmt: skip
        raise ParameterError(
            f"query {tuple(query.shape)} ({query.dtype}, {query.device}) and reference "
            f"{tuple(reference.shape)} ({reference.dtype}, {reference.device}) must be (M, D) and "
            "(N, D) of one dtype on one device."
        )
    squared = (reference * reference).sum(dim=1)
    block = max(1, int(block_bytes // (query.element_size() * max(1, len(reference)))))
    out = torch.empty(len(query), dtype=torch.int64, device=query.device)
    for start in range(0, len(query), block):
        q = query[start : start + block]
        out[start : start + len(q)] = torch.addmm(squared[None, :], q, reference.T, alpha=-2.0).argmin(dim=1)
    return out


def _zoomout_sizes(k: int, k_final: int | None, n_vertices: tuple[int, int]) -> tuple[int, int]:
    """``(k0, k_final)`` of a learned map's ZoomOut: from the model's ``k`` to ``k_final``
    (None: ``2k``), both capped at ``V - 1`` of the smaller mesh.

    Raises:
        ParameterError: ``k_final < k``.
    """
    if k_final is not None and k_final < k:
        raise ParameterError(
            f"k_final={k_final} is below the model's k={k}: ZoomOut grows. Fix: k_final >= {k}."
        )
    cap = min(n_vertices) - 1
    return min(k, cap), min(2 * k if k_final is None else k_final, cap)


def _zoomout(p2p_yx: np.ndarray, shapes: tuple[PreparedShape, ...], k0: int, k_final: int) -> Refined:
    """ZoomOut of ``p2p_yx`` in the shapes' eigenbases, from ``(k0, k0)`` to ``k_final``: the
    eigenbasis kind's refinement, as :func:`torchfmap.match` refines (the one call site of the
    learned path)."""
    bx, by = (s.eigenbasis.truncated(k0) for s in shapes)
    C_xy = p2p_to_fmap(p2p_yx, bx, by)
    refiner = get_kind("laplacian").refiner("zoomout", k_final=k_final, mode="orthogonal")
    return refiner(C_xy, p2p_yx, *shapes, bx, by)


class LearnedMatcher:
    """Matches meshes with a trained network, called like :func:`torchfmap.match`.

    ``matcher(mesh_x, mesh_y)`` returns the :class:`~torchfmap.results.MatchResult` of the pair:
    each mesh is prepared once (:func:`~torchfmap.prepare_shape`: one Laplacian and one
    eigendecomposition, float64 on the CPU, serving the network's inputs
    (:func:`~torchfmap.nn.inputs.shape_arrays`), its basis and ZoomOut); the network (adapted to
    the pair first when ``adapt_steps > 0``, :func:`adapt`) and the solver run on ``device``,
    and so does the point map: nearest neighbours of the rows of ``Φ_y`` among those of
    ``Φ_x C_xyᵀ`` (:func:`_nearest_rows`; the orthogonal rule of
    :func:`~torchfmap.fmap.fmap_to_p2p`), in float64 from the shapes' float64 basis values.

    Build it with :meth:`from_checkpoint` (a path or a shipped model's name), or from a network
    and its recipe. It keeps nothing between calls: shapes are reused only when the caller
    passes them (``shapes=``, as :func:`torchfmap.collection.evaluate_pairs` does). It pickles
    (for a process pool or a cluster executor): one built from a checkpoint as the checkpoint's
    name and its settings, the network loaded again where it is unpickled.

    Args:
        net: a :class:`~torchfmap.nn.networks.FeatureNetwork` (moved to ``device``).
        config: its :class:`~torchfmap.nn.TrainConfig` (basis kind and size ``k``, inputs,
            solver weights).
        name: what the result's ``model`` names.
        device: ``'auto'`` / ``'cpu'`` / ``'cuda'`` / a :class:`torch.device`
            (:func:`~torchfmap.nn.devices.resolve_device`).
        adapt_steps, adapt_lr: unsupervised test-time adaptation per pair (0: none).

    Raises:
        ParameterError: ``adapt_steps`` not an integer >= 0, an unknown or absent device, or a
            network that does not follow the protocol.
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
    ) -> None:
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
    ) -> LearnedMatcher:
        """The matcher of a checkpoint written by ``torchfmap train`` or of a shipped model's
        name (:func:`~torchfmap.nn.shipped.resolve_checkpoint`), read now (its best weights).

        Raises:
            CorruptFileError, ParameterError: an unreadable checkpoint or an unknown name (as
                :func:`~torchfmap.nn.checkpoints.load_checkpoint`), or as the constructor.
        """
        net, config, _ = load_checkpoint(name_or_path)
        settings = dict(device=device, adapt_steps=adapt_steps, adapt_lr=adapt_lr)
        matcher = cls(net, config, name=os.fspath(name_or_path), **settings)
        matcher.checkpoint = name_or_path
        return matcher

    def __getstate__(self) -> dict:
        settings = {"device": self.device_setting, "adapt_steps": self.adapt_steps, "adapt_lr": self.adapt_lr}
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
            f"device={str(self.device)!r}, adapt_steps={self.adapt_steps})"
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

    def _eigenpairs(self, n_vertices: int, k_final: int = 0) -> int:
        """Eigenpairs one preparation of a mesh of ``n_vertices`` needs: the solver's basis, the
        network's, the WKS inputs' and ZoomOut's ``k_final``, at most ``n_vertices - 1``."""
        cfg = self.config
        return min(max(cfg.k, cfg.k_net, K_WKS, k_final), n_vertices - 1)

    def _items(self, shape: PreparedShape, index: int) -> tuple[dict, Basis]:
        """``(dataset item, solver basis)`` of one prepared shape: the network's arrays
        (:func:`~torchfmap.nn.inputs.shape_arrays`, in the network's dtype) and the float64
        basis the map is solved in (the same kind's ``shape_basis`` shape_arrays reads)."""
        cfg = self.config
        arrays = shape_arrays(shape, cfg.k, cfg.n_wks, k_net=cfg.k_net, basis=cfg.basis)
        dtype = next(self.net.parameters()).dtype
        item = shape_item(arrays, cfg.inputs, dtype=dtype, name=shape.mesh.name or "", index=index)
        return item, get_kind(cfg.basis).shape_basis(shape, cfg.k, times=SEED_TIMES)

    def features(self, mesh: Mesh, *, shape: PreparedShape | None = None) -> np.ndarray:
        """``(V, D)`` float64: the network's per-vertex features of ``mesh`` as it lies (no
        adaptation, no facings), e.g. as :func:`~torchfmap.partial.match_partial`'s
        ``descriptors`` or for retrieval.

        Args:
            shape: ``prepare_shape(mesh, n)`` to reuse (its eigenbasis is grown in place when
                the network needs more).

        Raises:
            ParameterError: ``mesh`` is not a mesh, ``shape`` not one of it, or the mesh is too
                small for the model's ``k``.
        """
        check_meshes(mesh, mesh)
        need = self._eigenpairs(mesh.n_vertices)
        if shape is None:
            shape = prepare_shape(mesh, need)
        elif not isinstance(shape, PreparedShape) or shape.mesh is not mesh:
            raise ParameterError("shape must be prepare_shape(mesh, n) of this mesh.")
        else:
            shape = with_eigenpairs(shape, need)
        item, _ = self._items(shape, 0)
        with torch.no_grad():
            batch, _ = _pair(item, item, self.device)
            return features(self.net, batch)[0].to(torch.float64).cpu().numpy()

    def __call__(
        self,
        mesh_x: Mesh,
        mesh_y: Mesh,
        *,
        refine: str | None = None,
        k_final: int | None = None,
        shapes: tuple[PreparedShape, PreparedShape] | None = None,
    ) -> MatchResult:
        """The map ``y -> x`` of the pair: ``p2p_yx (V_y,)``, ``C_xy`` and the bases it lives in
        (the model's basis of ``k`` columns; with ZoomOut the eigenbases of ``k_final``),
        ``p2p_yx_initial`` (the network's map), ``kind`` (the model's basis kind), ``model``
        (``name``) and ``timings`` (seconds: ``prepare``, ``adapt``, ``network+fmap``, ``p2p``,
        ``refine``).

        Args:
            refine: ``'zoomout'`` (from the network's map, in the eigenbases, from the model's
                ``k`` eigenfunctions to ``k_final``; default ``2k``; both capped at ``V - 1`` of
                the smaller mesh) or None.
            shapes: ``(prepare_shape(mesh_x, n), prepare_shape(mesh_y, n))`` to reuse across
                pairs (their eigenbases are grown in place when the call needs more).

        Raises:
            ParameterError: inputs that are not meshes, another refinement, ``k_final`` without
                ZoomOut or below ``k``,
                ``shapes`` not of these meshes, or meshes too small for the model's ``k``.
        """
        check_meshes(mesh_x, mesh_y)
        warn_if_partial(mesh_x, mesh_y)
        if refine not in (None, "zoomout"):
            raise ParameterError(
                f"the learned path refines by ZoomOut only, got refine={refine!r}. Fix: 'zoomout' or None."
            )
        check_unused(get_kind("laplacian"), refine, k_final, None)
        cfg = self.config
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        sizes = (mesh_x.n_vertices, mesh_y.n_vertices)
        k0, k_final = _zoomout_sizes(cfg.k, k_final, sizes) if refine else (cfg.k, None)
        need = self._eigenpairs(min(sizes), k_final or 0)  # one eigendecomposition
        if shapes is None:
            shapes = (prepare_shape(mesh_x, need), prepare_shape(mesh_y, need))
        else:
            shapes = tuple(with_eigenpairs(s, need) for s in check_prepared(shapes, (mesh_x, mesh_y)))
        (ix, bx), (iy, by) = (self._items(s, i) for i, s in enumerate(shapes))
        timings["prepare"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        net = self.net
        if self.adapt_steps:
            net = adapt(net, self.solver, self.loss_fn, ix, iy, steps=self.adapt_steps, lr=self.adapt_lr,
                        device=self.device)  # fmt: skip
        timings["adapt"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        with torch.no_grad():
            sx, sy = _pair(ix, iy, self.device)
            solver = self.solver.to(self.device)
            fx = features(net, sx)
            C, least = None, float("inf")
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
                C_a = _solve_xy(solver, fx, features(net, turned), sx.basis, sy.basis)[0]
                defect = laplacian_defect(C_a, sx.basis, sy.basis)
                if C is None or defect < least:
                    C, least = C_a, defect
        timings["network+fmap"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        C = C.to(torch.float64)
        phi_x, phi_y = (torch.as_tensor(b.values, dtype=torch.float64, device=self.device) for b in (bx, by))
        p2p = _nearest_rows(phi_y, phi_x @ C.T).cpu().numpy()
        C_xy = C.cpu().numpy()
        timings["p2p"] = time.perf_counter() - t0
        result = MatchResult(p2p, C_xy, bx, by, p2p, timings, kind=cfg.basis, model=self.name)
        if refine is None:
            return result
        t0 = time.perf_counter()
        refined = _zoomout(p2p, shapes, k0, k_final)
        timings["refine"] = time.perf_counter() - t0
        return MatchResult(
            refined.p2p_yx, refined.C_xy, refined.basis_x, refined.basis_y, p2p, timings, kind=cfg.basis,
            refined=True, model=self.name,
        )  # fmt: skip
