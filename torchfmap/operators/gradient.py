"""Per-vertex tangent frames and the intrinsic vertex gradient (float64 numpy precomputation, applied
by :func:`torchfmap.nn.functional.spatial_gradient`): the area-weighted mean of the faces' gradients
in the frame ``(e1, e2 = n × e1)``, as an edge list with ``(∇f)_v = Σ_{rows == v} weights · f[cols]``."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..mesh import Mesh


def tangent_frames(mesh: Mesh) -> np.ndarray:
    """``(V, 3, 3)`` right-handed orthonormal frames: ``[:, 0] = e1``, ``[:, 1] = e2``, ``[:, 2] = n``;
    ``e1`` is the x axis (y where the normal is close to x) projected on the tangent plane."""
    n = mesh.vertex_normals
    ref = np.zeros_like(n)
    near_x = np.abs(n[:, 0]) > 0.9
    ref[~near_x, 0] = 1.0
    ref[near_x, 1] = 1.0
    e1 = ref - (ref * n).sum(axis=1, keepdims=True) * n
    e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-300)
    e2 = np.cross(n, e1)
    return np.stack([e1, e2, n], axis=1)


def gradient_operator(mesh: Mesh) -> dict[str, np.ndarray]:
    """The vertex gradient in tangent frames as an edge list (see the module docstring).

    Returns ``{'grad_rows', 'grad_cols'}`` (int64, ``(E,)``, sorted by ``(row, col)``),
    ``{'grad_x', 'grad_y'}`` (float64, ``(E,)``): the ``e1`` and ``e2`` components, and
    ``'grad_order_t'`` (int64, ``(E,)``): the permutation sorting the edges by ``(col, row)``.
    """
    v, f = mesh.vertices, mesh.faces
    n_v = len(v)
    areas = mesh.face_areas
    normals = mesh.face_normals
    frames = tangent_frames(mesh)
    vertex_area = np.zeros(n_v)
    for c in range(3):
        np.add.at(vertex_area, f[:, c], areas)
    rows, cols, wx, wy = [], [], [], []
    for u in range(3):  # the hat function of corner u: A_f · gradient = n × (x_{u+2} - x_{u+1}) / 2
        edge = v[f[:, (u + 2) % 3]] - v[f[:, (u + 1) % 3]]
        g = np.cross(normals, edge) / 2.0
        for c in range(3):  # the vertex receiving the face's contribution
            target = f[:, c]
            scale = 1.0 / np.maximum(vertex_area[target], 1e-300)
            rows.append(target)
            cols.append(f[:, u])
            wx.append((g * frames[target, 0]).sum(axis=1) * scale)
            wy.append((g * frames[target, 1]).sum(axis=1) * scale)
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    out = {}
    for name, w in (("grad_x", np.concatenate(wx)), ("grad_y", np.concatenate(wy))):
        out[name] = sp.coo_matrix((w, (rows, cols)), shape=(n_v, n_v)).tocsr()
    pattern = (abs(out["grad_x"]) + abs(out["grad_y"])).tocoo()
    r, c = pattern.row.astype(np.int64), pattern.col.astype(np.int64)
    by_row = np.lexsort((c, r))
    r, c = r[by_row], c[by_row]
    return {
        "grad_rows": r,
        "grad_cols": c,
        "grad_x": np.asarray(out["grad_x"][r, c]).ravel(),
        "grad_y": np.asarray(out["grad_y"][r, c]).ravel(),
        "grad_order_t": np.lexsort((r, c)).astype(np.int64),
    }
