"""Dev data made differently from ours: remeshed copies of the shared shapes, ground truth carried.

Run by hand from the repository root (needs ``pip install 'torchfmap[remesh]'``)::

    python -m tools.remesh                      # every set below, into bench/data/
    python -m tools.remesh --sets scape_r --out /tmp/remeshed

Sets (each a folder of ``<name>.off`` and ``corres/<name>.vts``, 1-based, row r of A.vts and of
B.vts corresponding, as in ``../shared/data``; a ``README.md`` says how it was made):

- ``scape_r``: the 51 SCAPE training poses, each remeshed on its own (isotropic, ~5,000
  vertices), as SCAPE_r is; ``.vts`` rows are the 12,500 template vertices;
- ``scape_a``: the same poses, anisotropically remeshed (``torchfmap.remesh``, stretch 3 along
  a random direction per pose), ~5,000 vertices;
- ``faust_a``: FAUST_r training shapes tr_reg_000..079 anisotropically remeshed from their
  FAUST_r meshing (stretch 3, random direction per shape), ~5,000 vertices, their ``.vts``
  carried through (5,000 rows);
- ``faust_h``, ``scape_h``: the hard meshings, harder than the anisotropic benchmark sets:
  triangles stretched 5 : 1 along a random direction, edges about 4 times longer at one end of
  the body than at the other (``remesh(density=4)``, along another random direction), and a
  vertex count drawn per shape between 3,000 and 10,000; FAUST_r tr_reg_000..079 and SCAPE
  mesh000..050 as for ``faust_a`` / ``scape_a``;
- ``fs_train``: links to the F+S training shapes in both meshings (FAUST_r and faust_a
  tr_reg_000..069, scape_r and scape_a mesh000..040; anisotropic copies named ``<name>_a``):
  the folder ``torchfmap train --pairs all`` reads for the shipped ``humans`` model;
- ``fsh_train``: ``fs_train`` and the hard meshings of the same shapes (``<name>_h``);
- ``smal_train``: links to the 24 SMAL_r training animals of the ``smal_r`` recipe (every 4th
  sorted name validates instead, ``bench/pairs.py``'s ``smal_split``);
- ``smal_val``: links to the other 8 animals and their ground truth, with a ``test_pairs.txt``
  of 16 ordered pairs among them (``drawn_pairs``, seed 0): ``torchfmap eval bench/data/smal_val
  --checkpoint smal_r`` gives the figures of ``docs/models.md``;
- ``smal_ftrain``, ``smal_fval``: the split by species (``bench/pairs.py``'s
  ``smal_family_split``: the animals clustered into five shape families by their geodesic
  proportions; the two smallest families, hippos and cows, validate): links to the 23 training
  animals, and to the 9 validation animals with their ground truth and a ``test_pairs.txt`` of 40
  ordered pairs among them (seed 0).

Ground truth through a remesh: each old vertex goes to its nearest new vertex, so the carried
ground truth has an error of about half an edge, far below the errors measured.
The files are git-ignored (they are derived from data that must not be shipped).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bench.common import LOCAL_DATA_DIR, Skip, log
from bench.common import require_data as _require_data
from bench.pairs import SMAL_FVAL_PAIRS, drawn_pairs, smal_family_split, smal_split
from torchfmap.io import load_mesh, mesh_files, read_vts, save_mesh, shape_name
from torchfmap.remesh import remesh


def require_data(name: str) -> Path:
    """``../shared/data/<name>``, or exit with one line when it is absent."""
    try:
        return _require_data(name)
    except Skip as why:
        raise SystemExit(f"tools.remesh: {why}") from None


SETS = (
    "scape_r", "scape_a", "faust_a", "faust_h", "scape_h", "fs_train", "fsh_train", "smal_train", "smal_val",
    "smal_ftrain", "smal_fval",
)  # fmt: skip
#: Remeshing of the hard sets (``*_h``): ``remesh`` settings, and the range of vertex counts.
HARD = {"stretch": 5.0, "density": 4.0}
HARD_VERTICES = (3000, 10000)
#: Ordered validation pairs of ``smal_val`` (its test_pairs.txt).
SMAL_VAL_PAIRS = 16
#: Training shapes of the F+S recipe (the rest of each set validates): FAUST_r 000..069, SCAPE 000..040.
FAUST_TRAIN = [f"tr_reg_{i:03d}" for i in range(70)]
SCAPE_TRAIN = [f"mesh{i:03d}" for i in range(41)]
N_VERTICES = 5000


def _write(out: Path, name: str, mesh, vts0: np.ndarray) -> None:
    (out / "corres").mkdir(parents=True, exist_ok=True)
    save_mesh(mesh, out / f"{name}.off")
    np.savetxt(out / "corres" / f"{name}.vts", vts0 + 1, fmt="%d")


def make(set_name: str, out: Path, names=None) -> None:
    src = require_data("scape_train" if set_name.startswith("scape") else "faust_r_train")
    method = "isotropic" if set_name == "scape_r" else "anisotropic"
    hard = set_name.endswith("_h")
    folder = out / set_name
    # seeds follow a shape's place among all of the source's shapes, so a subset gets the same meshes
    files = [(i, f) for i, f in enumerate(mesh_files(src)) if names is None or shape_name(f) in names]
    for i, path in tqdm(files, desc=set_name):
        name = shape_name(path)
        if (folder / f"{name}.off").exists():
            continue
        mesh = load_mesh(path, allow_nonmanifold=True)
        if hard:
            n = int(np.random.default_rng(2000 + i).integers(HARD_VERTICES[0], HARD_VERTICES[1] + 1))
            res = remesh(mesh, n, method, seed=2000 + i, **HARD)
        else:
            res = remesh(mesh, N_VERTICES, method, seed=1000 + i)
        if set_name.startswith("scape"):
            old = np.arange(mesh.n_vertices)  # identity ground truth on the template
        else:
            old = read_vts(src / "corres" / f"{name}.vts")
        _write(folder, name, res.mesh, res.to_new[old])
    size = f"{HARD}, {HARD_VERTICES[0]}-{HARD_VERTICES[1]} vertices" if hard else f"~{N_VERTICES} vertices"
    (folder / "README.md").write_text(
        f"# {set_name}\n\nMade by `python -m tools.remesh --sets {set_name}` from "
        f"`../shared/data/{src.name}` ({method} remeshing, {size}, "
        "ground truth carried to the nearest new vertex). Same terms as the source; do not ship.\n"
    )
    log(f"{set_name}: {len(files)} shapes in {folder}")


def make_training_folder(out: Path, hard: bool = False) -> None:
    """``fs_train``: links to the F+S training shapes in both meshings (FAUST_r and faust_a
    000..069, scape_r and scape_a 000..040; the anisotropic copies named ``<name>_a``);
    ``fsh_train`` (``hard``): the same and the hard meshings of faust_h and scape_h (``<name>_h``)."""
    folder = out / ("fsh_train" if hard else "fs_train")
    folder.mkdir(parents=True, exist_ok=True)
    faust = require_data("faust_r_train")
    links = [(faust / f"{n}.off", n) for n in FAUST_TRAIN]
    links += [(out / "faust_a" / f"{n}.off", f"{n}_a") for n in FAUST_TRAIN]
    links += [(out / "scape_r" / f"{n}.off", n) for n in SCAPE_TRAIN]
    links += [(out / "scape_a" / f"{n}.off", f"{n}_a") for n in SCAPE_TRAIN]
    if hard:
        links += [(out / "faust_h" / f"{n}.off", f"{n}_h") for n in FAUST_TRAIN]
        links += [(out / "scape_h" / f"{n}.off", f"{n}_h") for n in SCAPE_TRAIN]
    for target, name in links:
        if not target.exists():
            raise SystemExit(f"{target} is missing: make the sets it links ({target.parent.name}) first")
        link = folder / f"{name}.off"
        if not link.exists():
            link.symlink_to(target.resolve())
    log(f"{folder.name}: {len(links)} shapes in {folder}")


def make_smal_training_folder(out: Path, by_family: bool = False) -> None:
    """``smal_train``: links to the 24 SMAL_r training animals of the ``smal_r`` recipe
    (``bench/pairs.py``'s ``smal_split``; the other 8 validate); ``smal_ftrain`` (``by_family``):
    the 23 of ``smal_family_split``."""
    folder = out / ("smal_ftrain" if by_family else "smal_train")
    folder.mkdir(parents=True, exist_ok=True)
    src = require_data("smal_r_train")
    train, _ = smal_family_split() if by_family else smal_split()
    for name in train:
        link = folder / f"{name}.off.gz"
        if not link.exists():
            link.symlink_to((src / f"{name}.off.gz").resolve())
    log(f"{folder.name}: {len(train)} shapes in {folder}")


def make_smal_validation_folder(out: Path, by_family: bool = False) -> None:
    """``smal_val``: links to the 8 held-out animals of ``smal_split`` and their ``.vts``, and a
    ``test_pairs.txt`` of ``SMAL_VAL_PAIRS`` ordered pairs drawn among them (seed 0);
    ``smal_fval`` (``by_family``): the 9 of ``smal_family_split`` and ``SMAL_FVAL_PAIRS`` pairs."""
    folder = out / ("smal_fval" if by_family else "smal_val")
    (folder / "corres").mkdir(parents=True, exist_ok=True)
    src = require_data("smal_r_train")
    _, val = smal_family_split() if by_family else smal_split()
    for name in val:
        for link, target in (
            (folder / f"{name}.off.gz", src / f"{name}.off.gz"),
            (folder / "corres" / f"{name}.vts", src / "corres" / f"{name}.vts"),
        ):
            if not link.exists():
                link.symlink_to(target.resolve())
    lines = [f"{a}\t{b}\n" for a, b in drawn_pairs(val, SMAL_FVAL_PAIRS if by_family else SMAL_VAL_PAIRS)]
    (folder / "test_pairs.txt").write_text("".join(lines))
    log(f"{folder.name}: {len(val)} shapes, {len(lines)} pairs in {folder}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--sets",
        type=lambda t: [s.strip() for s in t.split(",") if s.strip()],
        default=list(SETS),
        help=f"comma list of {', '.join(SETS)}",
    )
    p.add_argument("--out", default=str(LOCAL_DATA_DIR), help="output folder (default bench/data)")
    args = p.parse_args()
    for s in args.sets:
        if s not in SETS:
            raise SystemExit(f"unknown set {s!r}: one of {', '.join(SETS)}")
        if s in ("fs_train", "fsh_train"):
            make_training_folder(Path(args.out), hard=s == "fsh_train")
        elif s in ("smal_train", "smal_ftrain"):
            make_smal_training_folder(Path(args.out), by_family=s == "smal_ftrain")
        elif s in ("smal_val", "smal_fval"):
            make_smal_validation_folder(Path(args.out), by_family=s == "smal_fval")
        else:
            make(s, Path(args.out))


if __name__ == "__main__":
    main()
