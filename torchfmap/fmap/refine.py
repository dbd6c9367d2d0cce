"""Refinement of functional maps: ICP (Ovsjanikov et al. 2012) and ZoomOut (Melzi et al. 2019), by
eigenbasis prefixes (:func:`zoomout`) or over sequences of bases with growing spans
(:func:`zoomout_sequence`); the kinds' refiners call these with bases and plain settings."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, NamedTuple, Protocol

import numpy as np
from tqdm import tqdm

from ..bases.basis import Basis
from ..errors import ParameterError
from .convert import check_p2p, embedding_pair, fmap_to_p2p, p2p_to_fmap
from .defaults import zoomout_step
from .nearest import SurfaceSampling, local_nearest, nearest_neighbor, search_p2p

Mode = Literal["pullback", "orthogonal"]


def icp_refine(
    C_xy: np.ndarray,
    basis_x: Basis,
    basis_y: Basis,
    n_iter: int = 10,
    tol: float = 1e-10,
    *,
    mode: Mode = "orthogonal",
    samplings: tuple[SurfaceSampling, SurfaceSampling] | None = None,
):
    """ICP refinement of a square ``C_xy``; returns ``(C_xy, p2p_yx)``. ``mode``: the point-map
    conversion (:func:`~torchfmap.fmap.fmap_to_p2p`; ``'pullback'`` works in any basis);
    ``samplings``: both shapes' surface samplings, every point map searched locally."""
    C = np.asarray(C_xy, dtype=np.float64)
    if C.shape[0] != C.shape[1]:
        raise ParameterError(f"ICP needs a square map, got {C.shape}. Fix: use the same K on both shapes.")
    k = C.shape[0]
    p2p = fmap_to_p2p(C, basis_x, basis_y, mode=mode, samplings=samplings)
    for _ in range(n_iter):
        target = p2p_to_fmap(p2p, basis_x, basis_y, k, k)
        u, _, vt = np.linalg.svd(target)
        new = u @ vt
        p2p = fmap_to_p2p(new, basis_x, basis_y, mode=mode, samplings=samplings)
        change = np.linalg.norm(new - C) / max(np.linalg.norm(C), 1e-300)
        C = new
        if change < tol:
            break
    return C, p2p


def _check_samples(subsample, basis_x: Basis, basis_y: Basis) -> Samples | None:
    """``subsample`` (a pair of vertex arrays, or :class:`Samples`) as :class:`Samples`, checked."""
    if subsample is None:
        return None
    if isinstance(subsample, Samples):
        sx, sy = subsample.x, subsample.y
    else:
        try:
            sx, sy = (np.asarray(s) for s in subsample)
        except (TypeError, ValueError) as err:
            raise ParameterError("subsample must be a pair (vertices of x, vertices of y).") from err
    for s, b, name in ((sx, basis_x, "x"), (sy, basis_y, "y")):
        if s.ndim != 1 or not len(s) or not np.issubdtype(s.dtype, np.integer):
            raise ParameterError(f"subsample of {name} must be a non-empty 1-D array of vertex indices.")
        if s.min() < 0 or s.max() >= b.n_vertices:
            raise ParameterError(f"subsample of {name} has vertices outside [0, {b.n_vertices}).")
    if isinstance(subsample, Samples):
        return subsample
    return Samples(sx.astype(np.int64), sy.astype(np.int64))


def check_anchors(anchors, basis_x: Basis, basis_y: Basis) -> tuple[np.ndarray, np.ndarray] | None:
    """``anchors`` as float64 ``(A_x (V_x, m), A_y (V_y, m))``, finite, one row per vertex (None
    passes). Raises ParameterError naming what is wrong."""
    if anchors is None:
        return None
    try:
        ax, ay = (np.asarray(a, dtype=np.float64) for a in anchors)
    except (TypeError, ValueError) as err:
        raise ParameterError("anchors must be a pair (A_x (V_x, m), A_y (V_y, m)) of arrays.") from err
    if ax.ndim != 2 or ay.ndim != 2 or ax.shape[1] != ay.shape[1] or not ax.shape[1]:
        raise ParameterError(
            f"anchors must be (V_x, m) and (V_y, m) arrays, m >= 1; got {ax.shape}, {ay.shape}."
        )
    if (len(ax), len(ay)) != (basis_x.n_vertices, basis_y.n_vertices):
        raise ParameterError(
            f"anchors have {len(ax)} and {len(ay)} rows; the bases {basis_x.n_vertices} and "
            f"{basis_y.n_vertices} vertices. Fix: one row per vertex, source first."
        )
    if not (np.isfinite(ax).all() and np.isfinite(ay).all()):
        raise ParameterError("anchors hold NaN or infinite values. Fix: finite coordinates only.")
    return ax, ay


class Samples(NamedTuple):
    """Where ZoomOut iterates when not on every vertex: sampled vertices ``x (S_x,)``, ``y (S_y,)``;
    ``weight (S_y,)``: fit weights on ``y``'s samples (None: unweighted); ``surfaces``: both
    shapes' ``SurfaceSampling`` to search the final map locally (None: exhaustive search)."""

    x: np.ndarray
    y: np.ndarray
    weight: np.ndarray | None = None
    surfaces: tuple[SurfaceSampling, SurfaceSampling] | None = None

    @classmethod
    def of_surfaces(cls, sampling_x: SurfaceSampling, sampling_y: SurfaceSampling) -> Samples:
        """Iterations on two surfaces' samples, fitted with their cells' areas, final map local."""
        return cls(sampling_x.index, sampling_y.index, sampling_y.weight, (sampling_x, sampling_y))

    @classmethod
    def of_pair(cls, samplings: tuple[SurfaceSampling, SurfaceSampling] | None) -> Samples | None:
        """:meth:`of_surfaces` of ``(sampling_x, sampling_y)``, None for None (every vertex)."""
        return None if samplings is None else cls.of_surfaces(*samplings)


class ZoomOutStep(Protocol):
    """One ZoomOut variant: ``fit`` a map at a size from a point map; ``embed`` it as the rows whose
    nearest neighbours are the next point map. ``rows``: None (every vertex) or :class:`Samples`."""

    def fit(self, p2p_yx: np.ndarray, size, rows: Samples | None) -> np.ndarray: ...

    def embed(self, C: np.ndarray, size, rows: Samples | None) -> tuple[np.ndarray, np.ndarray]:
        """``(E_y, E_x)``: query rows of ``y``, reference rows of ``x`` (of ``rows`` if given)."""
        ...


def least_squares_fit(phi_y: np.ndarray, target: np.ndarray, weight: np.ndarray | None) -> np.ndarray:
    """``C`` minimising ``Σ_s w_s ‖phi_y[s] C - target[s]‖²`` (``weight`` None: unweighted): the
    map fitted on samples, a quadrature of ``C = Φ_yᵀ B_y Φ_x[p2p]`` when ``w`` are areas."""
    if weight is not None:
        root = np.sqrt(weight)[:, None]
        phi_y, target = phi_y * root, target * root
    return np.linalg.lstsq(phi_y, target, rcond=None)[0]


@dataclass(frozen=True)
class SpectralStep:
    """ZoomOut's step in a pair of bases: at size ``k``, ``C`` is ``(rank(k), k)`` (``rank`` None:
    ``k``); point maps by ``mode`` with ``anchors`` appended."""

    basis_x: Basis
    basis_y: Basis
    mode: Mode = "orthogonal"
    anchors: tuple[np.ndarray, np.ndarray] | None = None
    rank: Callable[[int], int] | None = None

    def sizes(self, k: int) -> tuple[int, int]:
        return k, (k if self.rank is None else self.rank(k))

    def fit(self, p2p_yx, size, rows):
        kx, ky = self.sizes(size)
        if rows is None:
            return p2p_to_fmap(p2p_yx, self.basis_x, self.basis_y, kx, ky)
        phi_y = self.basis_y.values[rows.y, :ky]
        return least_squares_fit(phi_y, self.basis_x.values[p2p_yx, :kx], rows.weight)

    def embed(self, C, size, rows):
        cy, cx = C.shape
        phi_x, phi_y, anchors = self.basis_x.values, self.basis_y.values, self.anchors
        if rows is not None:
            phi_x, phi_y = phi_x[rows.x], phi_y[rows.y]
            anchors = None if anchors is None else (anchors[0][rows.x], anchors[1][rows.y])
        return embedding_pair(C, phi_x[:, :cx], phi_y[:, :cy], mode=self.mode, anchors=anchors)


def zoomout_iterations(
    step: ZoomOutStep,
    sizes,
    *,
    C_xy: np.ndarray | None = None,
    p2p_yx: np.ndarray | None = None,
    samples: Samples | None = None,
    guard: EnergyGuard | None = None,
    progress: bool = False,
):
    """The ZoomOut loop of every variant: for each of ``sizes``, ``C = step.fit(p2p, size)``, then
    the point map from ``step.embed(C, size)``, from exactly one of ``C_xy`` and ``p2p_yx (V_y,)``
    (else ParameterError). ``samples``: iterate on samples, the final map on every vertex.
    ``guard`` (:class:`EnergyGuard`): offered every map on every vertex; its best is returned.
    Returns ``(C, p2p_yx (V_y,))``, ``C`` at the last size."""
    sizes = list(sizes)
    if (C_xy is None) == (p2p_yx is None) or (p2p_yx is not None and not sizes):
        raise ParameterError(
            "ZoomOut starts from exactly one of C_xy and p2p_yx (a point map needs at least one size)."
        )
    C = None if C_xy is None else np.asarray(C_xy, dtype=np.float64)
    bar = tqdm(total=len(sizes), desc="ZoomOut", unit="size", disable=not progress, leave=False)
    if samples is None:
        p2p = p2p_yx if C is None else nearest_neighbor(*step.embed(C, None, None), precision="single")
        if guard is not None:
            guard.offer(p2p)
        for size in sizes:
            C = step.fit(p2p, size, None)
            p2p = nearest_neighbor(*step.embed(C, size, None), precision="single")
            if guard is not None:
                guard.offer(p2p)
            bar.update()
    else:
        if C is None:
            if guard is not None:
                guard.offer(p2p_yx)
            images = np.asarray(p2p_yx)[samples.y]
        else:
            images, coarse = _sample_images(step, C, None, samples, fine=bool(sizes))
        for i, size in enumerate(sizes):
            C = step.fit(images, size, samples)
            images, coarse = _sample_images(step, C, size, samples, fine=i + 1 < len(sizes))
            bar.update()
        query, reference = step.embed(C, sizes[-1] if sizes else None, None)
        p2p = search_p2p(query, reference, samples.surfaces, coarse=coarse if samples.surfaces else None)
        if guard is not None:
            guard.offer(p2p)
    bar.close()
    if guard is not None and guard.replaces(p2p):
        p2p = guard.p2p_yx
        C = step.fit(p2p, sizes[-1], None) if sizes else C
    return C, p2p


def _sample_images(step: ZoomOutStep, C: np.ndarray, size, samples: Samples, *, fine: bool = True):
    """``(images (S_y,), coarse (S_y,))``: where ``C`` sends ``y``'s samples among ``x``'s vertices,
    and the samples of ``x`` they matched (``fine``: refined locally with surface samplings)."""
    query, reference = step.embed(C, size, samples)
    coarse = nearest_neighbor(query, reference, precision="single")
    if samples.surfaces is None or not fine:
        return samples.x[coarse], coarse
    query, reference = step.embed(C, size, None)
    sampling_x, sampling_y = samples.surfaces
    images = local_nearest(query, reference, sampling_y, sampling_x, coarse=coarse, only_samples=True)
    return images[samples.y], coarse


def check_k_final(k: int, k_final: int | None) -> None:
    """ZoomOut grows the basis from ``k``: raise ParameterError unless ``k_final`` (None: ``2k``) is
    ``>= k``."""
    if k_final is not None and k_final < k:
        raise ParameterError(
            f"k_final={k_final} is below k={k}: ZoomOut grows the basis from k to k_final. Fix: "
            f"k_final >= {k} (or no k_final: 2k)."
        )


def zoomout(
    C_xy: np.ndarray,
    basis_x: Basis,
    basis_y: Basis,
    k_final: int,
    step: int | None = None,
    *,
    mode: Mode = "orthogonal",
    subsample=None,
    guard: bool = True,
    anchors: tuple[np.ndarray, np.ndarray] | None = None,
    p2p_yx: np.ndarray | None = None,
    progress: bool = False,
):
    """ZoomOut by basis prefixes (nested bases): from ``C_xy.shape`` to ``(k_final, k_final)``.

    Args:
        step: eigenfunctions added per iteration (default :func:`~torchfmap.fmap.defaults.zoomout_step`).
        mode: point-map conversion.
        subsample: ``(vertices of x, vertices of y)`` or :class:`Samples`: iterate on these only;
            the final point map uses every vertex.
        guard: return the iterate of lowest :func:`zoomout_energy` (never worse than the start).
        anchors: ``(A_x (V_x, m), A_y (V_y, m))``: corresponding coordinates appended to every
            point-map step's embedding.
        p2p_yx: ``(V_y,)`` the point map ``C_xy`` came from: the guard's start with ``subsample``.
        progress: a progress bar over the iterations.

    Returns:
        ``(C_xy (k_final, k_final), p2p_yx (V_y,))``.
    """
    C = np.asarray(C_xy, dtype=np.float64)
    check_k_final(min(C.shape), k_final)
    if k_final > min(basis_x.k, basis_y.k):
        raise ParameterError(f"k_final={k_final} exceeds the bases' sizes {basis_x.k}, {basis_y.k}.")
    step = zoomout_step(min(C.shape)) if step is None else step
    if step < 1:
        raise ParameterError(f"step must be >= 1, got {step}.")
    samples = _check_samples(subsample, basis_x, basis_y)
    anchors = check_anchors(anchors, basis_x, basis_y)
    k = min(C.shape)
    sizes = list(range(k, k_final, step)) + [k_final]
    best = EnergyGuard(basis_x, basis_y, sizes, enabled=guard)
    spectral = SpectralStep(basis_x, basis_y, mode, anchors)
    if samples is not None and p2p_yx is not None:
        p2p_yx = check_p2p(p2p_yx, basis_y.n_vertices, basis_x.n_vertices, "p2p_yx")
        return zoomout_iterations(spectral, sizes[1:] or sizes, p2p_yx=p2p_yx, samples=samples, guard=best,
                                  progress=progress)  # fmt: skip
    if samples is not None and guard:
        best.offer(search_p2p(*spectral.embed(C, None, None), samples.surfaces))
    return zoomout_iterations(spectral, sizes[1:], C_xy=C, samples=samples, guard=best, progress=progress)


class EnergyGuard:
    """ZoomOut's guard: keeps the offered point map of lowest :func:`zoomout_energy` in
    ``basis_x, basis_y`` over ``sizes`` (the first of equal ones). ``enabled=False``: keeps none."""

    def __init__(self, basis_x: Basis, basis_y: Basis, sizes, *, enabled: bool = True) -> None:
        self.basis_x, self.basis_y, self.sizes, self.enabled = basis_x, basis_y, list(sizes), enabled
        self.energy = np.inf
        #: the kept point map ``(V_y,)``, None before the first offer (or when disabled)
        self.p2p_yx: np.ndarray | None = None

    def offer(self, p2p_yx: np.ndarray) -> None:
        """Score ``p2p_yx`` and keep it if its energy is the lowest so far."""
        if self.enabled:
            energy = zoomout_energy(p2p_yx, self.basis_x, self.basis_y, self.sizes)
            if self.p2p_yx is None or energy < self.energy:
                self.energy, self.p2p_yx = energy, p2p_yx

    def replaces(self, p2p_yx: np.ndarray) -> bool:
        """Whether the kept map is another than ``p2p_yx`` (the last iterate)."""
        return self.p2p_yx is not None and self.p2p_yx is not p2p_yx


def zoomout_energy(p2p_yx: np.ndarray, basis_x: Basis, basis_y: Basis, sizes) -> float:
    """ZoomOut's energy of a point map (Melzi et al. 2019, Eq. 2): ``Σ_k ‖C_kᵀ C_k - I‖² / k`` over
    ``k`` in ``sizes``, ``C_k`` the ``(k, k)`` prefix of ``C = Φ_yᵀ B_y Φ_x[p2p]`` at the largest."""
    kf = max(sizes)
    C = p2p_to_fmap(p2p_yx, basis_x, basis_y, kf, kf)
    total = 0.0
    for k in sizes:
        Ck = C[:k, :k]
        total += float(np.sum((Ck.T @ Ck - np.eye(k)) ** 2)) / k
    return total


@dataclass(frozen=True)
class SequenceStep:
    """ZoomOut's step over sequences of bases: at size ``i`` the pair ``(bases_x[i], bases_y[i])``."""

    bases_x: tuple[Basis, ...]
    bases_y: tuple[Basis, ...]
    mode: Mode

    def fit(self, p2p_yx, size, rows):
        bx, by = self.bases_x[size], self.bases_y[size]
        if rows is None:
            return p2p_to_fmap(p2p_yx, bx, by)
        return least_squares_fit(by.values[rows.y], bx.values[p2p_yx], rows.weight)

    def embed(self, C, size, rows):
        size = len(self.bases_x) - 1 if size is None else size
        return SpectralStep(self.bases_x[size], self.bases_y[size], self.mode).embed(C, size, rows)


def zoomout_sequence(
    p2p_yx: np.ndarray, bases_x: list[Basis], bases_y: list[Basis], *, mode: Mode = "pullback", subsample=None
):
    """ZoomOut over sequences of bases with growing spans: from a point map, for each pair
    ``(bases_x[i], bases_y[i])`` project and convert back by ``mode`` (``subsample`` as
    :func:`zoomout`). Returns ``(C_xy in the last pair, p2p_yx (V_y,))``."""
    if len(bases_x) != len(bases_y) or not bases_x:
        raise ParameterError("bases_x and bases_y must be non-empty sequences of the same length.")
    p2p = check_p2p(p2p_yx, bases_y[0].n_vertices, bases_x[0].n_vertices, "p2p_yx")
    samples = _check_samples(subsample, bases_x[0], bases_y[0])
    step = SequenceStep(tuple(bases_x), tuple(bases_y), mode)
    if samples is None:
        return zoomout_iterations(step, range(len(bases_x)), p2p_yx=p2p)
    C = p2p_to_fmap(p2p, bases_x[0], bases_y[0])
    return zoomout_iterations(step, range(1, len(bases_x)), C_xy=C, samples=samples)


class Refined(NamedTuple):
    """A refiner's result: the map, its bases and their seed pairs ``(S, 2)`` (or None)."""

    C_xy: np.ndarray
    p2p_yx: np.ndarray
    basis_x: Basis
    basis_y: Basis
    seeds: np.ndarray | None
