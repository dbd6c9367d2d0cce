"""Inference with a trained network: point maps of dataset items (:func:`predict_p2p`),
unsupervised test-time adaptation (:func:`adapt`), evaluation with the classical metrics
(:func:`evaluate`), ZoomOut refinement in the eigenbases (:func:`refine_p2p`) and matching two
meshes without a dataset (:func:`match_with_network`)."""

from __future__ import annotations

import copy

import numpy as np
import torch

from ..bases.prepared import PreparedShape, prepare_shape
from ..errors import ParameterError
from ..eval import geodesic_errors
from ..fmap.convert import nearest_neighbor, p2p_to_fmap, values_to_p2p
from ..kinds import get_kind
from ..mesh import Mesh
from .checkpoints import load_checkpoint
from .config import TrainConfig, build_solver
from .data import ShapeBatch, ShapeDataset, collate_pairs
from .inputs import K_WKS, shape_arrays, shape_item
from .modules import RegularizedFMSolver
from .networks import check_network, features
from .train import pair_loss

#: Eigenfunctions the ZoomOut refinement of the learned path starts from and grows to
#: (:func:`refine_p2p`'s ``k0`` and ``k_final``; the published recipe's 50 -> 200).
REFINE_K_START = 50
REFINE_K_FINAL = 200


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


def refine_p2p(
    mesh_x: Mesh,
    mesh_y: Mesh,
    p2p_yx: np.ndarray,
    k0: int = REFINE_K_START,
    k_final: int = REFINE_K_FINAL,
    *,
    shapes: tuple[PreparedShape, PreparedShape] | None = None,
) -> np.ndarray:
    """ZoomOut in the Laplacian eigenbases from a point map: ``p2p_yx`` -> ``C_xy (k0, k0)``
    -> ``k_final``; returns the refined ``p2p_yx``. Both sizes are capped for small meshes. It
    is the eigenbasis kind's own refiner (``KINDS['laplacian'].refiner('zoomout')``, that of
    :func:`torchfmap.match`), point maps by the orthogonal rule (nearest neighbours of ``Φ_y``
    in ``Φ_x C_xyᵀ``).

    ``shapes``: the meshes prepared once (``prepare_shape(mesh, n)``, unit-area frames, ``n >=
    k_final`` eigenpairs), to reuse them across pairs and with the network's inputs; prepared
    here when None.

    Raises:
        ParameterError: ``shapes`` that are not of these meshes, or hold fewer than ``k_final``
            eigenpairs.
    """
    k_final = min(k_final, mesh_x.n_vertices - 1, mesh_y.n_vertices - 1)
    k0 = min(k0, k_final)
    if shapes is None:
        # in each mesh's unit-area frame, so meshes at different scales refine alike
        shapes = tuple(prepare_shape(m, k_final) for m in (mesh_x, mesh_y))
    for name, shape, mesh in (("x", shapes[0], mesh_x), ("y", shapes[1], mesh_y)):
        if (
            not isinstance(shape, PreparedShape)
            or shape.mesh.n_vertices != mesh.n_vertices
            or (shape.n_eigen < k_final)
        ):
            raise ParameterError(
                f"shapes[{name}] must be mesh_{name} prepared with >= {k_final} eigenpairs "
                f"({mesh.n_vertices} vertices). Fix: prepare_shape(mesh_{name}, {k_final})."
            )
    bx, by = (s.eigenbasis.truncated(k0) for s in shapes)
    C_xy = p2p_to_fmap(p2p_yx, bx, by, k0, k0)
    refiner = get_kind("laplacian").refiner("zoomout", k_final=k_final, mode="orthogonal")
    return refiner(C_xy, p2p_yx, *shapes, bx, by).p2p_yx


def _prepared(mesh: Mesh, config: TrainConfig, refine: bool) -> tuple[dict, PreparedShape]:
    """``(dataset item, prepared shape)`` of ``mesh``: one Laplacian and one eigendecomposition,
    serving the network's inputs and bases and, with ``refine``, ZoomOut."""
    need = max(config.k, config.k_net, K_WKS, REFINE_K_FINAL if refine else 0)
    shape = prepare_shape(mesh, min(need, mesh.n_vertices - 1))
    arrays = shape_arrays(shape, config.k, config.n_wks, k_net=config.k_net, basis=config.basis)
    item = shape_item(arrays, config.inputs, name=mesh.name or "")
    return item, shape


def _network_p2p(
    net, solver, loss_fn, items, meshes, *, adapt_steps, adapt_lr, refine, mode, device, shapes,
) -> np.ndarray:  # fmt: skip
    """One pair's ``p2p_yx``: adapt (optional), predict, refine (optional)."""
    if adapt_steps:
        net = adapt(net, solver, loss_fn, items[0], items[1], steps=adapt_steps, lr=adapt_lr, device=device)
    p2p = predict_p2p(net, solver, items[0], items[1], mode=mode, device=device)
    return refine_p2p(meshes[0], meshes[1], p2p, shapes=shapes) if refine else p2p


def _refines(refine) -> bool:
    """Whether a learned map is refined: ``refine`` is ``'zoomout'`` or None, as in
    :func:`torchfmap.match` (True / False: the older form)."""
    if refine in (None, False, True, "zoomout"):
        return bool(refine)
    raise ParameterError(
        f"the learned path refines by ZoomOut only, got refine={refine!r}. Fix: 'zoomout' or None."
    )


def _check_inference(adapt_steps: int, mode: str) -> None:
    if isinstance(adapt_steps, bool) or not isinstance(adapt_steps, (int, np.integer)) or adapt_steps < 0:
        raise ParameterError(f"adapt_steps must be an integer >= 0, got {adapt_steps!r}.")
    if mode not in ("fmap", "features"):
        raise ParameterError(f"unknown mode {mode!r}. Fix: 'fmap' or 'features'.")


def match_with_network(
    net,
    config: TrainConfig,
    mesh_x: Mesh,
    mesh_y: Mesh,
    *,
    adapt_steps: int = 0,
    adapt_lr: float = 1e-4,
    refine: str | None = None,
    mode: str = "fmap",
    device="cpu",
    landmarks=None,
) -> np.ndarray:
    """``p2p_yx`` of two meshes with a trained network: no dataset folder, no cache.

    Precomputes both shapes as in training (:func:`~torchfmap.nn.inputs.shape_arrays`),
    optionally adapts the network to the pair (:func:`adapt`), predicts (:func:`predict_p2p`)
    and, with ``refine='zoomout'`` (the name
    :func:`torchfmap.match` takes; True is the older form), refines with ZoomOut
    (:func:`refine_p2p`).

    Raises:
        ParameterError: ``adapt_steps < 0``, an unknown ``mode`` or refinement, or landmarks
            (the learned path takes none: the landmark-seeded second stage is
            :func:`torchfmap.experimental.stages.two_stage_p2p`).
    """
    _check_inference(adapt_steps, mode)
    refine = _refines(refine)
    if landmarks is not None:
        raise ParameterError(
            "a trained network matches without landmarks. Fix: drop them (--landmarks), or seed the "
            "second stage with them: torchfmap.experimental.stages.two_stage_p2p."
        )
    (ix, sx), (iy, sy) = (_prepared(m, config, refine) for m in (mesh_x, mesh_y))
    ix["index"], iy["index"] = 0, 1
    solver, loss_fn = build_solver(config)
    return _network_p2p(
        net,
        solver,
        loss_fn,
        (ix, iy),
        (mesh_x, mesh_y),
        adapt_steps=adapt_steps,
        adapt_lr=adapt_lr,
        refine=refine,
        mode=mode,
        device=device,
        shapes=(sx, sy),
    )


class CheckpointMatcher:
    """Matches pairs of meshes with a trained network, for collections
    (:func:`torchfmap.collection.evaluate_pairs` ``matcher=``; ``torchfmap eval --checkpoint``).

    Calling ``matcher(mesh_x, mesh_y, key_x, key_y)`` returns ``p2p_yx (V_y,)`` as
    :func:`match_with_network` would, but each mesh is precomputed once (and, with ``refine``,
    its ZoomOut eigenbasis computed once) per process, keyed by ``key_*`` (e.g. its path). The
    object pickles as its checkpoint name and settings only, so a process pool or a cluster
    executor can take it: each process loads the network on its first call and keeps its own
    shapes.

    Args:
        checkpoint: a path written by ``torchfmap train`` or a shipped model's name
            (:func:`~torchfmap.nn.shipped.resolve_checkpoint`); read here, so a bad one raises now.
        adapt_steps, adapt_lr, refine, mode: as :func:`match_with_network`.

    Raises:
        CorruptFileError, ParameterError: an unreadable checkpoint or an unknown name (as
            :func:`~torchfmap.nn.checkpoints.load_checkpoint`), ``adapt_steps < 0`` or an
            unknown ``mode``.
    """

    def __init__(
        self,
        checkpoint,
        *,
        adapt_steps: int = 0,
        adapt_lr: float = 1e-4,
        refine: str | None = None,
        mode="fmap",
    ):
        _check_inference(adapt_steps, mode)
        refine = _refines(refine)
        self.checkpoint = checkpoint
        self.adapt_steps, self.adapt_lr, self.refine, self.mode = adapt_steps, adapt_lr, refine, mode
        self._model = self._load()
        self._items: dict = {}
        self._shapes: dict = {}

    def _load(self) -> tuple:
        net, config, _ = load_checkpoint(self.checkpoint)
        solver, loss_fn = build_solver(config)
        return net, config, solver, loss_fn

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.update(_model=None, _items={}, _shapes={})  # loaded again in each process
        return state

    def __call__(self, mesh_x: Mesh, mesh_y: Mesh, key_x, key_y) -> np.ndarray:
        if self._model is None:
            self._model = self._load()
        net, config, solver, loss_fn = self._model
        for key, mesh in ((key_x, mesh_x), (key_y, mesh_y)):
            if key not in self._items:
                self._items[key], self._shapes[key] = _prepared(mesh, config, self.refine)
        return _network_p2p(
            net,
            solver,
            loss_fn,
            (self._items[key_x], self._items[key_y]),
            (mesh_x, mesh_y),
            adapt_steps=self.adapt_steps,
            adapt_lr=self.adapt_lr,
            refine=self.refine,
            mode=self.mode,
            device="cpu",
            shapes=(self._shapes[key_x], self._shapes[key_y]),
        )
