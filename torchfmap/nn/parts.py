"""Supervised training on parts: :class:`PartPairs` (cuts of a folder's whole shapes, each paired with every
whole, the ground truth carried from the wholes' ``.vts`` files through the cut) and :class:`PartLoss`
(the expected geodesic error of the features' soft map, part -> whole)."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..bases.prepared import prepare_shape
from ..data.cuts import cut_holes, cut_plane
from ..errors import MeshError, ParameterError
from ..io import find_file, read_vts
from ..matching.partial import shot_descriptors
from ..operators.geodesic import GeodesicSolver
from .data import ShapeDataset, collate_pairs, mesh_key
from .functional import geodesic_loss, soft_map
from .inputs import coordinates_on, has_shot, shape_arrays, shape_item
from .train import batch_score, forward_pair

#: Area ratios the parts are drawn in (uniformly): a hand alone up to most of the body.
PART_RATIOS = (0.1, 0.9)
#: Ground-truth rows kept per whole (template rows of the ``.vts`` files, drawn once): each pair supervises
#: the ones its part keeps, with their geodesic distance rows on the whole.
TRUTH_ROWS = 1024
#: Most holes of a holes cut (1 to this many, drawn).
MAX_HOLES = 4

__all__ = ["PART_RATIOS", "TRUTH_ROWS", "PartLoss", "PartPairs", "part_score"]


class PartPairs(torch.utils.data.Dataset):
    """``n_cuts`` parts of every whole shape of ``shapes`` (alternately a plane cut and 1 to
    :data:`MAX_HOLES` holes, area ratio drawn uniformly in ``ratios``, all from ``seed``), each paired
    with every whole: item ``k`` is ``(whole item, part item, truth)`` with ``truth`` holding ``rows (P,)``
    (part vertices) and ``dist (P, V_whole)`` (geodesic distances on the whole from their true matches,
    in units of ``sqrt(area)`` of the whole), for those of the ``truth_rows`` template rows (drawn once)
    that the part keeps; a part that keeps none is left out.

    A part's inputs are those of inference (:class:`~torchfmap.nn.LearnedMatcher` with ``partial=True``):
    SHOT at its whole's radius, coordinates in its whole's frame. Parts and distance rows are cached in
    ``shapes``' cache. ``corres``: a folder of ``<name>.vts`` files (1-based, rows corresponding across
    shapes), one per whole.

    Raises:
        ParameterError: ``n_cuts`` < 1, ``ratios`` not within ``[0.05, 1)``, fewer than 2 wholes, a
            missing ``.vts`` file or ``.vts`` files of different lengths."""

    def __init__(
        self,
        shapes: ShapeDataset,
        corres: str | os.PathLike,
        n_cuts: int,
        *,
        seed: int = 0,
        ratios: tuple[float, float] = PART_RATIOS,
        truth_rows: int = TRUTH_ROWS,
        progress: bool = True,
    ) -> None:
        if isinstance(n_cuts, bool) or not isinstance(n_cuts, int) or n_cuts < 1:
            raise ParameterError(f"n_cuts must be an integer >= 1, got {n_cuts!r}. Fix: e.g. 4 a shape.")
        lo, hi = (float(r) for r in ratios)
        if not 0.05 <= lo <= hi < 1:
            raise ParameterError(f"ratios must satisfy 0.05 <= lo <= hi < 1, got {ratios!r}.")
        if len(shapes) < 2:
            raise ParameterError("parts are matched to other wholes: give at least two whole shapes.")
        self.shapes, self.n_cuts = shapes, n_cuts
        vts = [_read_vts(corres, name) for name in shapes.names]
        if len({len(v) for v in vts}) != 1:
            raise ParameterError(
                f"the .vts files in {corres} have {sorted({len(v) for v in vts})} rows; rows must correspond "
                "across shapes (one template). Fix: the data set's own corres/ files."
            )
        rng = np.random.default_rng(seed)
        n_rows = len(vts[0])
        self.template_rows = np.sort(rng.choice(n_rows, min(truth_rows, n_rows), replace=False))
        meshes = [shapes.mesh(i) for i in range(len(shapes))]
        self.dist = [
            self._distance_rows(m, v[self.template_rows])
            for m, v in tqdm(list(zip(meshes, vts, strict=True)), desc="distance rows", disable=not progress)
        ]
        self.parts, self.truth, self.whole_of, self.part_vertices = [], [], [], []
        draws = [(i, c, rng.uniform(lo, hi), int(rng.integers(1, MAX_HOLES + 1)), int(rng.integers(2**31)))
                 for i in range(len(shapes)) for c in range(n_cuts)]  # fmt: skip
        # the whole being cut (draws go whole by whole), prepared once and only for parts not in the cache
        prepared_whole = functools.lru_cache(maxsize=1)(lambda i: prepare_shape(meshes[i], 0))
        for i, c, ratio, holes, cut_seed in tqdm(draws, desc="parts", disable=not progress):
            name, whole = f"{shapes.names[i]}-part{c}", functools.partial(prepared_whole, i)
            item, vertices = self._part(meshes[i], whole, name, c, ratio, holes, cut_seed)
            inverse = np.full(meshes[i].n_vertices, -1, dtype=np.int64)
            inverse[vertices] = np.arange(len(vertices))
            on_part = inverse[vts[i][self.template_rows]]  # (R,): part vertex of each kept template row
            kept = np.flatnonzero(on_part >= 0)
            if len(kept) == 0:
                continue
            item["index"] = len(self.parts)
            self.parts.append(item)
            self.truth.append((kept, on_part[kept]))
            self.whole_of.append(i)
            self.part_vertices.append(vertices)
        self.pairs = [(p, j) for p in range(len(self.parts)) for j in range(len(shapes))]

    def _distance_rows(self, mesh, sources: np.ndarray) -> np.ndarray:
        def compute() -> dict[str, np.ndarray]:
            unique, back = np.unique(sources, return_inverse=True)  # .vts rows may share a vertex
            d = GeodesicSolver(mesh).distances(unique)[back] / np.sqrt(mesh.area)
            return {"dist": np.maximum(d, 0.0).astype(np.float32)}

        params, cache = {"truth_rows": sources.tolist(), "version": 1}, self.shapes.cache
        arrays = compute() if cache is None else cache.get(mesh_key(mesh, params), compute)
        return arrays["dist"]

    def _part(self, mesh, whole, name: str, c: int, ratio: float, holes: int, cut_seed: int):
        """``(item, vertices)``: the part's dataset item and its vertices on the whole ``mesh``
        (``whole()``: its prepared shape)."""
        p = self.shapes.params
        kind = "plane" if c % 2 == 0 else "holes"
        try:
            cut = cut_plane(mesh, ratio, seed=cut_seed) if kind == "plane" else (
                cut_holes(mesh, ratio, holes, seed=cut_seed))  # fmt: skip
        except MeshError as err:
            raise MeshError(f"cutting {name} ({kind}, ratio {ratio:.2f}) failed: {err}") from None

        def compute() -> dict[str, np.ndarray]:
            k_all = max(p["k"], p["k_net"])
            part = prepare_shape(cut.mesh, min(k_all, cut.mesh.n_vertices - 1))
            arrays = shape_arrays(part, p["k"], p["n_wks"], k_net=p["k_net"], basis=p["basis"])
            arrays["xyz"] = coordinates_on(part.mesh, whole())
            if has_shot(self.shapes.inputs):
                arrays["shot"] = shot_descriptors(part, whole())
            arrays["vertices_on_whole"] = cut.vertices
            return arrays

        key = mesh_key(cut.mesh, {**p, "part_of_area": float(mesh.area), "version": 1})
        cache = self.shapes.cache
        arrays = compute() if cache is None else cache.get(key, compute)
        item = shape_item(arrays, self.shapes.inputs, self.shapes.dtype, name, 0)
        return item, np.asarray(arrays["vertices_on_whole"], dtype=np.int64)

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, k: int) -> tuple[dict, dict, dict]:
        p, j = self.pairs[k]
        rows, on_part = self.truth[p]
        truth = {"rows": torch.as_tensor(on_part), "dist": torch.as_tensor(self.dist[j][rows])}
        return self.shapes[j], self.parts[p], truth

    def collate(self, batch: list) -> dict:
        """:func:`~torchfmap.nn.data.collate_pairs` of (whole, part) with ``'truth'``: ``rows (B, P)``,
        ``dist (B, P, V)`` (padded rows: part vertex 0 at distance 0 everywhere, so they add nothing)."""
        out = collate_pairs([(x, y) for x, y, _ in batch])
        P = max(len(t["rows"]) for _, _, t in batch)
        V = out["x"].basis.values.shape[1]
        rows = torch.zeros(len(batch), P, dtype=torch.int64)
        dist = torch.zeros(len(batch), P, V, dtype=batch[0][2]["dist"].dtype)
        for b, (_, _, t) in enumerate(batch):
            n, v = t["dist"].shape
            rows[b, :n], dist[b, :n, :v] = t["rows"], t["dist"]
        return {**out, "truth": {"rows": rows, "dist": dist}}


def _read_vts(corres, name: str) -> np.ndarray:
    path = find_file(Path(corres), f"{name}.vts")
    if path is None:
        raise ParameterError(
            f"no ground truth {Path(corres) / (name + '.vts')}: training on parts is supervised. Fix: a "
            "corres/ folder of <name>.vts files beside the meshes (FAUST_r, SCAPE_r layouts)."
        )
    return read_vts(path)


class PartLoss(torch.nn.Module):
    """The expected geodesic error of the features' soft map from the part (``y``) to the whole (``x``) at
    the ground-truth rows of a :meth:`PartPairs.collate` batch (:func:`~torchfmap.nn.functional.soft_map`
    at ``tau``, :func:`~torchfmap.nn.functional.geodesic_loss`), in units of ``sqrt(area)`` of the whole:
    an :class:`~torchfmap.nn.train.ExtraLoss` returning ``{'total': weight * error, 'error': error}``.

    Raises:
        ParameterError: ``tau`` or ``weight`` not finite and > 0, or (called) a batch without ``'truth'``."""

    name = "part"

    def __init__(self, tau: float = 0.07, weight: float = 1.0) -> None:
        super().__init__()
        for what, v in (("tau", tau), ("weight", weight)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < float("inf"):
                raise ParameterError(f"{what} must be finite and > 0, got {v!r}.")
        self.tau, self.weight = float(tau), float(weight)

    def forward(self, out, batch: dict, *, solver=None, loss_fn=None, generator=None) -> dict:
        if "truth" not in batch:
            raise ParameterError(
                "PartLoss needs the ground truth of a PartPairs batch ('truth'). Fix: a DataLoader over "
                "PartPairs with collate_fn=parts.collate."
            )
        device = out.feat_y.device
        rows, dist = batch["truth"]["rows"].to(device), batch["truth"]["dist"].to(out.feat_x)
        picked = torch.gather(out.feat_y, 1, rows[..., None].expand(-1, -1, out.feat_y.shape[-1]))
        pi = soft_map(out.feat_x, picked, tau=self.tau, lengths_x=batch["x"].basis.lengths)  # (B, P, V_x)
        order = torch.arange(rows.shape[1], device=device).expand(rows.shape[0], -1)
        error = geodesic_loss(pi, order, dist)
        return {"total": self.weight * error, "error": error}


def part_score(data: PartPairs, pairs, loss: PartLoss, solver, device: str | torch.device = "cpu"):
    """``score(net) -> float``: the mean :class:`PartLoss` error (eval mode) on the items ``pairs`` of
    ``data``; lower is better."""
    batches = [data.collate([data[k]]) for k in pairs]

    def value(net, batch: dict) -> torch.Tensor:
        return loss(forward_pair(net, solver, batch), batch)["error"]

    return batch_score(batches, value, device)
