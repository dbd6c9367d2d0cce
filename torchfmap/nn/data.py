"""Datasets of meshes and pairs, collation, and an on-disk precompute cache (entries keyed by a SHA-256 of
the mesh and parameters, written atomically, checksummed; a corrupted entry is rebuilt)."""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from tqdm import tqdm

from .._util.files import load_arrays, save_arrays
from ..errors import CorruptFileError, ParameterError
from ..fmap.defaults import DEFAULT_K
from ..io import load_mesh, mesh_files
from ..kinds import learned_kind
from ..mesh import Mesh
from .functional import BasisBatch, GradientBatch
from .inputs import INPUTS, has_shot, shape_arrays, shape_item

log = logging.getLogger(__name__)

#: Key of the checksum array in cache entries (kept from the first cache format).
CACHE_CHECKSUM_KEY = "__checksum__"


def mesh_key(mesh: Mesh, params: dict) -> str:
    """SHA-256 of the mesh arrays and the parameters (sorted JSON)."""
    h = hashlib.sha256(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    h.update(json.dumps(params, sort_keys=True).encode())
    return h.hexdigest()


class PrecomputeCache:
    """A folder of verified ``.npz`` entries; :meth:`get` computes and stores on a miss."""

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)

    def path(self, key: str) -> Path:
        return self.folder / f"{key}.npz"

    def load(self, key: str) -> dict[str, np.ndarray] | None:
        """The entry, or None if missing, unreadable or failing its checksum."""
        path = self.path(key)
        try:
            return load_arrays(path, CACHE_CHECKSUM_KEY, what="cache entry")
        except FileNotFoundError:
            return None
        except CorruptFileError as err:  # truncated zip, bad header, missing or wrong checksum...
            log.warning("cache entry %s unusable (%s): rebuilding", path.name, err)
            return None

    def store(self, key: str, arrays: dict[str, np.ndarray]) -> None:
        save_arrays(self.path(key), arrays, CACHE_CHECKSUM_KEY)

    def get(self, key: str, compute) -> dict[str, np.ndarray]:
        """The entry of ``key``, else ``compute()``, stored if the folder takes it."""
        arrays = self.load(key)
        if arrays is None:
            arrays = compute()
            try:
                self.folder.mkdir(parents=True, exist_ok=True)
                self.store(key, arrays)
            except OSError as err:
                log.warning(
                    "cache folder %s cannot store %s (%s): computed without the cache", self.folder, key, err
                )
        return arrays


def default_cache_dir() -> Path:
    """The per-user cache folder: ``$XDG_CACHE_HOME/torchfmap`` or ``~/.cache/torchfmap``."""
    root = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(root) / "torchfmap"


class ShapeDataset(torch.utils.data.Dataset):
    """Meshes of a folder (or files), precomputed (:func:`~torchfmap.nn.inputs.shape_arrays`, cached in
    ``cache_dir``: None the default folder, ``False`` none) and held in memory; ``inputs``: one of
    :data:`~torchfmap.nn.inputs.INPUTS`. Items are dicts of tensors (floats in ``dtype``): solver basis
    ``values (V, K)``, ``mass (V,)``, ``lam (K,)``, ``U (K, K)``; network basis ``net_values (V, K_net)``,
    ``net_lam``, ``net_U``; ``inputs (V, C)``; gradient ``grad_rows``, ``grad_cols``, ``grad_order_t``
    (int64), ``grad_x``, ``grad_y`` ``(E,)``; ``xyz (V, 3)``; ``vertices``, ``faces``, ``name``, ``index``."""

    def __init__(
        self,
        files,
        cache_dir: str | os.PathLike | None | bool = None,
        *,
        k: int = DEFAULT_K,
        n_wks: int = 32,
        k_net: int = 0,
        basis: str = "laplacian",
        inputs: str = "wks",
        dtype: torch.dtype = torch.float32,
        rank: int = 0,
        world_size: int = 1,
        progress: bool = True,
    ) -> None:
        files = mesh_files(files) if isinstance(files, (str, os.PathLike)) else list(files)
        if not files:
            raise ParameterError(
                "no meshes found. Fix: point to a folder of .off/.ply/.obj/.stl (.gz) files."
            )
        if inputs not in INPUTS:
            raise ParameterError(f"unknown inputs {inputs!r}. Fix: one of {', '.join(INPUTS)}.")
        learned_kind(basis)  # refuses an unknown or classical-only kind (torchfmap.bases.KINDS)
        self.files = [Path(f) for f in files]
        self.names = [f.name.split(".")[0] for f in self.files]
        self.cache = _open_cache(default_cache_dir() if cache_dir is None else cache_dir)
        self.params = {"k": k, "n_wks": n_wks, "k_net": k_net, "basis": basis, "version": 4}
        if has_shot(inputs):  # keys of the other inputs' entries stay as they were
            self.params["shot"] = True
        self.inputs, self.dtype = inputs, dtype
        self.items: list[dict | None] = [None] * len(self.files)
        self.precompute(rank, world_size, progress)

    def _compute(self, i: int) -> dict[str, np.ndarray]:
        mesh, p = load_mesh(self.files[i]), self.params

        def compute():
            return shape_arrays(
                mesh, p["k"], p["n_wks"], k_net=p["k_net"], basis=p["basis"], shot="shot" in p
            )

        return compute() if self.cache is None else self.cache.get(mesh_key(mesh, p), compute)

    def _item(self, i: int, arrays: dict[str, np.ndarray]) -> dict:
        return shape_item(arrays, self.inputs, self.dtype, self.names[i], i)

    def precompute(self, rank: int = 0, world_size: int = 1, progress: bool = True) -> None:
        """Fill the cache (ranks each their share, then synchronise) and load every mesh once."""
        if world_size > 1 and self.cache is not None:
            for i in tqdm(range(rank, len(self.files), world_size), desc="precompute", disable=not progress):
                self._compute(i)
            if torch.distributed.is_available() and torch.distributed.is_initialized():
                torch.distributed.barrier()
        for i in tqdm(range(len(self.files)), desc="load shapes", disable=not progress or rank != 0):
            self.items[i] = self._item(i, self._compute(i))

    def __len__(self) -> int:
        return len(self.files)

    def mesh(self, i: int) -> Mesh:
        """Shape ``i`` as a :class:`~torchfmap.Mesh` (its stored vertices and faces)."""
        item = self[i]
        return Mesh(item["vertices"].numpy(), item["faces"].numpy(), validate=False)

    def __getitem__(self, i: int) -> dict:
        return self.items[i]


def _open_cache(folder) -> PrecomputeCache | None:
    """A cache in ``folder``; ``False`` or an unusable folder gives None (no cache)."""
    if folder is False:
        return None
    try:
        cache = PrecomputeCache(folder)
        probe = cache.folder / f".probe.{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
        return cache
    except OSError as err:
        log.warning("cache folder %s is not writable (%s): computing without a cache", folder, err)
        return None


def class_pairs(names: list[str], within: bool = True) -> list[tuple[int, int]]:
    """Ordered pairs within classes (names alike but for trailing digits and ``_-``); all ordered pairs
    with ``within=False`` or if no class has two."""
    kind = [n.rstrip("0123456789").rstrip("_-") for n in names]
    every = [(i, j) for i in range(len(names)) for j in range(len(names)) if i != j]
    return ([(i, j) for i, j in every if kind[i] == kind[j]] or every) if within else every


class PairDataset(torch.utils.data.Dataset):
    """Pairs ``(x, y)`` of a :class:`ShapeDataset`: all ordered pairs, or the given index pairs."""

    def __init__(self, shapes: ShapeDataset, pairs=None) -> None:
        """Raises :class:`ParameterError` when there is no pair or a pair indexes outside the shapes."""
        n, self.shapes = len(shapes), shapes
        self.pairs = [(i, j) for i in range(n) for j in range(n) if i != j] if pairs is None else list(pairs)
        if not self.pairs:
            raise ParameterError(
                f"no pair of shapes to train on ({n} mesh{'es' if n != 1 else ''}"
                f"{': ' + ', '.join(shapes.names) if 0 < n <= 3 else ''}). Fix: give a folder with "
                "at least two meshes (pairs are formed within classes, e.g. cat0, cat1)."
            )
        bad = [p for p in self.pairs if len(p) != 2 or not all(0 <= int(i) < n for i in p)]
        if bad:
            raise ParameterError(f"pairs {bad[:3]} index outside the {n} shapes. Fix: indices in [0, {n}).")

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, i: int) -> tuple[dict, dict]:
        a, b = self.pairs[i]
        return self.shapes[a], self.shapes[b]


class ShapeBatch(NamedTuple):
    """A padded batch of shapes (:func:`collate_shapes`): solver ``basis`` ``(B, V, K)``,
    ``inputs (B, V, C)``, ``net_basis`` ``(B, V, K_net)`` (else the solver basis), ``grad`` and
    ``xyz (B, V, 3)`` (or None). Padding is ``basis.lengths`` and each basis' ``valid``; padded inputs are
    zero, padded gradient weights 0."""

    basis: BasisBatch
    inputs: torch.Tensor
    net_basis: BasisBatch
    grad: GradientBatch | None
    xyz: torch.Tensor | None

    @property
    def lengths(self) -> torch.Tensor:
        """``(B,)`` int64 vertex counts (``basis.lengths``, or ``V`` each when none is padded)."""
        if self.basis.lengths is not None:
            return self.basis.lengths
        B, V = self.basis.values.shape[:2]
        return torch.full((B,), V, dtype=torch.int64, device=self.basis.values.device)

    def to(self, *args, **kwargs) -> ShapeBatch:
        """Floats follow ``.to(dtype/device)``; lengths and indices only move device."""
        basis = self.basis.to(*args, **kwargs)
        net = basis if self.net_basis is self.basis else self.net_basis.to(*args, **kwargs)
        grad, xyz = (None if t is None else t.to(*args, **kwargs) for t in (self.grad, self.xyz))
        return ShapeBatch(basis, self.inputs.to(*args, **kwargs), net, grad, xyz)


def _pad(tensors: list[torch.Tensor], fill: float = 0.0) -> torch.Tensor:
    """Stack tensors of different sizes, padding every dimension at the end with ``fill``."""
    shape = [max(t.shape[d] for t in tensors) for d in range(tensors[0].dim())]
    out = torch.full((len(tensors), *shape), fill, dtype=tensors[0].dtype)
    for b, t in enumerate(tensors):
        out[(b, *(slice(0, n) for n in t.shape))] = t
    return out


def _basis_batch(items: list[dict], prefix: str, lengths: torch.Tensor | None) -> BasisBatch:
    values = _pad([it[f"{prefix}values"] for it in items])
    K = values.shape[-1]
    U = torch.eye(K, dtype=values.dtype).repeat(len(items), 1, 1)
    valid = torch.zeros(len(items), K, dtype=values.dtype)
    for b, it in enumerate(items):
        k = it[f"{prefix}values"].shape[1]
        U[b, :k, :k] = it[f"{prefix}U"]
        valid[b, :k] = 1
    mass = _pad([it["mass"] for it in items])
    return BasisBatch(values, mass, _pad([it[f"{prefix}lam"] for it in items]), U, valid, lengths)


def collate_shapes(items: list[dict]) -> ShapeBatch:
    """Pad shapes of different ``V`` and ``K`` into a :class:`ShapeBatch`; items need ``values``, ``mass``,
    ``lam``, ``U`` and ``inputs`` (or ``wks``), optionally ``net_*``, ``grad_*``, ``xyz``."""
    counts = [it["values"].shape[0] for it in items]
    lengths = None if len(set(counts)) == 1 else torch.tensor(counts, dtype=torch.int64)
    basis = _basis_batch(items, "", lengths)
    net = _basis_batch(items, "net_", lengths) if all("net_values" in it for it in items) else basis
    inputs = _pad([it["inputs"] if "inputs" in it else it["wks"] for it in items])
    grad = None
    if all("grad_rows" in it for it in items):
        # padded edges point at the last (padded) vertex with weight 0, so every shape's edges
        # stay sorted by (row, col) and by (col, row) through order_t
        last, order_t = max(counts) - 1, None
        if all("grad_order_t" in it for it in items):
            E = max(len(it["grad_order_t"]) for it in items)
            order_t = torch.arange(E).repeat(len(items), 1)
            for b, it in enumerate(items):
                order_t[b, : len(it["grad_order_t"])] = it["grad_order_t"]
        rows, cols = (_pad([it[key] for it in items], last) for key in ("grad_rows", "grad_cols"))
        wx, wy = (_pad([it[key] for it in items]) for key in ("grad_x", "grad_y"))
        grad = GradientBatch(rows, cols, wx, wy, order_t)
    xyz = _pad([it["xyz"] for it in items]) if all("xyz" in it for it in items) else None
    return ShapeBatch(basis, inputs, net, grad, xyz)


def collate_pairs(batch: list[tuple[dict, dict]]) -> dict:
    """Collate ``(x, y)`` pairs: ``{'x': ShapeBatch, 'y': ShapeBatch, 'names': [...], 'index': [...]}``."""
    xs, ys = zip(*batch, strict=True)
    names, index = [(a["name"], b["name"]) for a, b in batch], [(a["index"], b["index"]) for a, b in batch]
    return {"x": collate_shapes(list(xs)), "y": collate_shapes(list(ys)), "names": names, "index": index}
