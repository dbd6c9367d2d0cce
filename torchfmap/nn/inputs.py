"""What the learned path needs of one shape, cached on its :class:`~torchfmap.PreparedShape`: network
inputs, all its arrays (:func:`shape_arrays`), dataset items (:func:`shape_item`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ..bases.prepared import PreparedShape, prepare_shape, with_eigenpairs
from ..descriptors import SHOT_GRID, wks
from ..errors import ParameterError
from ..fmap.defaults import DEFAULT_K
from ..kinds import get_kind, learned_kind
from ..matching.partial import shot_descriptors
from ..mesh import Mesh
from .modules import basis_arrays

#: Per-vertex network inputs (``TrainConfig.inputs``): WKS, unit-area coordinates, both (coordinates last,
#: which augmentation moves), or SHOT (local, invariant to rigid motions and scale).
INPUTS = ("wks", "xyz", "wks+xyz", "shot")


def input_channels(inputs: str, n_wks: int) -> int:
    """Channels of one of :data:`INPUTS` with ``n_wks`` WKS channels."""
    return sum({"wks": n_wks, "xyz": 3, "shot": int(np.prod(SHOT_GRID))}[part] for part in inputs.split("+"))


def has_shot(inputs: str | None) -> bool:
    """Whether inputs of one of :data:`INPUTS` include SHOT."""
    return inputs is not None and "shot" in inputs.split("+")


def has_coordinates(inputs: str | None) -> bool:
    """Whether inputs of one of :data:`INPUTS` end with coordinates; None: False."""
    return inputs is not None and inputs.split("+")[-1] == "xyz"


#: Eigenpairs the WKS inputs are computed from (:func:`shape_arrays`'s ``k_wks``).
K_WKS = 100
#: Relative diffusion times of the feature-aware bases on the learned path.
SEED_TIMES = (0.01, 0.03)

_ITEM_FLOATS = ("values", "mass", "lam", "U", "net_values", "net_lam", "net_U", "grad_x", "grad_y")


def coordinates_on(mesh: Mesh, whole: PreparedShape) -> np.ndarray:
    """``(V, 3)`` float64: ``mesh``'s vertices as coordinate inputs in ``whole``'s frame (a part as it
    lies on its whole, in the whole's units: the whole's inputs at the part's points).

    Raises:
        ParameterError: ``mesh`` not a :class:`~torchfmap.Mesh` or ``whole`` not a
            :class:`~torchfmap.PreparedShape`."""
    if not isinstance(mesh, Mesh) or not isinstance(whole, PreparedShape):
        raise ParameterError(
            f"coordinates_on(mesh, whole) takes a Mesh and a PreparedShape, got {type(mesh).__name__} "
            f"and {type(whole).__name__}. Fix: coordinates_on(part, prepare_shape(whole_mesh, n))."
        )
    mass = whole.operators.mass.diagonal()
    centre = (whole.mesh.vertices * mass[:, None]).sum(axis=0) / mass.sum()
    return (mesh.vertices - centre) * whole.scale


def network_inputs(shape: PreparedShape, n_wks: int = 32, k_wks: int = K_WKS) -> dict[str, np.ndarray]:
    """Float64 inputs of one shape, cached on it: ``'wks'`` ``(V, n_wks)`` (WKS of ``k_wks`` eigenpairs,
    capped at ``V - 1``, channels standardised) and ``'xyz'`` ``(V, 3)`` (unit area, centred). Raises
    :class:`ParameterError`: ``n_wks`` or ``k_wks`` below 1."""
    if n_wks < 1 or k_wks < 1:
        raise ParameterError(f"n_wks and k_wks must be >= 1, got {n_wks} and {k_wks}.")
    k_wks = min(k_wks, shape.mesh.n_vertices - 1)

    def compute() -> dict[str, np.ndarray]:
        eig = with_eigenpairs(shape, k_wks).eigenbasis
        feats = wks(eig.eigenvalues[:k_wks], eig.values[:, :k_wks], n_wks)
        feats = (feats - feats.mean(axis=0)) / np.maximum(feats.std(axis=0), 1e-12)
        return {"wks": feats, "xyz": coordinates_on(shape.mesh, shape)}

    return shape.derive(("network_inputs", n_wks, k_wks), compute)


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
    """New float64 arrays of one shape (a :class:`~torchfmap.PreparedShape`, grown in place, or a
    :class:`~torchfmap.Mesh`) in its operators' frame:

    - solver basis (``basis`` kind, ``k`` functions): ``values (V, k)``, ``mass (V,)``, ``lam``, ``U``;
    - network basis (``k_net`` eigenfunctions, 0: none): ``net_values (V, k_net)``, ``net_lam``, ``net_U``;
    - inputs (:func:`network_inputs`): ``wks (V, n_wks)``, ``xyz (V, 3)``; with ``shot``, ``shot (V, 352)``;
    - gradient operator: ``grad_rows, grad_cols, grad_x, grad_y, grad_order_t (E,)``; ``vertices``, ``faces``.

    Raises:
        ParameterError: an unknown or classical-only ``basis``, ``shape`` neither a prepared shape nor a
            mesh, or ``k`` / ``k_net`` not below the vertex count."""
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
    full = with_eigenpairs(shape, k_all).eigenbasis.truncated(k_all)
    exact = dataclasses.replace(
        shape, eigenbasis=full
    )  # the kinds read exactly the k_all pairs the inputs use
    arrays = basis_arrays(get_kind(basis).shape_basis(exact, k, times=SEED_TIMES))
    if k_net:
        net = basis_arrays(full.truncated(k_net))
        arrays.update({f"net_{name}": net[name] for name in ("values", "lam", "U")})
    arrays.update(network_inputs(shape, n_wks, k_wks))
    if shot:
        arrays["shot"] = shot_descriptors(shape)
    arrays.update(shape.gradient())
    arrays["vertices"], arrays["faces"] = shape.mesh.vertices, shape.mesh.faces
    # copies: the arrays may be views of the shape's caches, eigenbasis and mesh
    return {key: np.array(value) for key, value in arrays.items()}


def shape_item(
    arrays: dict[str, np.ndarray], inputs: str = "wks", dtype=torch.float32, name: str = "", index: int = 0
) -> dict:
    """A dataset item (:class:`~torchfmap.nn.data.ShapeDataset`) of :func:`shape_arrays` arrays: floats in
    ``dtype``, ``inputs`` (one of :data:`INPUTS`) as ``'inputs'``, indices int64."""
    item = {k: torch.as_tensor(arrays[k], dtype=dtype) for k in _ITEM_FLOATS if k in arrays}
    parts = [arrays[name] for name in inputs.split("+")]
    item["inputs"] = torch.as_tensor(np.concatenate(parts, axis=1), dtype=dtype)
    item["xyz"] = torch.as_tensor(arrays["xyz"], dtype=dtype)
    for key in ("grad_rows", "grad_cols", "grad_order_t", "vertices", "faces"):
        if key in arrays:
            item[key] = torch.as_tensor(arrays[key])
    item["name"], item["index"] = name, index
    return item
