"""The solve step shared by :func:`torchfmap.match` and the landmark default: descriptors, a kind's pair of
bases and one kind's unrefined map (:func:`solve_pair`)."""

from __future__ import annotations

import time
from typing import Literal, NamedTuple

import numpy as np

from .._util.checks import check_count
from .._util.progress import SILENT, Steps
from ..bases import Basis
from ..bases.prepared import PreparedShape, check_prepared, prepare_shape, with_eigenpairs
from ..descriptors import WKS_ENERGIES, landmark_descriptors, normalize_descriptors, wks
from ..errors import ParameterError
from ..fmap import solve_fmap
from ..fmap.defaults import W_DCOMM, W_LMK, W_PRIOR
from ..kinds import BasisKind, get_kind
from ..kinds.refiners import pair_samplings
from ..mesh import Mesh
from .quality import geodesic_distortion
from .results import MatchResult

P2PMode = Literal["pullback", "orthogonal"]

__all__ = [
    "P2PMode", "SolvedMap", "match_bases", "match_descriptors", "prepare_shapes", "solve_functional_map",
    "solve_pair",
]  # fmt: skip


def match_descriptors(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    landmarks: np.ndarray | None = None,
    *,
    n_descriptors: int = 20,
    k_descriptors: int = 100,
) -> tuple[np.ndarray, np.ndarray]:
    """``(V_x, D)``, ``(V_y, D)`` unit-B-norm descriptors: ``n_descriptors`` WKS columns on ``k_descriptors``
    eigenpairs, then, with ``landmarks`` ``(L, 2)``, :func:`~torchfmap.descriptors.landmark_descriptors`.

    Raises:
        ParameterError: ``n_descriptors < 1`` or shapes prepared without eigenpairs."""
    if n_descriptors < 1:
        raise ParameterError(f"n_descriptors must be >= 1, got {n_descriptors}.")
    out = []
    for s, shape in enumerate((shape_x, shape_y)):
        if shape.eigenbasis is None:
            raise ParameterError("WKS descriptors need eigenpairs. Fix: prepare_shape(mesh, n_eigen > 0).")
        eig = shape.eigenbasis.truncated(min(k_descriptors, shape.eigenbasis.k))
        step = max(1, WKS_ENERGIES // n_descriptors)
        parts = [wks(eig.eigenvalues, eig.values)[:, ::step][:, :n_descriptors]]
        if landmarks is not None:
            parts.append(_landmark_columns(shape, landmarks[:, s]))
        out.append(normalize_descriptors(np.hstack(parts), shape.operators[1]))
    return out[0], out[1]


def _landmark_columns(shape: PreparedShape, landmarks: np.ndarray) -> np.ndarray:
    """``(V, L·T)`` landmark descriptors on a prepared shape, each landmark solved once (cached)."""
    kept = shape.derive("landmark descriptors", dict)
    missing = [int(v) for v in dict.fromkeys(np.asarray(landmarks).tolist()) if int(v) not in kept]
    if missing:
        columns = landmark_descriptors(missing, operators=shape.operators)  # (V, len(missing)·T)
        per = columns.shape[1] // len(missing)
        kept.update({v: columns[:, j * per : (j + 1) * per] for j, v in enumerate(missing)})
    return np.hstack([kept[int(v)] for v in np.asarray(landmarks).tolist()])


def match_bases(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    kind: str | BasisKind,
    k: int,
    landmarks: np.ndarray | None = None,
    times=None,
) -> tuple[Basis, Basis, np.ndarray | None]:
    """The pair of B-orthonormal ``k``-column bases of ``kind`` and their seed pairs ``(S, 2)`` (None when
    columns do not correspond; also set as ``Basis.pair_landmarks``).

    Raises:
        ParameterError: an unknown kind, a kind needing landmarks without them, or ``k`` out of range."""
    bx, by, seeds = get_kind(kind).pair_bases(shape_x, shape_y, k, landmarks, times)
    if seeds is not None:
        bx.pair_landmarks = by.pair_landmarks = np.asarray(seeds, dtype=np.int64).reshape(-1, 2)
    return bx, by, seeds


class SolvedMap(NamedTuple):
    """A kind's functional map ``C_xy (K_y, K_x)``, its bases, seed pairs ``(S, 2)`` or None, timings."""

    C_xy: np.ndarray
    basis_x: Basis
    basis_y: Basis
    seeds: np.ndarray | None
    timings: dict[str, float]


def solve_functional_map(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    kind: BasisKind,
    k: int,
    *,
    landmarks: np.ndarray | None = None,
    bases: tuple[Basis, Basis] | None = None,
    seeds: np.ndarray | None = None,
    times=None,
    n_descriptors: int = 20,
    k_descriptors: int = 100,
    w_lap: float | None = None,
    w_orient: float | None = None,
    w_dcomm: float = W_DCOMM,
    w_lmk: float = W_LMK,
    w_prior: float | None = None,
    n_eigen: int = 0,
    steps: Steps = SILENT,
) -> SolvedMap:
    """:func:`solve_pair` up to the functional map; arguments as there.

    Raises:
        ParameterError: as :func:`solve_pair`."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    n_max = min(shape_x.mesh.n_vertices, shape_y.mesh.n_vertices) - 1
    k = check_count(k, 1, n_max, "k (basis size)")
    k_descriptors = min(check_count(k_descriptors, 2, 10**9, "k_descriptors"), n_max)  # small meshes
    prior = kind.needs_landmarks and (bases is None or seeds is not None)  # else columns need not correspond
    w_prior = (W_PRIOR if w_prior is None else w_prior) if prior else 0.0
    need_desc = kind.uses_descriptors(w_prior)
    n_eigen = max(kind.n_eigen(k), n_eigen, k_descriptors if need_desc else 0)
    steps(f"{kind.name}: eigenpairs")
    for shape in (shape_x, shape_y):
        with_eigenpairs(shape, n_eigen)
    timings["operators+eigen"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    steps(f"{kind.name}: basis")
    if bases is None:
        bx, by, seeds = match_bases(shape_x, shape_y, kind, k, landmarks, times)
    else:
        bx, by = bases
    timings["basis"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    steps(f"{kind.name}: descriptors")
    if need_desc:
        desc_x, desc_y = match_descriptors(
            shape_x, shape_y, landmarks, n_descriptors=n_descriptors, k_descriptors=k_descriptors
        )
    timings["descriptors"] = time.perf_counter() - t0
    t0 = time.perf_counter()

    def solve_block(block_x: Basis, block_y: Basis, prior) -> np.ndarray:
        return solve_fmap(
            block_x, block_y, desc_x, desc_y, w_lap=kind.w_lap if w_lap is None else w_lap,
            w_orient=kind.w_orient if w_orient is None else w_orient, w_dcomm=w_dcomm,
            meshes=(shape_x.mesh, shape_y.mesh), landmarks=landmarks,
            w_lmk=w_lmk if landmarks is not None else 0.0, prior=prior,
            w_prior=w_prior if prior is not None else 0.0,
        )  # fmt: skip

    steps(f"{kind.name}: functional map")
    C = kind.solve_map(bx, by, solve_block, w_prior)
    timings["fmap"] = time.perf_counter() - t0
    return SolvedMap(C, bx, by, seeds, timings)


def solve_pair(
    shape_x: PreparedShape,
    shape_y: PreparedShape,
    kind: str | BasisKind,
    k: int,
    *,
    landmarks: np.ndarray | None = None,
    p2p_mode: P2PMode | None = None,
    **settings,
) -> MatchResult:
    """One kind's unrefined :class:`MatchResult` on prepared shapes (``distortion`` set with landmarks):
    :func:`match_bases` (or given ``bases`` with their ``seeds``) -> :func:`match_descriptors` -> the kind's
    ``solve_map`` and ``to_p2p``. ``landmarks``: checked ``(L, 2)`` pairs or None; ``settings``: those of
    :func:`solve_functional_map` (``n_eigen``: eigenpairs to hold for ZoomOut; the rest as :func:`match`).

    Raises:
        ParameterError: as the kind's bases, or ``k`` / ``k_descriptors`` out of range."""
    kind = get_kind(kind)
    C, bx, by, seeds, timings = solve_functional_map(
        shape_x, shape_y, kind, k, landmarks=landmarks, **settings
    )
    t0 = time.perf_counter()
    settings.get("steps", SILENT)(f"{kind.name}: point map")
    p2p = kind.to_p2p(C, bx, by, p2p_mode or kind.p2p_mode, samplings=pair_samplings(shape_x, shape_y))
    timings["fmap+p2p"] = timings.pop("fmap") + time.perf_counter() - t0
    distortion = None
    if landmarks is not None:
        settings.get("steps", SILENT)(f"{kind.name}: distortion")
        distortion = geodesic_distortion(shape_x, shape_y, p2p)
    return MatchResult(p2p, C, bx, by, p2p, timings, seeds, kind.name, distortion)


def prepare_shapes(mesh_x: Mesh, mesh_y: Mesh, shapes, n_eigen: int) -> tuple[PreparedShape, PreparedShape]:
    """``shapes`` checked against the meshes (eigenpairs grown to ``n_eigen``), else both prepared.

    Raises:
        ParameterError: ``shapes`` that are not the meshes' prepared shapes."""
    if shapes is None:
        return prepare_shape(mesh_x, n_eigen), prepare_shape(mesh_y, n_eigen)
    return tuple(with_eigenpairs(s, n_eigen) for s in check_prepared(shapes, (mesh_x, mesh_y)))
