"""The :class:`Basis` result type: ``(V, K)`` values, the mesh's mass matrix, the provenance of
every input column (kept or dropped by orthonormalisation), save/load."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .._util.checks import check_count
from .._util.files import load_arrays, save_arrays
from ..errors import CorruptFileError, ParameterError

_FORMAT_VERSION = 1


@dataclass(frozen=True)
class Column:
    """Where a basis column comes from: ``family`` (``'diffusion'``, ``'harmonic'``, ``'laplacian'``
    or ``'custom'``), ``seed`` vertex, relative diffusion ``time`` (absolute ``t * |M|``),
    eigenfunction ``index`` (``-1``/None: none); ``kept``: survived orthonormalisation."""

    family: str
    seed: int = -1
    time: float | None = None
    index: int = -1
    kept: bool = True

    def label(self) -> str:
        if self.family == "diffusion":
            return f"diffusion(seed={self.seed}, t={self.time:g})"
        if self.family == "harmonic":
            return f"harmonic(seed={self.seed})"
        if self.family == "laplacian":
            return f"laplacian({self.index})"
        return self.family


class Basis:
    """A set of functions on a mesh: ``values`` ``(V, K)``; ``mass`` ``(V, V)`` sparse (or ``(V,)``
    lumped); ``provenance``: one :class:`Column` per input column, ``K`` of them ``kept``;
    ``orthonormal``: ``values.T @ mass @ values == I``; optional ``stiffness`` ``(V, V)`` and
    ``eigenvalues`` ``(K,)``."""

    def __init__(
        self,
        values: np.ndarray,
        mass,
        provenance: list[Column] | None = None,
        orthonormal: bool = False,
        stiffness=None,
        eigenvalues: np.ndarray | None = None,
    ) -> None:
        values = np.asarray(values, dtype=np.float64)
        if values.ndim != 2:
            raise ParameterError(f"basis values must be (V, K), got shape {values.shape}.")
        mass = sp.diags(np.asarray(mass, dtype=np.float64)) if np.ndim(mass) == 1 else mass
        mass = sp.csr_matrix(mass, dtype=np.float64)
        if mass.shape != (values.shape[0],) * 2:
            raise ParameterError(
                f"mass is {mass.shape} but the basis has {values.shape[0]} vertices. Fix: use the "
                "mass matrix of the same mesh."
            )
        if provenance is None:
            provenance = [Column("custom") for _ in range(values.shape[1])]
        if sum(c.kept for c in provenance) != values.shape[1]:
            raise ParameterError(
                f"provenance lists {sum(c.kept for c in provenance)} kept columns, values has "
                f"{values.shape[1]}."
            )
        self.values = values
        self.mass = mass
        self.provenance = list(provenance)
        self.orthonormal = orthonormal
        self.stiffness = None if stiffness is None else sp.csr_matrix(stiffness, dtype=np.float64)
        self.eigenvalues = None if eigenvalues is None else np.asarray(eigenvalues, dtype=np.float64)
        #: ``(n, 2)`` landmark pairs ``(source, target)`` this basis was built from with its
        #: partner, or None (saved with the basis).
        self.pair_landmarks: np.ndarray | None = None

    @property
    def n_vertices(self) -> int:
        return self.values.shape[0]

    @property
    def k(self) -> int:
        """Number of (kept) basis functions ``K``."""
        return self.values.shape[1]

    @property
    def columns(self) -> list[Column]:
        """Provenance of the kept columns, in the order of :attr:`values`."""
        return [c for c in self.provenance if c.kept]

    @property
    def dropped(self) -> list[Column]:
        """Provenance of the input columns removed as numerically dependent."""
        return [c for c in self.provenance if not c.kept]

    def families(self) -> np.ndarray:
        """``(K,)`` function family of each kept column (:attr:`Column.family`)."""
        return np.array([c.family for c in self.columns])

    def __repr__(self) -> str:
        counts = {}
        for c in self.columns:
            counts[c.family] = counts.get(c.family, 0) + 1
        parts = ", ".join(f"{n} {family}" for family, n in counts.items())
        return (
            f"Basis(V={self.n_vertices}, K={self.k}: {parts}; dropped {len(self.dropped)}; "
            f"orthonormal={self.orthonormal})"
        )

    def gram(self) -> np.ndarray:
        """``(K, K)`` Gram matrix ``Φᵀ B Φ`` (the identity for an orthonormal basis)."""
        return self.values.T @ (self.mass @ self.values)

    def project(self, f: np.ndarray) -> np.ndarray:
        """Coefficients ``Φᵀ B f``: ``(V,)`` -> ``(K,)`` or ``(V, D)`` -> ``(K, D)`` (the best
        approximation's only when B-orthonormal; else :meth:`least_squares`)."""
        f = np.asarray(f, dtype=np.float64)
        if f.shape[0] != self.n_vertices:
            raise ParameterError(f"f has {f.shape[0]} rows, the basis has {self.n_vertices} vertices.")
        return self.values.T @ (self.mass @ f)

    def least_squares(self, f: np.ndarray) -> np.ndarray:
        """B-weighted least-squares coefficients for any (not necessarily orthonormal) basis."""
        return np.linalg.lstsq(self.gram(), self.project(f), rcond=None)[0]

    def reconstruct(self, coeffs: np.ndarray) -> np.ndarray:
        """``Φ c``: ``(K,)`` -> ``(V,)`` or ``(K, D)`` -> ``(V, D)``."""
        coeffs = np.asarray(coeffs, dtype=np.float64)
        if coeffs.shape[0] != self.k:
            raise ParameterError(f"coeffs has {coeffs.shape[0]} rows, the basis has K={self.k}.")
        return self.values @ coeffs

    def projected_laplacian(self) -> np.ndarray:
        """``(K, K)`` ``W = Φᵀ L Φ`` (diagonal eigenvalues for an eigenbasis, full otherwise)."""
        if self.stiffness is None:
            raise ParameterError("this basis has no stiffness matrix. Fix: build it with `stiffness=L`.")
        return self.values.T @ (self.stiffness @ self.values)

    def truncated(self, k: int) -> Basis:
        """The first ``k`` columns as a new :class:`Basis` (mass, stiffness, flags and the
        provenance up to them kept). Raises :class:`ParameterError` unless ``1 <= k <= K``."""
        k = check_count(k, 1, self.k, "k (columns kept)")
        prov, kept = [], 0
        for c in self.provenance:
            if kept == k:
                break
            prov.append(c)
            kept += c.kept
        eig = None if self.eigenvalues is None else self.eigenvalues[:k]
        return Basis(self.values[:, :k], self.mass, prov, self.orthonormal, self.stiffness, eig)

    def support(self, eps: float = 1e-3, weighted: bool = False) -> np.ndarray:
        """``(K,)`` support fraction of each column; see :func:`support_fraction`."""
        return support_fraction(self.values, eps=eps, mass=self.mass if weighted else None)

    def save(self, path: str | os.PathLike) -> Path:
        """Write to ``.npz`` atomically (temp file + rename) with a checksum verified on load."""
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(path.suffix + ".npz") if path.suffix else path.with_suffix(".npz")
        mass = self.mass.tocoo()
        arrays = {
            "values": self.values,
            "mass_row": mass.row.astype(np.int64),
            "mass_col": mass.col.astype(np.int64),
            "mass_data": mass.data,
            "prov_kind": np.array([c.family for c in self.provenance], dtype=str),  # the file's key
            "prov_seed": np.array([c.seed for c in self.provenance], dtype=np.int64),
            "prov_time": np.array(
                [np.nan if c.time is None else c.time for c in self.provenance], dtype=np.float64
            ),
            "prov_index": np.array([c.index for c in self.provenance], dtype=np.int64),
            "prov_kept": np.array([c.kept for c in self.provenance], dtype=bool),
            "orthonormal": np.array(self.orthonormal),
            "version": np.array(_FORMAT_VERSION),
        }
        if self.stiffness is not None:
            stiff = self.stiffness.tocoo()
            arrays.update(
                stiff_row=stiff.row.astype(np.int64),
                stiff_col=stiff.col.astype(np.int64),
                stiff_data=stiff.data,
            )
        if self.eigenvalues is not None:
            arrays["eigenvalues"] = self.eigenvalues
        if self.pair_landmarks is not None:
            arrays["pair_landmarks"] = np.asarray(self.pair_landmarks, dtype=np.int64).reshape(-1, 2)
        save_arrays(path, arrays)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> Basis:
        """Read a basis written by :meth:`save`. Raises FileReadError (no such file, a folder, no
        permission) or CorruptFileError (altered or truncated, or not a basis of this format)."""
        arrays = load_arrays(path, what="basis file")
        try:
            return cls._from_arrays(arrays)
        except (KeyError, ValueError, IndexError, TypeError) as err:
            problem = f"no {err} array" if isinstance(err, KeyError) else str(err)
            raise CorruptFileError(
                f"{path} is not a basis torchfmap can read ({problem}). Fix: save the basis again "
                "with Basis.save (or rebuild it)."
            ) from None

    @classmethod
    def _from_arrays(cls, arrays: dict[str, np.ndarray]) -> Basis:
        version = int(arrays["version"])
        if version != _FORMAT_VERSION:
            raise ValueError(f"format version {version}, this torchfmap reads {_FORMAT_VERSION}")
        values = arrays["values"]
        if values.ndim != 2 or not np.issubdtype(values.dtype, np.floating) or not np.isfinite(values).all():
            raise ValueError(f"values of shape {values.shape} and dtype {values.dtype}, or not finite")
        n = values.shape[0]

        def matrix(prefix: str) -> sp.csr_matrix:
            row, col, data = (arrays[f"{prefix}_{part}"] for part in ("row", "col", "data"))
            if not (len(row) == len(col) == len(data)) or (
                len(row) and (min(row.min(), col.min()) < 0 or max(row.max(), col.max()) >= n)
            ):
                raise ValueError(f"{prefix} entries of unequal lengths or outside the {n} vertices")
            return sp.csr_matrix((data, (row, col)), shape=(n, n))  # fmt: skip

        mass = matrix("mass")
        stiffness = matrix("stiff") if "stiff_data" in arrays else None
        fields = (arrays[f"prov_{name}"] for name in ("kind", "seed", "time", "index", "kept"))
        prov = [
            Column(str(k), int(s), None if np.isnan(t) else float(t), int(i), bool(kept))
            for k, s, t, i, kept in zip(*fields, strict=True)
        ]
        basis = cls(values, mass, prov, bool(arrays["orthonormal"]), stiffness, arrays.get("eigenvalues"))
        basis.pair_landmarks = arrays.get("pair_landmarks")
        return basis


def support_fraction(values: np.ndarray, eps: float = 1e-3, mass=None) -> np.ndarray:
    """``(K,)`` fraction in ``[0, 1]`` of the surface where ``|f| > eps * max|f|``, per column of
    ``values (V, K)`` (a scalar for ``(V,)``); with ``mass`` ``(V, V)``: area-weighted."""
    f = np.abs(np.asarray(values, dtype=np.float64))
    single = f.ndim == 1
    f = f[:, None] if single else f
    inside = f > eps * f.max(axis=0, keepdims=True)
    if mass is None:
        frac = inside.mean(axis=0)
    else:
        areas = np.asarray(sp.csr_matrix(mass).sum(axis=1)).ravel()
        frac = (areas @ inside) / areas.sum()
    return frac[0] if single else frac
