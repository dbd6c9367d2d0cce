"""Match two meshes with ``torchfmap.match``: without landmarks, then with a few.

Shows the map convention (``p2p_yx[i]`` is the vertex of ``x`` matched to vertex ``i`` of
``y``), the geodesic error against a ground truth, and the map file. By default it runs on the
demo pair shipped in the package (a bumpy blob and its bent, vertex-shuffled copy, with the
true map), its landmarks drawn from the ground truth::

    python examples/01_match.py                      # the demo pair, writes map.txt
    python examples/01_match.py X.off Y.ply --landmarks pairs.txt --gt truth.txt --out map.txt

``--landmarks``: one pair per line, ``vertex_of_x vertex_of_y`` (0-based). ``--gt``: the true
map, in the format this writes (line ``i``: the vertex of ``x`` for vertex ``i`` of ``y``).
Errors are geodesic distances on ``x`` to the true match, in units of ``sqrt(area of x)``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import torchfmap as tf
from torchfmap.data import demo_pair_paths
from torchfmap.evaluate.scores import evaluate_map, gt_from_map, landmarks_from_gt
from torchfmap.io import read_landmark_pairs, read_map, write_map
from torchfmap.operators import DistanceRows


def main(argv: list[str] | None = None) -> dict:
    """Run the example; returns ``{'errors': {label: mean error}, 'out': map file}`` (errors
    only with a ground truth)."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("x", nargs="?", type=Path, help="source mesh (default: the demo's blob_a)")
    parser.add_argument("y", nargs="?", type=Path, help="target mesh (default: the demo's blob_b)")
    parser.add_argument("--landmarks", type=Path, help="landmark pairs file (demo: drawn from the truth)")
    parser.add_argument("--n-landmarks", type=int, default=6, help="landmarks drawn on the demo pair")
    parser.add_argument("--gt", type=Path, help="the true map y -> x (demo: its shipped map)")
    parser.add_argument("--k", type=int, default=40, help="basis size")
    parser.add_argument("--out", type=Path, default=Path("map.txt"), help="the map file to write")
    args = parser.parse_args(argv)

    demo_x, demo_y, demo_gt = demo_pair_paths()
    x = tf.load_mesh(args.x or demo_x)  # vertex order kept: indices are the file's
    y = tf.load_mesh(args.y or demo_y)
    gt_file = args.gt or (demo_gt if args.x is None else None)
    gt = gt_from_map(read_map(gt_file)) if gt_file else None  # a Correspondence (idx_x, idx_y)
    print(f"x: {x.n_vertices} vertices, y: {y.n_vertices} vertices")

    # 1. no landmarks: the Laplacian eigenbasis, WKS descriptors, then ZoomOut
    plain = tf.match(x, y, k=args.k, refine="zoomout")
    p2p_yx = plain.p2p_yx  # (V_y,): p2p_yx[i] is the vertex of x matched to vertex i of y
    print(f"no landmarks: basis {plain.kind}, C_xy {plain.C_xy.shape} (K_y, K_x), p2p_yx {p2p_yx.shape}")
    print("  timings [s]: " + ", ".join(f"{name} {t:.2f}" for name, t in plain.timings.items()))
    # the convention at work: a function on x (here its height) carried to y is f_x[p2p_yx]
    height_on_y = x.vertices[:, 2][p2p_yx]
    print(f"  height of x carried to y: {height_on_y.shape}, range {np.ptp(height_on_y):.3f}")
    results = {"no landmarks": plain.p2p_yx_initial, "no landmarks + zoomout": p2p_yx}

    # 2. a few landmarks: match chooses its basis by geodesic distortion (no ground truth used)
    landmarks = read_landmark_pairs(args.landmarks) if args.landmarks else None
    if landmarks is None and gt is not None:
        landmarks = landmarks_from_gt(x, gt, args.n_landmarks)  # (L, 2) pairs (x vertex, y vertex)
    if landmarks is not None:
        guided = tf.match(x, y, landmarks=landmarks, k=args.k, refine="zoomout")
        print(f"{len(landmarks)} landmarks: chose {guided.kind} (distortion: {guided.scores()})")
        print(f"  {guided.refine_check}")  # the guard's evidence: kept or dropped, and why
        results[f"{len(landmarks)} landmarks"] = guided.p2p_yx_initial
        results[f"{len(landmarks)} landmarks + zoomout"] = guided.p2p_yx
        p2p_yx = guided.p2p_yx
    else:
        print("no landmarks given: pass --landmarks pairs.txt to match with them")

    # 3. the error against the ground truth, one distance row per true source vertex, kept
    errors = {}
    if gt is not None:
        rows = DistanceRows(x)  # geodesic rows on x, shared by the maps scored below
        for label, p2p in results.items():
            report, _ = evaluate_map(x, y, p2p, gt, solver=rows)
            errors[label] = report.mean_error
            print(f"  {label:<26} mean geodesic error {report.mean_error:.4f}  (AUC {report.auc:.3f})")

    # 4. the map file: line i holds p2p_yx[i] (the format of `torchfmap match --out`)
    path = write_map(args.out, p2p_yx)
    assert np.array_equal(read_map(path), p2p_yx)
    print(f"wrote {path} ({len(p2p_yx)} lines: vertex of x for each vertex of y)")
    return {"errors": errors, "out": path}


if __name__ == "__main__":
    main()
