"""pyFM (PyPI ``pyfmaps``) runs shared by the matching benchmarks in ``bench/``.

Direction: pyFM's ``mesh1`` is our source ``x`` and ``mesh2`` our target ``y``; its ``FM_12`` is
``(k2, k1)`` like our ``C_xy`` and ``get_p2p()`` returns ``p2p_21``, the vertex of ``mesh1`` for
every vertex of ``mesh2``: our ``p2p_yx``. Landmarks ``(L, 2)`` go to ``preprocess(landmarks=...)``
whose column 0 is on ``mesh1`` and column 1 on ``mesh2``: our ``(x vertex, y vertex)`` pairs.
``TriMesh(vertices, faces)`` is built from our arrays, so the vertex order is identical.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import _common  # noqa: F401  (puts this checkout first on sys.path, before torchfmap)
import numpy as np

import torchfmap

#: Energy weights of pyFM's README example (cat -> lion with 20 landmarks, WKS descriptors).
PYFM_FIT = {"w_descr": 1e0, "w_lap": 1e-2, "w_dcomm": 1e-1, "w_orient": 0.0}
#: ICP iterations (ours: ``icp_refine(n_iter=10)``).
PYFM_ICP_NIT = 10


@dataclass
class PyfmRun:
    """Point maps (``p2p_yx``) and wall times of one pyFM pipeline, per refinement."""

    p2p: dict[str | None, np.ndarray] = field(default_factory=dict)
    #: total seconds of the pipeline ending with each refinement (None: no refinement).
    times: dict[str | None, float] = field(default_factory=dict)
    #: seconds of the phases: preprocess (eigenpairs + descriptors), fit, p2p, icp, zoomout.
    phases: dict[str, float] = field(default_factory=dict)
    n_descr: int = 0
    k_process: int = 0


def _refined_p2p(model, refine: str, step: int, zoomout_samples: int) -> np.ndarray:
    """``p2p_yx`` after one refinement of the fitted map ``FM_12`` (times include ``get_p2p``)."""
    if refine == "icp":
        fm = model.icp_refine(nit=PYFM_ICP_NIT)
    elif refine == "zoomout":
        fm = model.zoomout_refine(nit=10, step=step)
    elif refine == "zoomout-sub":
        fm = model.zoomout_refine(nit=10, step=step, subsample=zoomout_samples)
    else:
        raise ValueError(f"unknown refinement {refine!r}")
    return np.asarray(model.get_p2p(fm), dtype=np.int64)


def run_pyfm(
    mesh_x: torchfmap.Mesh,
    mesh_y: torchfmap.Mesh,
    *,
    k: int,
    landmarks: np.ndarray | None = None,
    refine: tuple[str, ...] = ("icp", "zoomout"),
    n_descr: int = 50,
    k_descr: int = 50,
    subsample_step: int = 1,
    zoomout_step: int | None = None,
    zoomout_samples: int = 2000,
    fit: dict | None = None,
) -> PyfmRun:
    """pyFM's whole pipeline: ``TriMesh`` -> ``preprocess`` (WKS) -> ``fit`` -> ``get_p2p`` [-> refine].

    Args:
        k: functional map size ``K=(k, k)``.
        landmarks: ``(L, 2)`` pairs ``(x vertex, y vertex)`` (landmark WKS descriptors), or None.
        refine: refinements run after the unrefined map, each from ``FM_12``: ``'icp'``
            (``icp_refine(nit=10)``) and ``'zoomout'`` (``zoomout_refine(nit=10, step)``, from
            ``k`` to ``2k`` like ``match(refine='zoomout')``; ``step`` defaults to ``k // 10``).
        n_descr: WKS energies per descriptor (plain WKS, and per landmark).
        k_descr: eigenpairs used by the WKS (``k_process`` is at least this).
        subsample_step: keep every n-th descriptor column (pyFM's option).
        zoomout_samples: FPS samples per shape of the ``'zoomout-sub'`` refinement
            (``zoomout_refine(subsample=...)``).
        fit: energy weights of ``fit`` (default :data:`PYFM_FIT`).
    """
    from pyFM.functional import FunctionalMapping
    from pyFM.mesh import TriMesh

    step = zoomout_step or max(1, k // 10)
    zooms = any(r.startswith("zoomout") for r in refine)
    k_process = max(k + 10 * step if zooms else k, k_descr)
    run = PyfmRun(k_process=k_process)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        t0 = time.perf_counter()
        m1 = TriMesh(np.array(mesh_x.vertices), np.array(mesh_x.faces))
        m2 = TriMesh(np.array(mesh_y.vertices), np.array(mesh_y.faces))
        model = FunctionalMapping(m1, m2)
        model.preprocess(
            n_descr=n_descr,
            descr_type="WKS",
            landmarks=None if landmarks is None else np.asarray(landmarks),
            subsample_step=subsample_step,
            k_process=k_process,
            k_descr=k_descr,
        )
        t1 = time.perf_counter()
        model.fit(K=(k, k), **(PYFM_FIT if fit is None else fit))
        t2 = time.perf_counter()
        run.p2p[None] = np.asarray(model.get_p2p(), dtype=np.int64)
        t3 = time.perf_counter()
        run.phases = {"preprocess": t1 - t0, "fit": t2 - t1, "p2p": t3 - t2}
        run.times[None] = t3 - t0
        run.n_descr = model.descr1.shape[1]
        for r in refine:
            t0 = time.perf_counter()
            run.p2p[r] = _refined_p2p(model, r, step, zoomout_samples)
            run.phases[r] = time.perf_counter() - t0
            run.times[r] = run.times[None] + run.phases[r]
    for p2p in run.p2p.values():
        if p2p.shape != (mesh_y.n_vertices,) or p2p.max() >= mesh_x.n_vertices:
            raise RuntimeError(f"pyFM returned a map of shape {p2p.shape}: not p2p_yx (direction?)")
    return run
