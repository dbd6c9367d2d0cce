"""Feature-aware bases: harmonic and diffusion functions at seeds, their checks, and matching.

On one mesh (default: the demo's ``blob_a``), at seeds (``--landmarks``: the source column of
a landmark pairs file, else farthest points):

- harmonic functions ``psi_i`` (``Delta psi_i = 0``, ``psi_i(seed_j) = delta_ij``): they are a
  partition of unity (``sum_i psi_i = 1`` everywhere);
- heat kernels at each seed and relative time ``t`` (absolute ``t * area``): their support
  (share of the surface where ``|f| > 1e-3 max|f|``) grows with ``t``;
- the B-orthonormal stack of both (``basis_stack``): ``Phi^T B Phi = I``; columns that depend
  on earlier ones are dropped and listed (``basis.dropped``; wide kernels at crowded seeds).

Then it matches the demo pair (or ``x y`` given with ``--landmarks`` and ``--gt``) from a few
landmarks in the feature-aware ``basis='diffusion'`` and in the eigenbasis, and scores both.
``--png`` draws a few basis functions (needs matplotlib; skipped with a message without it)::

    python examples/02_feature_aware_bases.py --png bases.png
    python examples/02_feature_aware_bases.py X.off Y.off --landmarks pairs.txt --gt truth.txt
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import torchfmap as tf
from torchfmap.data import demo_pair_paths
from torchfmap.evaluate.scores import evaluate_map, gt_from_map, landmarks_from_gt
from torchfmap.io import read_landmark_pairs, read_map
from torchfmap.operators import DistanceRows

TIMES = (1e-3, 1e-2, 1e-1)  # relative diffusion times, small to large


def draw(mesh: tf.Mesh, functions: dict[str, np.ndarray], seeds: np.ndarray, path: Path) -> bool:
    """One panel per function on ``mesh`` (colour: the function's value), seeds as dots.
    Returns False (and says why) when matplotlib is absent."""
    try:
        from matplotlib import colormaps
        from matplotlib.figure import Figure
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection
    except ImportError:
        print(f"matplotlib is not installed: no {path} (pip install matplotlib)")
        return False
    fig = Figure(figsize=(3.2 * len(functions), 3.4))
    v, f = mesh.vertices, mesh.faces
    for i, (title, values) in enumerate(functions.items()):
        ax = fig.add_subplot(1, len(functions), i + 1, projection="3d")
        face_values = values[f].mean(axis=1)
        shade = (face_values - face_values.min()) / max(np.ptp(face_values), 1e-12)  # each panel its scale
        ax.add_collection3d(Poly3DCollection(v[f], facecolors=colormaps["viridis"](shade), linewidth=0))
        ax.scatter(*v[seeds].T, color="red", s=6)
        lo, hi = v.min(axis=0), v.max(axis=0)
        ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]), title=title)
        ax.set_box_aspect(hi - lo, zoom=1.2)
        ax.set_axis_off()
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.92, wspace=0)
    fig.savefig(path, dpi=100)
    print(f"wrote {path}")
    return True


def main(argv: list[str] | None = None) -> dict:
    """Run the example; returns the checks (``'unity'``, ``'orthonormality'``: largest
    deviations), ``'support'`` (mean support per time), ``'errors'`` (mean geodesic error per
    basis kind, with a ground truth) and ``'png'`` (the figure written, or None)."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("x", nargs="?", type=Path, help="source mesh (default: the demo's blob_a)")
    parser.add_argument("y", nargs="?", type=Path, help="target mesh (default: the demo's blob_b)")
    parser.add_argument("--landmarks", type=Path, help="landmark pairs file (demo: drawn from the truth)")
    parser.add_argument("--gt", type=Path, help="the true map y -> x (demo: its shipped map)")
    parser.add_argument("--seeds", type=int, default=12, help="seeds of the bases on x")
    parser.add_argument("--n-landmarks", type=int, default=6, help="landmarks drawn on the demo pair")
    parser.add_argument("--k", type=int, default=40, help="basis size of the matches")
    parser.add_argument("--png", type=Path, help="draw a few basis functions here (matplotlib)")
    args = parser.parse_args(argv)

    demo_x, demo_y, demo_gt = demo_pair_paths()
    x, y = tf.load_mesh(args.x or demo_x), tf.load_mesh(args.y or demo_y)
    gt_file = args.gt or (demo_gt if args.x is None else None)
    gt = gt_from_map(read_map(gt_file)) if gt_file else None
    landmarks = read_landmark_pairs(args.landmarks) if args.landmarks else None
    if landmarks is None and gt is not None:
        landmarks = landmarks_from_gt(x, gt, args.n_landmarks)  # (L, 2): (x vertex, y vertex)

    # seeds on x: the landmarks first, farthest points after (geodesic farthest-point sampling)
    first = None if landmarks is None else landmarks[:, 0]
    n_seeds = max(args.seeds, 0 if first is None else len(first))
    seeds = tf.farthest_point_sampling(x, n_seeds, landmarks=first)
    ops = tf.laplacian(x)  # (L, B), shared by the bases below

    harmonic = tf.harmonic_basis(x, seeds, operators=ops)  # (V, S), not orthonormal
    unity = float(np.abs(harmonic.values.sum(axis=1) - 1).max())
    interpolates = float(np.abs(harmonic.values[seeds] - np.eye(len(seeds))).max())
    print(f"{len(seeds)} seeds on x ({x.n_vertices} vertices)")
    print(f"harmonic: max |sum_i psi_i - 1| = {unity:.1e}, "
          f"max |psi_i(seed_j) - delta_ij| = {interpolates:.1e}")  # fmt: skip

    diffusion = tf.diffusion_basis(x, seeds, times=TIMES, operators=ops)  # columns by time, then seed
    times = np.array([c.time for c in diffusion.columns])
    support = {t: float(diffusion.support()[times == t].mean()) for t in TIMES}
    shares = ", ".join(f"t={t:g}: {100 * s:.0f}%" for t, s in support.items())
    print(f"diffusion: mean support of the kernels {shares}")

    stack = tf.basis_stack(x, seeds, times=TIMES, harmonic=True, operators=ops)  # B-orthonormal
    orthonormality = float(np.abs(stack.gram() - np.eye(stack.k)).max())
    print(f"stack: {diffusion.k} kernels + {harmonic.k} harmonic -> {stack.k} columns kept, "
          f"{len(stack.dropped)} dropped as dependent; "
          f"max |Phi^T B Phi - I| = {orthonormality:.1e}")  # fmt: skip

    errors = {}
    if landmarks is not None and gt is not None:
        rows = DistanceRows(x)
        for basis in ("diffusion", "laplacian"):
            result = tf.match(x, y, landmarks=landmarks, basis=basis, k=args.k)
            report, _ = evaluate_map(x, y, result.p2p_yx, gt, solver=rows)
            errors[basis] = report.mean_error
            print(f"match, {len(landmarks)} landmarks, basis={basis!r:<12} "
                  f"mean geodesic error {report.mean_error:.4f}")  # fmt: skip
    else:
        print("matching needs landmarks and a ground truth: pass --landmarks and --gt (or run on the demo)")

    png = None
    if args.png:
        eigen = tf.laplacian_eigenbasis(x, 6, operators=ops)
        j = int(np.argmax(x.vertices[seeds, 2]))  # the top seed, in view
        panels = {
            f"harmonic psi_{j}": harmonic.values[:, j],
            f"heat kernel t={TIMES[0]:g}": diffusion.values[:, j],  # columns: time-major, then seed
            f"heat kernel t={TIMES[-1]:g}": diffusion.values[:, (len(TIMES) - 1) * len(seeds) + j],
            "eigenfunction 5": eigen.values[:, 5],
        }
        png = args.png if draw(x, panels, seeds, args.png) else None
    return {
        "unity": unity, "orthonormality": orthonormality, "support": support, "errors": errors, "png": png,
    }  # fmt: skip


if __name__ == "__main__":
    main()
