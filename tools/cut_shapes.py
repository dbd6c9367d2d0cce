"""Partial dev data: real shapes cut by planes and holes, ground truth carried to the whole.

Run by hand from the repository root::

    python -m tools.cut_shapes            # the fixed validation list -> bench/data/partial_faust
    python -m tools.cut_shapes --remesh 4000 --out /tmp/partial_remeshed

Each pair ``(whole, other)`` of the fixed validation list ``PAIRS`` (FAUST_r training humans
070-079, the validation humans of the rest of bench) gives parts of ``other`` cut by
``torchfmap.data.cuts`` (a plane, or four holes) at each area ratio, written as the partial
collection ``torchfmap eval --partial`` reads (``torchfmap.evaluate.partial``): ``full/<whole>.off``,
``partial/<whole>_<other>_<cut><ratio>.off``, ``corres/<part>.map`` (0-based; line ``v``: the
whole's vertex of part vertex ``v``, ``-1`` where the template correspondence of the data set
does not reach it). Ground truth goes through the data set's template rows (``corres/*.vts``:
row ``r`` of both files is one template point). With ``--remesh N`` each part is remeshed
(pymeshlab, isotropic, ~N vertices), so it is not a subset of the whole's vertices; each new
vertex takes the ground truth of its nearest old one (an error of about half an edge).
The files are git-ignored (derived from data that must not be shipped).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from bench.common import LOCAL_DATA_DIR, log
from bench.common import require_data as _require_data
from torchfmap.data.cuts import cut_holes, cut_plane
from torchfmap.io import load_mesh, read_vts, save_mesh, write_map

#: The fixed validation list: FAUST_r training pairs (different people and poses).
PAIRS = [("tr_reg_070", "tr_reg_071"), ("tr_reg_072", "tr_reg_073"), ("tr_reg_074", "tr_reg_075"),
         ("tr_reg_076", "tr_reg_077"), ("tr_reg_078", "tr_reg_079")]  # fmt: skip
RATIOS = (0.3, 0.5, 0.7, 0.9)
CUTS = ("plane", "holes")


def part_to_whole(vts_whole: np.ndarray, vts_other: np.ndarray, part_vertices: np.ndarray, n_other: int):
    """``(V_part,)`` the whole's vertex of each part vertex through the template rows (-1: none)."""
    other_to_whole = np.full(n_other, -1, dtype=np.int64)
    other_to_whole[vts_other] = vts_whole  # the last template row reaching a vertex wins
    return other_to_whole[part_vertices]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="faust_r_train", help="data set folder under ../shared/data")
    parser.add_argument("--out", type=Path, default=LOCAL_DATA_DIR / "partial_faust")
    parser.add_argument("--remesh", type=int, default=0, help="remesh each part to about N vertices")
    args = parser.parse_args(argv)
    src = _require_data(args.data)
    for sub in ("full", "partial", "corres"):
        (args.out / sub).mkdir(parents=True, exist_ok=True)
    jobs = [(w, o, r, c) for w, o in PAIRS for r in RATIOS for c in CUTS]
    for whole_name, other_name, ratio, how in tqdm(jobs, desc="cut"):
        whole, other = load_mesh(src / f"{whole_name}.off"), load_mesh(src / f"{other_name}.off")
        save_mesh(whole, args.out / "full" / f"{whole_name}.off")
        cut = cut_plane(other, ratio, seed=1) if how == "plane" else cut_holes(other, ratio, 4, seed=1)
        vts = [read_vts(src / "corres" / f"{n}.vts") for n in (whole_name, other_name)]
        gt = part_to_whole(vts[0], vts[1], cut.vertices, other.n_vertices)
        part = cut.mesh
        if args.remesh:
            from torchfmap.remesh import remesh

            part = remesh(cut.mesh, args.remesh, "isotropic").mesh
            gt = gt[cKDTree(cut.mesh.vertices).query(part.vertices)[1]]
        name = f"{whole_name}_{other_name}_{how}{round(100 * ratio)}"
        save_mesh(part, args.out / "partial" / f"{name}.off")
        write_map(args.out / "corres" / f"{name}.map", gt)
    log(f"{len(jobs)} parts -> {args.out} (torchfmap eval {args.out} --partial)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
