"""Datasets over folders of meshes and pairs, an on-disk precompute cache, and collation.

The cache stores, per mesh and parameter set, the arrays a training loop needs (basis values,
lumped mass, spectral frame of ``W``, WKS input features). Entries are keyed by a SHA-256 of
the vertex and face arrays and the parameters; they are written atomically (temporary file,
fsync, rename), carry a checksum verified on every read, and a corrupted or truncated entry is
rebuilt. Two processes filling the same entry both write complete files; the last rename wins.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from .._files import load_arrays, save_arrays
from ..bases import laplacian_eigenbasis
from ..descriptors import wks
from ..errors import CorruptFileError, ParameterError
from ..io import load_mesh
from ..mesh import Mesh
from ..operators.laplacian import normalize_area
from .functional import BasisBatch
from .modules import basis_arrays

log = logging.getLogger(__name__)

#: Key of the checksum array in cache entries (kept from the first cache format).
CACHE_CHECKSUM_KEY = "__checksum__"


def mesh_key(mesh: Mesh, params: dict) -> str:
    """SHA-256 of the mesh arrays and the parameters (sorted JSON)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
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
        arrays = self.load(key)
        if arrays is None:
            arrays = compute()
            self.store(key, arrays)
        return arrays


def precompute_shape(mesh: Mesh, k: int = 50, n_wks: int = 32, k_wks: int = 100) -> dict[str, np.ndarray]:
    """Arrays for training: eigenbasis ``values (V, k)``, ``mass (V,)``, ``lam``, ``U``, ``wks (V, n_wks)``.

    The mesh is scaled to unit area first (learned diffusion times are then comparable).
    """
    unit = normalize_area(mesh)
    k_all = max(k, k_wks)
    full = laplacian_eigenbasis(unit, k_all)
    feats = wks(full.eigenvalues, full.values, n_wks)
    feats = (feats - feats.mean(axis=0)) / np.maximum(feats.std(axis=0), 1e-12)
    arrays = basis_arrays(full.truncated(k))
    arrays["wks"] = feats
    arrays["vertices"] = mesh.vertices
    arrays["faces"] = mesh.faces
    return arrays


class ShapeDataset(torch.utils.data.Dataset):
    """Meshes of a folder (or a list of files), precomputed through a :class:`PrecomputeCache`.

    Items are dicts of float tensors: ``values (V, K)``, ``mass (V,)``, ``lam (K,)``, ``U (K, K)``,
    ``wks (V, C)``, plus ``name`` and the ``index``.
    """

    def __init__(
        self,
        files,
        cache_dir: str | os.PathLike,
        *,
        k: int = 50,
        n_wks: int = 32,
        dtype: torch.dtype = torch.float32,
        rank: int = 0,
        world_size: int = 1,
        progress: bool = True,
    ) -> None:
        files = sorted(Path(files).glob("*.off")) if isinstance(files, (str, os.PathLike)) else list(files)
        if not files:
            raise ParameterError("no meshes found. Fix: point to a folder with .off files or pass a list.")
        self.files = [Path(f) for f in files]
        self.names = [f.name.split(".")[0] for f in self.files]
        self.cache = PrecomputeCache(cache_dir)
        self.params = {"k": k, "n_wks": n_wks, "version": 1}
        self.dtype = dtype
        self.precompute(rank, world_size, progress)

    def _compute(self, i: int) -> dict[str, np.ndarray]:
        mesh = load_mesh(self.files[i])
        key = mesh_key(mesh, self.params)
        return self.cache.get(key, lambda: precompute_shape(mesh, self.params["k"], self.params["n_wks"]))

    def precompute(self, rank: int = 0, world_size: int = 1, progress: bool = True) -> None:
        """Fill the cache; with several ranks each fills its share (then synchronise)."""
        mine = range(rank, len(self.files), world_size)
        for i in tqdm(mine, desc=f"precompute (rank {rank})", disable=not progress):
            self._compute(i)
        if world_size > 1 and torch.distributed.is_available() and torch.distributed.is_initialized():
            torch.distributed.barrier()

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, i: int) -> dict:
        arrays = self._compute(i)
        item = {
            k: torch.as_tensor(arrays[k], dtype=self.dtype) for k in ("values", "mass", "lam", "U", "wks")
        }
        item["vertices"] = torch.as_tensor(arrays["vertices"])
        item["faces"] = torch.as_tensor(arrays["faces"])
        item["name"] = self.names[i]
        item["index"] = i
        return item


class PairDataset(torch.utils.data.Dataset):
    """Pairs ``(x, y)`` of a :class:`ShapeDataset`: all ordered pairs, or the given index pairs."""

    def __init__(self, shapes: ShapeDataset, pairs=None) -> None:
        n = len(shapes)
        self.shapes = shapes
        self.pairs = [(i, j) for i in range(n) for j in range(n) if i != j] if pairs is None else list(pairs)

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, i: int) -> tuple[dict, dict]:
        a, b = self.pairs[i]
        return self.shapes[a], self.shapes[b]


def collate_shapes(items: list[dict]) -> tuple[BasisBatch, torch.Tensor, torch.Tensor]:
    """Pad shapes of different ``V`` and ``K``: ``(BasisBatch, features (B, V, C), lengths (B,))``.

    Padded vertices get zero mass and zero basis values; padded columns zero values, ``lam = 0``,
    an identity block in ``U`` and ``valid = 0``.
    """
    B = len(items)
    V = max(it["values"].shape[0] for it in items)
    K = max(it["values"].shape[1] for it in items)
    C = items[0]["wks"].shape[1]
    dtype = items[0]["values"].dtype
    values = torch.zeros(B, V, K, dtype=dtype)
    mass = torch.zeros(B, V, dtype=dtype)
    lam = torch.zeros(B, K, dtype=dtype)
    U = torch.eye(K, dtype=dtype).repeat(B, 1, 1)
    valid = torch.zeros(B, K, dtype=dtype)
    feats = torch.zeros(B, V, C, dtype=dtype)
    lengths = torch.zeros(B, dtype=torch.long)
    for b, it in enumerate(items):
        v, k = it["values"].shape
        values[b, :v, :k] = it["values"]
        mass[b, :v] = it["mass"]
        lam[b, :k] = it["lam"]
        U[b, :k, :k] = it["U"]
        valid[b, :k] = 1
        feats[b, :v] = it["wks"]
        lengths[b] = v
    return BasisBatch(values, mass, lam, U, valid), feats, lengths


def collate_pairs(batch: list[tuple[dict, dict]]) -> dict:
    """Collate ``(x, y)`` pairs into padded batches: ``{'x': (basis, feats, lengths), 'y': ..., 'names'}``."""
    xs, ys = zip(*batch, strict=True)
    return {
        "x": collate_shapes(list(xs)),
        "y": collate_shapes(list(ys)),
        "names": [(a["name"], b["name"]) for a, b in batch],
        "index": [(a["index"], b["index"]) for a, b in batch],
    }
