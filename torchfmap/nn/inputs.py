"""What the learned path needs of one shape, read off its :class:`~torchfmap.PreparedShape`.

One per-shape precompute serves both paths: :func:`~torchfmap.prepare_shape` builds the
operators and eigenpairs once (unit-area frame, float64), and everything the network needs is
derived from that object and cached on it (:meth:`~torchfmap.PreparedShape.derive`), so
training, inference, ZoomOut refinement and evaluation of a shape share one Laplacian and one
eigendecomposition:

- :func:`network_inputs`: the input features (standardised WKS, centred unit-area coordinates);
- :func:`coordinates_on`: a part's coordinate inputs in the frame of the whole it lies on;
- :meth:`~torchfmap.PreparedShape.gradient`: the intrinsic gradient operator;
- :func:`shape_arrays`: all of it plus the solver and network bases as numpy arrays (what the
  on-disk cache of :class:`~torchfmap.nn.data.ShapeDataset` stores);
- :func:`shape_item`: those arrays as the tensors of a dataset item (the only cast to the
  network's dtype).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ..bases.basis import Basis
from ..bases.prepared import PreparedShape, prepare_shape, with_eigenpairs
from ..descriptors import SHOT_GRID, wks
from ..errors import ParameterError
from ..fmap.defaults import DEFAULT_K
from ..kinds import get_kind, learned_kind
from ..matching.partial import shot_descriptors
from ..mesh import Mesh
from .modules import basis_arrays

#: Per-vertex network inputs (``TrainConfig.inputs``): WKS channels, unit-area coordinates,
#: both (the WKS channels first, the three coordinates last, which augmentation moves), or SHOT
#: (local and invariant to rigid motions and scale: a part's agree with its whole's away from
#: the cut, however either is turned).
INPUTS = ("wks", "xyz", "wks+xyz", "shot")


def input_channels(inputs: str, n_wks: int) -> int:
    """Channels of one of :data:`INPUTS` with ``n_wks`` WKS channels."""
    return sum({"wks": n_wks, "xyz": 3, "shot": int(np.prod(SHOT_GRID))}[part] for part in inputs.split("+"))


def has_shot(inputs: str | None) -> bool:
    """Whether inputs of one of :data:`INPUTS` include SHOT (computed only for them: it costs a
    neighbourhood search per vertex)."""
    return inputs is not None and "shot" in inputs.split("+")


def has_coordinates(inputs: str | None) -> bool:
    """Whether inputs of one of :data:`INPUTS` end with coordinates (what augmentation and the
    facing search move); None (unknown inputs): False."""
    return inputs is not None and inputs.split("+")[-1] == "xyz"


#: Eigenpairs the WKS inputs are computed from (:func:`shape_arrays`'s ``k_wks``).
K_WKS = 100
#: Relative diffusion times of the feature-aware bases on the learned path.
SEED_TIMES = (0.01, 0.03)

_ITEM_FLOATS = ("values", "mass", "lam", "U", "net_values", "net_lam", "net_U", "grad_x", "grad_y")


def coordinates_on(
    mesh: Mesh, whole: PreparedShape, motion: tuple[np.ndarray, np.ndarray] | None = None
) -> np.ndarray:
    """``(V, 3)`` float64: ``mesh``'s vertices as coordinate inputs in ``whole``'s input frame
    (its unit-area frame, centred at its area-weighted centroid: :func:`network_inputs`'s
    ``'xyz'`` of ``whole``). For a part lying where it lies on the whole, in the whole's units,
    these are the whole's inputs at the part's points; the part's own frame (its own area and
    centroid) would scale them by ``1 / sqrt(area ratio)`` and shift them. ``motion``: ``(R
    (3, 3), t (3,))``, the part placed at ``vertices @ R.T + t`` first (e.g. by
    :func:`~torchfmap.mesh.rigid_fit`).

    Raises:
        ParameterError: ``mesh`` not a :class:`~torchfmap.Mesh`, ``whole`` not a
            :class:`~torchfmap.PreparedShape`, or ``motion`` not a ``(3, 3)`` and a ``(3,)`` array.
    """
    if not isinstance(mesh, Mesh) or not isinstance(whole, PreparedShape):
        raise ParameterError(
            f"coordinates_on(mesh, whole) takes a Mesh and a PreparedShape, got {type(mesh).__name__} "
            f"and {type(whole).__name__}. Fix: coordinates_on(part, prepare_shape(whole_mesh, n))."
        )
    vertices = mesh.vertices
    if motion is not None:
        R, t = (np.asarray(a, dtype=np.float64) for a in motion)
        if R.shape != (3, 3) or t.shape != (3,):
            raise ParameterError(f"motion must be (R (3, 3), t (3,)), got shapes {R.shape} and {t.shape}.")
        vertices = vertices @ R.T + t
    mass = whole.operators.mass.diagonal()
    centre = (whole.mesh.vertices * mass[:, None]).sum(axis=0) / mass.sum()
    return (vertices - centre) * whole.scale


def network_inputs(shape: PreparedShape, n_wks: int = 32, k_wks: int = K_WKS) -> dict[str, np.ndarray]:
    """The network's input features of one shape, float64, computed once per shape and
    ``(n_wks, k_wks)`` (cached on ``shape``): ``'wks'`` ``(V, n_wks)`` (the wave-kernel signature
    of the first ``k_wks`` eigenpairs, each channel standardised over the vertices) and ``'xyz'``
    ``(V, 3)`` (unit-area coordinates, centred at the area-weighted centroid). The eigenbasis is
    grown in place when it holds fewer than ``k_wks`` pairs (capped at ``V - 1``).

    Raises:
        ParameterError: ``n_wks`` or ``k_wks`` below 1.
    """
    if n_wks < 1 or k_wks < 1:
        raise ParameterError(f"n_wks and k_wks must be >= 1, got {n_wks} and {k_wks}.")
    k_wks = min(k_wks, shape.mesh.n_vertices - 1)

    def compute() -> dict[str, np.ndarray]:
        eig = with_eigenpairs(shape, k_wks).eigenbasis
        feats = wks(eig.eigenvalues[:k_wks], eig.values[:, :k_wks], n_wks)
        feats = (feats - feats.mean(axis=0)) / np.maximum(feats.std(axis=0), 1e-12)
        return {"wks": feats, "xyz": coordinates_on(shape.mesh, shape)}

    return shape.derive(("network_inputs", n_wks, k_wks), compute)


def _solver_basis(shape: PreparedShape, kind: str, k: int) -> Basis:
    """The functional-map basis of ``k`` functions of a registered kind
    (:data:`torchfmap.bases.KINDS`), built on one prepared shape by the kind's ``shape_basis``
    (farthest-point seeds for seeded kinds, diffusion at :data:`SEED_TIMES`), B-orthonormal."""
    return get_kind(kind).shape_basis(shape, k, times=SEED_TIMES)


def shape_arrays(
    shape: PreparedShape | Mesh,
    k: int = DEFAULT_K,
    n_wks: int = 32,
    k_wks: int = K_WKS,
    *,
    k_net: int = 0,
    basis: str = "laplacian",
    shot: bool = False,
) -> dict[str, np.ndarray]:
    """Arrays for training and inference of one shape, float64, in the frame of its operators
    (the unit-area frame, unless the shape was prepared with the caller's operators).

    ``shape``: a :class:`~torchfmap.PreparedShape` (``prepare_shape(mesh, n)``, its eigenbasis
    grown in place to ``max(k, k_wks, k_net)`` if it holds fewer, so that a caller who also
    refines with ZoomOut computes one Laplacian and one eigendecomposition per shape), or a
    :class:`~torchfmap.Mesh`, prepared here.

    - solver basis (``basis`` kind, ``k`` functions): ``values (V, k)``, ``mass (V,)``, ``lam``, ``U``;
    - network basis (``k_net`` eigenfunctions, 0: none): ``net_values (V, k_net)``, ``net_lam``, ``net_U``;
    - inputs (:func:`network_inputs`): ``wks (V, n_wks)``, ``xyz (V, 3)``; with ``shot``,
      ``shot (V, 352)`` (:func:`~torchfmap.matching.partial.shot_descriptors` at the shape's own
      radius);
    - gradient operator (:meth:`~torchfmap.PreparedShape.gradient`): ``grad_rows, grad_cols,
      grad_x, grad_y, grad_order_t (E,)``;
    - the original ``vertices``, ``faces``.

    The arrays are new (copies, not views of ``shape``'s caches, eigenbasis or mesh), so a
    caller may change them in place.
    ``k_wks`` is capped at ``V - 1`` on small meshes.

    Raises:
        ParameterError: an unknown or classical-only ``basis``, ``shape`` neither a prepared
            shape nor a mesh, or ``k`` / ``k_net`` not below the vertex count.
    """
    learned_kind(basis)  # refuses an unknown or classical-only kind before any work
    if not isinstance(shape, (Mesh, PreparedShape)):
        raise ParameterError(
            f"shape must be a PreparedShape or a Mesh, got {type(shape).__name__}. "
            "Fix: shape_arrays(prepare_shape(mesh, n), ...) or shape_arrays(mesh, ...)."
        )
    n_max = (shape if isinstance(shape, Mesh) else shape.mesh).n_vertices - 1
    k_wks = min(k_wks, n_max)  # the WKS takes what a small mesh has
    if max(k, k_net) > n_max:
        raise ParameterError(
            f"k={k} and k_net={k_net} eigenfunctions need a mesh of more than {max(k, k_net)} vertices, "
            f"this one has {n_max + 1}. Fix: smaller k / k_net, or a finer mesh."
        )
    k_all = max(k, k_wks, k_net)
    if isinstance(shape, Mesh):
        shape = prepare_shape(shape, k_all)
    mesh = shape.mesh
    full = with_eigenpairs(shape, k_all).eigenbasis.truncated(k_all)
    # the kinds read the shape's eigenbasis: give them exactly the k_all pairs the inputs use
    arrays = basis_arrays(_solver_basis(dataclasses.replace(shape, eigenbasis=full), basis, k))
    if k_net:
        net = basis_arrays(full.truncated(k_net))
        arrays.update({f"net_{name}": net[name] for name in ("values", "lam", "U")})
    arrays.update(network_inputs(shape, n_wks, k_wks))
    if shot:
        arrays["shot"] = shot_descriptors(shape)
    arrays.update(shape.gradient())
    arrays["vertices"] = mesh.vertices
    arrays["faces"] = mesh.faces
    # copies, all of them: the arrays are the caller's, while the shape's caches, eigenbasis and
    # mesh (which basis values, inputs and gradient may be views of) stay as computed
    return {key: np.array(value) for key, value in arrays.items()}


def shape_item(
    arrays: dict[str, np.ndarray], inputs: str = "wks", dtype=torch.float32, name: str = "", index: int = 0
) -> dict:
    """A dataset item (see :class:`~torchfmap.nn.data.ShapeDataset`) from :func:`shape_arrays`
    arrays: floats cast to ``dtype``, ``inputs`` (one of :data:`INPUTS`, ``'wks+xyz'``: the WKS
    channels then the three coordinates) as the item's ``'inputs'``, index arrays int64."""
    item = {k: torch.as_tensor(arrays[k], dtype=dtype) for k in _ITEM_FLOATS if k in arrays}
    parts = [arrays[name] for name in inputs.split("+")]
    item["inputs"] = torch.as_tensor(np.concatenate(parts, axis=1), dtype=dtype)
    item["xyz"] = torch.as_tensor(arrays["xyz"], dtype=dtype)
    for key in ("grad_rows", "grad_cols", "grad_order_t", "vertices", "faces"):
        if key in arrays:
            item[key] = torch.as_tensor(arrays[key])
    item["name"], item["index"] = name, index
    return item
