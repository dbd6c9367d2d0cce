"""Shared fixtures: small analytic meshes and the real data beside the project (skip if absent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from torchfmap import Mesh
from torchfmap.data import icosphere, make_demo_pair

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def data_path(*parts: str) -> Path:
    """Path under ``../shared/data``; skips the test when it is missing."""
    path = DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data not present: {path}")
    return path


def bumpy_blob(subdivisions: int) -> Mesh:
    """The demo blob (an asymmetric bumpy ellipsoid) at ``10 * 4**s + 2`` vertices: the first
    mesh of :func:`torchfmap.data.make_demo_pair`."""
    return make_demo_pair(subdivisions)[0]


def bend(vertices: np.ndarray, strength: float) -> np.ndarray:
    """Bend along x around the z axis (radius ``1/strength``): near-isometric and non-rigid, so
    a bent copy keeps the connectivity and has the identity as ground truth."""
    radius = 1.0 / strength
    theta = vertices[:, 0] / radius
    rr = radius - vertices[:, 1]
    return np.stack([rr * np.sin(theta), radius - rr * np.cos(theta), vertices[:, 2]], axis=1)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


@pytest.fixture(autouse=True)
def _seed_random_generators():
    """Every test starts from the same torch random state, so failures reproduce.

    (numpy randomness in the tests and the library goes through seeded ``default_rng``.)
    """
    try:
        import torch
    except ImportError:  # pragma: no cover - torch is a dependency
        return
    torch.manual_seed(0)


def smallest_eigenvalues(L, B, k: int) -> np.ndarray:
    """The ``k`` smallest generalised eigenvalues of ``L x = λ B x``, ascending.

    Dense (exact) up to 3000 vertices; beyond, ARPACK shift-invert from a fixed start vector
    with 8 extra eigenpairs, so a degenerate cluster at the end of the range is not cut short
    (ARPACK from a random start can miss copies of a multiple eigenvalue).
    """
    import scipy.linalg as dla
    import scipy.sparse.linalg as sla

    n = L.shape[0]
    if n <= 3000:
        return dla.eigh(L.toarray(), B.toarray(), eigvals_only=True, subset_by_index=(0, k - 1))
    m = min(k + 8, n - 2)
    v0 = np.random.default_rng(0).standard_normal(n)
    vals = sla.eigsh(
        L.tocsc(),
        k=m,
        M=B.tocsc(),
        sigma=-1e-8,
        which="LM",
        v0=v0,
        ncv=min(n - 1, max(2 * m + 1, 40)),
        return_eigenvectors=False,
    )
    return np.sort(vals)[:k]


@pytest.fixture(scope="session")
def sphere2() -> Mesh:
    return icosphere(2)


@pytest.fixture(scope="session")
def sphere3() -> Mesh:
    return icosphere(3)


@pytest.fixture(scope="session")
def blob() -> Mesh:
    """An irregular closed mesh: the demo blob at 642 vertices, with jitter."""
    m = bumpy_blob(3)
    rng = np.random.default_rng(1)
    return m.copy(m.vertices + 0.01 * rng.normal(size=m.vertices.shape))


@pytest.fixture()
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def planar_grid(n: int = 8, jitter: float = 0.2, seed: int = 0) -> Mesh:
    """A jittered planar ``n x n`` grid in z = 0, split into triangles."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    interior = (v[:, 0] > 0) & (v[:, 0] < n - 1) & (v[:, 1] > 0) & (v[:, 1] < n - 1)
    v[interior, :2] += jitter * rng.uniform(-1, 1, size=(interior.sum(), 2))
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return Mesh(v, faces)


def make_bent_pair(strength: float = 0.3, seed: int = 2):
    """``(x, y, gt)``: the bumpy blob ``x`` (642 vertices), ``y`` the same surface bent and its
    vertices shuffled, and the ground truth ``Correspondence`` (vertex ``v`` of ``y`` is
    ``gt.idx_x[v]`` of ``x``)."""
    from torchfmap.eval import Correspondence

    x = bumpy_blob(3)
    perm = np.random.default_rng(seed).permutation(x.n_vertices)
    y = x.copy(bend(x.vertices, strength)).permuted(perm)
    return x, y, Correspondence(idx_x=perm, idx_y=np.arange(y.n_vertices))


@pytest.fixture(scope="session")
def bent_pair():
    """:func:`make_bent_pair` with its defaults (shared by the tests of matching)."""
    return make_bent_pair()
