"""Shared fixtures and helpers, one home each: small analytic meshes, the bent and permuted
pairs, prepared bases and batches shared by the tests of several modules, and the real data
beside the project (skip if absent). The tests mirror the package (``tests/test_structure.py``:
``test_tests_mirror_the_package``); helpers used by one test file stay in that file."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sla
import scipy.sparse as sp
import torch

from torchfmap import (
    Basis,
    Column,
    Mesh,
    basis_stack,
    farthest_point_sampling,
    laplacian,
    laplacian_eigenbasis,
    save_mesh,
)
from torchfmap.data import icosphere, make_demo_pair
from torchfmap.fmap import laplacian_mask
from torchfmap.kinds import KINDS
from torchfmap.nn import BasisModule
from torchfmap.nn.data import collate_shapes
from torchfmap.nn.inputs import shape_arrays, shape_item
from torchfmap.nn.modules import SpectralDiffusion

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


def make_bent_pair(strength: float = 0.3, seed: int = 2, subdivisions: int = 3):
    """``(x, y, gt)``: the bumpy blob ``x`` (642 vertices; ``10 * 4**subdivisions + 2``), ``y``
    the same surface bent and its vertices shuffled, and the ground truth ``Correspondence``
    (vertex ``v`` of ``y`` is ``gt.idx_x[v]`` of ``x``)."""
    from torchfmap.evaluate.scores import Correspondence

    x = bumpy_blob(subdivisions)
    perm = np.random.default_rng(seed).permutation(x.n_vertices)
    y = x.copy(bend(x.vertices, strength)).permuted(perm)
    return x, y, Correspondence(idx_x=perm, idx_y=np.arange(y.n_vertices))


@pytest.fixture(scope="session")
def bent_pair():
    """:func:`make_bent_pair` with its defaults (shared by the tests of matching)."""
    return make_bent_pair()


#: Scales of the target in the scale-invariance tests: not powers of two (so the unit-area frames
#: differ by round-off), and 2 (a power of two: exactly the same frame).
SCALES = (1e-3, 2.0, 1e3)


def _agree(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean(a == b))


@pytest.fixture(scope="session")
def small_bent_pair():
    """``(x, y, landmarks)``: :func:`make_bent_pair` at 162 vertices (seed 5) and 6 landmarks
    from its ground truth (the scale-invariance tests)."""
    from torchfmap.evaluate.scores import landmarks_from_gt

    x, y, gt = make_bent_pair(seed=5, subdivisions=2)
    return x, y, landmarks_from_gt(x, gt, 6)


@pytest.fixture(scope="session")
def permuted_pair():
    """A mesh and its vertex-permuted copy: y vertex i is x vertex perm[i]."""
    x = bumpy_blob(3)
    perm = np.random.default_rng(4).permutation(x.n_vertices)
    inverse = np.argsort(perm)
    y = x.permuted(perm)
    landmarks = np.array([[v, inverse[v]] for v in (3, 200, 450, 600)])
    return x, y, perm, landmarks


@pytest.fixture(scope="session")
def permuted_bases():
    """The blob, a vertex-permuted copy and their 40-function eigenbases (the conversion and
    refinement tests of ``torchfmap.fmap``)."""
    x = bumpy_blob(3)
    perm = np.random.default_rng(5).permutation(x.n_vertices)
    y = x.permuted(perm)  # y vertex i is x vertex perm[i]: p2p_yx = perm
    return x, y, perm, laplacian_eigenbasis(x, 40), laplacian_eigenbasis(y, 40)


@pytest.fixture(scope="session")
def sphere4() -> Mesh:
    return icosphere(4)  # 2562 vertices


@pytest.fixture(scope="session")
def small_blob() -> Mesh:
    """The demo blob at 162 vertices (no jitter)."""
    return bumpy_blob(2)


#: The basis kinds the learned path accepts.
LEARNED = [name for name, kind in KINDS.items() if kind.learned]

#: A regular tetrahedron (outward faces).
TET_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def with_fin(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """``mesh`` plus one extra triangle (a fin) on an existing edge: that edge then has three faces."""
    a, b = mesh.faces[0, 0], mesh.faces[0, 1]
    tip = mesh.vertices[[a, b]].mean(axis=0) + 0.05 * mesh.vertex_normals[a]
    v = np.vstack([mesh.vertices, tip])
    f = np.vstack([mesh.faces, [[a, b, len(mesh.vertices)]]])
    return v, f


def _basis(n: int = 400, k: int = 60, value: float = 0.0) -> Basis:
    rng = np.random.default_rng(int(value * 1000) % 2**32)
    return Basis(
        rng.standard_normal((n, k)) + value,
        sp.diags(np.full(n, 1.0 / n)),
        [Column("custom") for _ in range(k)],
        stiffness=sp.identity(n, format="csr"),
    )


# -- heat kernels ------------------------------------------------------------------------------
REL_TIMES = np.array([1e-4, 1e-3, 1e-2, 1e-1])


@pytest.fixture(scope="session")
def heat_setting():
    """The blob's operators, three seeds and their heat kernels by ``scipy.linalg.expm`` at
    :data:`REL_TIMES` (the tests of ``operators.heat`` and ``bases.diffusion``)."""
    mesh = bumpy_blob(3)
    L, B = laplacian(mesh)
    seeds = np.array([0, 101, 333])
    times = REL_TIMES * mesh.area
    d = B.diagonal()
    ref = np.stack([sla.expm(-t * (L.toarray() / d[:, None]))[:, seeds] / d[seeds] for t in times])
    return mesh, (L, B), seeds, times, ref


def np_mask(lam_x, lam_y, kind="laplacian", **kwargs):
    """The core's mask (torch) on numpy inputs, returned as numpy."""
    kwargs = {k: torch.as_tensor(v) if isinstance(v, np.ndarray) else v for k, v in kwargs.items()}
    return laplacian_mask(torch.as_tensor(lam_x), torch.as_tensor(lam_y), kind, **kwargs).numpy()


# -- the learned path --------------------------------------------------------------------------
@pytest.fixture(scope="session")
def nn_setting():
    """A bent pair at 162 vertices (each of unit area), near-equal descriptors, eigenbases (7, 6)
    and stacks (the tests of the torch layers and functions)."""
    x = bumpy_blob(2).normalized()  # unit area: the frame the layers work in (nn.basis_arrays)
    y = x.copy(bend(x.vertices, 0.3)).normalized()
    rng = np.random.default_rng(0)
    dx = rng.normal(size=(x.n_vertices, 5))
    dy = dx + 0.05 * rng.normal(size=dx.shape)
    seeds = farthest_point_sampling(x, 4, metric="euclidean")
    eig = (laplacian_eigenbasis(x, 7), laplacian_eigenbasis(y, 6))
    stack = (basis_stack(x, seeds, times=[1e-2], n_eigen=2), basis_stack(y, seeds, times=[1e-2], n_eigen=2))
    return x, y, dx, dy, eig, stack


def as_batch(*bases):
    return [BasisModule(b).batch() for b in bases]


def _grid(n: int = 5) -> Mesh:
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1.3, n), indexing="ij")
    vertices = np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return Mesh(vertices, faces)


def _batch(mesh: Mesh, k: int = 8, k_net: int = 12):
    arrays = shape_arrays(mesh, k, 6, 20, k_net=k_net)
    return collate_shapes([shape_item(arrays, dtype=torch.float64)])


class TinyNet(torch.nn.Module):
    """A user-written network: a linear lift and one learned diffusion (ignores gradients). Its
    constructor arguments are in ``init_kwargs``, so checkpoints can rebuild it."""

    def __init__(self, c_in: int, c_out: int = 8) -> None:
        super().__init__()
        self.init_kwargs = {"c_in": c_in, "c_out": c_out}
        self.lift, self.diffuse = torch.nn.Linear(c_in, c_out), SpectralDiffusion(c_out)

    def forward(self, inputs, basis, grad):
        return self.diffuse(self.lift(inputs), basis)


@pytest.fixture(scope="session")
def blob_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("blobs")
    base = bumpy_blob(2)
    return [
        save_mesh(base.copy(bend(base.vertices, s)), folder / f"blob{i}.off")
        for i, s in enumerate((0.1, 0.3, 0.5))
    ]


@pytest.fixture
def tiny_folder(tmp_path):
    folder = tmp_path / "tiny"
    folder.mkdir()
    base = bumpy_blob(2)
    for i, s in enumerate((0.1, 0.3, 0.5)):
        save_mesh(
            base.copy(bend(base.vertices, s)),
            folder / f"blob{i}.off.gz" if i == 2 else folder / f"blob{i}.ply",
        )
    return folder


@pytest.fixture(scope="session")
def permuted_files(tmp_path_factory):
    """A blob and a vertex-permuted copy on disk (``y`` vertex ``i`` is ``x`` vertex ``perm[i]``)."""
    folder = tmp_path_factory.mktemp("perm")
    x = bumpy_blob(2)
    perm = np.random.default_rng(0).permutation(x.n_vertices)
    y = Mesh(x.vertices[perm], np.argsort(perm)[x.faces])
    save_mesh(x, folder / "a0.off"), save_mesh(y, folder / "a1.off")
    return folder, x, y, perm


# -- the command line --------------------------------------------------------------------------
#: The shipped demo meshes, relative to the repository root (where the suite runs).
DEMO = "torchfmap/data/demo"


def _err(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def _identity_folder(tmp_path):
    folder = tmp_path / "set"
    folder.mkdir()
    x = bumpy_blob(2)
    for i, s in enumerate((0.1, 0.3, 0.5)):
        save_mesh(x.copy(bend(x.vertices, s)), folder / f"m{i}.off")
    return folder


#: Optional extras: tests that need one skip without it.
requires_matplotlib = pytest.mark.skipif(
    importlib.util.find_spec("matplotlib") is None, reason="matplotlib is not installed"
)
requires_plotly = pytest.mark.skipif(
    importlib.util.find_spec("plotly") is None, reason="plotly is not installed"
)
