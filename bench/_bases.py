"""Settings and helpers shared by ``bases.py``, ``heat_accuracy.py`` and ``heat_support.py``.

All meshes are ``bench_mesh(n)`` (irregular, closed, genus 0); ``(L, B)`` is
``torchfmap.laplacian(mesh)`` (cotan + lumped voronoi mass). Seeds are ``N_SEEDS`` Euclidean
farthest-point samples, so that seed selection is not part of any basis timing.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.sparse.linalg as ssla
from _common import log, timed
from _meshes import bench_mesh

import torchfmap
from torchfmap.bases import concatenate, orthonormalize
from torchfmap.operators.heat import heat_kernels

N_SEEDS = 50
#: Relative diffusion times (multiplied by the mesh area) of the diffusion bases.
TIMES = (1e-3, 3e-3, 1e-2, 3e-2)
SMALL_TIMES = (1e-5, 1e-4)
HEAT_TOL = 1e-6
EIGSH_RATIO_K = 100


class Failed(str):
    """A table cell for an operation that raised (the traceback goes to stderr)."""


def attempt(label: str, fn: Callable[[], Any]) -> Any:
    """``fn()``, or a :class:`Failed` cell with the traceback logged if it raises."""
    try:
        return fn()
    except Exception as exc:  # noqa: BLE001 - a benchmark reports failures and carries on
        log(f"  !! {label} raised {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
        return Failed(f"ERROR {type(exc).__name__}")


def run_timed(label: str, fn: Callable[[], Any], repeats: int, max_repeat_s: float) -> tuple[Any, Any]:
    """``(median time, last result)`` of :func:`timed`, or ``(Failed cell, None)`` if ``fn`` raises."""
    res = attempt(label, lambda: timed(fn, repeats, max_repeat_s=max_repeat_s))
    return (res, None) if isinstance(res, Failed) else (res[0], res[2])


def rel_diff(K: np.ndarray, K_ref: np.ndarray) -> float:
    """Max over columns of ``max|K - K_ref| / max|K_ref|`` for ``(V, C)`` arrays."""
    return float((np.abs(K - K_ref).max(axis=0) / np.abs(K_ref).max(axis=0)).max())


def column_errors(K: np.ndarray, K_ref: np.ndarray) -> np.ndarray:
    """``max|K - K_ref| / max|K_ref|`` for every (time, seed) column of ``(T, V, S)`` arrays."""
    return np.abs(K - K_ref).max(axis=1) / np.abs(K_ref).max(axis=1)


def eigsh(L, B, k: int):
    """The baseline: ``scipy.sparse.linalg.eigsh`` in shift-invert mode (SuperLU)."""
    return ssla.eigsh(L, k=k, M=B, sigma=-1e-8, which="LM")


def diffusion(mesh, seeds, ops, times=TIMES, local: bool | str = False):
    """``diffusion_basis`` with krylov, tol ``HEAT_TOL``."""
    return torchfmap.diffusion_basis(mesh, seeds, times, "krylov", operators=ops, tol=HEAT_TOL, local=local)


def setup(n: int, seed: int, n_seeds: int = N_SEEDS):
    """``(mesh, L, B, seeds)`` of ``bench_mesh(n, seed)`` with ``n_seeds`` Euclidean FPS seeds."""
    mesh = bench_mesh(n, seed)
    L, B = torchfmap.laplacian(mesh)
    seeds = torchfmap.farthest_point_sampling(mesh, n_seeds, metric="euclidean")
    return mesh, L, B, seeds


def warm_up(n: int, seed: int) -> None:
    """One call of every timed operation on a small mesh (imports, ARPACK, CHOLMOD set-up)."""
    log(f"warm-up of every timed operation on bench_mesh({n})")
    mesh, L, B, s50 = setup(n, seed)
    torchfmap.farthest_point_sampling(mesh, 5, metric="geodesic")
    h = torchfmap.harmonic_basis(mesh, s50, operators=(L, B))
    times = np.array(SMALL_TIMES + TIMES) * mesh.area
    for method in ("krylov", "rational", "backward_euler", "spectral"):
        heat_kernels((L, B), s50[:5], times[:2], method=method, tol=HEAT_TOL)
    dg = diffusion(mesh, s50, (L, B), local=False)
    diffusion(mesh, s50, (L, B), local="auto")
    for m in ("mgs", "cholqr"):
        orthonormalize(concatenate([dg, h]), m)
    eigsh(L, B, 50)
