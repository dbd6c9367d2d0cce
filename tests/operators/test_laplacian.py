"""Laplace-Beltrami operators (``torchfmap.operators.laplacian``) against closed forms, hand
computations and invariances; point clouds; unreferenced vertices refused."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from torchfmap import (
    Factorization,
    Mesh,
    MeshError,
    Operators,
    ParameterError,
    factorize,
    laplacian,
    mass_matrix,
    point_cloud_laplacian,
)
from torchfmap.data import icosphere
from torchfmap.operators import normalize_area

from ..conftest import data_path, planar_grid, random_rotation, smallest_eigenvalues


# -- hand-checked small cases ------------------------------------------------------------------
def test_single_right_triangle_by_hand():
    mesh = Mesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]))
    L, B = laplacian(mesh, mass="voronoi")
    # right angle at vertex 0 (cot 0) -> edge 1-2 has weight 0; 45-degree angles -> weight 1/2
    assert np.allclose(L.toarray(), [[1, -0.5, -0.5], [-0.5, 0.5, 0], [-0.5, 0, 0.5]])
    assert np.allclose(B.diagonal(), [0.25, 0.125, 0.125])
    assert np.allclose(mass_matrix(mesh, "barycentric").diagonal(), [1 / 6] * 3)
    fem = mass_matrix(mesh, "fem").toarray()
    assert np.allclose(fem, 0.5 / 12 * (np.ones((3, 3)) + np.eye(3)))


S3 = np.sqrt(3.0)


def off_diagonal_dense(a):
    return a[~np.eye(len(a), dtype=bool)]


def regular_tetrahedron(edge: float = 1.0) -> Mesh:
    v = np.array([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]) * edge / (2 * np.sqrt(2))
    f = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    return Mesh(v, f)


@pytest.mark.parametrize("edge", [1.0, 2.5])
def test_regular_tetrahedron_by_hand(edge):
    mesh = regular_tetrahedron(edge)
    L, B = laplacian(mesh)
    # every angle is 60 degrees: each edge has weight 2 * (cot 60 / 2) = 1/sqrt(3)
    expected = (4 * np.eye(4) - np.ones((4, 4))) / S3
    assert np.allclose(L.toarray(), expected)
    face_area = S3 / 4 * edge**2
    assert np.allclose(B.diagonal(), face_area)  # 3 faces x area/3
    fem = mass_matrix(mesh, "fem").toarray()
    assert np.allclose(np.diag(fem), face_area / 2) and np.allclose(off_diagonal_dense(fem), face_area / 6)
    Lmv, _ = laplacian(mesh, scheme="mean_value")
    # tan(30 deg) = 1/sqrt(3), two faces per edge, divided by the edge length
    assert np.allclose(Lmv.toarray(), (4 * np.eye(4) - np.ones((4, 4))) * 2 / (S3 * edge))


# -- structural properties ---------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["cotan", "robust"])
def test_symmetric_psd_rows_sum_zero(blob, kind):
    L, B = laplacian(blob, scheme=kind)
    assert abs(L - L.T).max() < 1e-12
    assert np.abs(np.asarray(L.sum(axis=1))).max() < 1e-10
    assert (L.diagonal() > 0).all()
    smallest = smallest_eigenvalues(L, B, 2)
    assert np.min(smallest) > -1e-9  # PSD: -L is the negative semidefinite "cotan Laplacian"
    assert B.sum() == pytest.approx(blob.area, rel=1e-12)


def off_diagonal(a):
    a = a.toarray()
    return a - np.diag(np.diag(a))


def test_robust_weights_nonnegative_and_equal_cotan_on_delaunay(blob, sphere3):
    L, _ = laplacian(blob, scheme="robust")
    assert off_diagonal(L).max() <= 1e-14  # all weights >= 0
    Lc, _ = laplacian(blob, scheme="cotan")
    assert off_diagonal(Lc).max() > 0  # the jittered blob has negative cotan weights
    # an icosphere is already Delaunay: intrinsic and extrinsic cotan weights coincide
    Lr, _ = laplacian(sphere3, scheme="robust", mollify_factor=0.0)
    Lc, _ = laplacian(sphere3, scheme="cotan")
    assert abs(Lr - Lc).max() < 1e-8 * abs(Lc).max()


def test_robust_on_nonmanifold_and_point_cloud(sphere3):
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]])
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    L, B = laplacian(Mesh(v, f, allow_nonmanifold=True), scheme="robust")
    assert abs(L - L.T).max() < 1e-12 and np.allclose(L.sum(axis=1), 0)
    Lp, Bp = laplacian(sphere3.vertices, scheme="robust")
    vals = smallest_eigenvalues(Lp, Bp, 9)
    assert np.allclose(vals[1:4], 2, rtol=0.1) and np.allclose(vals[4:9], 6, rtol=0.1)
    with pytest.raises(MeshError, match="scheme='robust'"):
        laplacian(sphere3.vertices, scheme="cotan")


def test_mean_value_positive_rows_sum_zero_non_symmetric(blob):
    L, B = laplacian(blob, scheme="mean_value")
    coo = L.tocoo()
    weights = -coo.data[coo.row != coo.col]
    assert weights.min() > 0  # Floater's weights are strictly positive
    assert np.abs(np.asarray(L.sum(axis=1))).max() < 1e-9
    assert abs(L - L.T).max() > 1e-3  # genuinely non-symmetric
    assert np.array_equal(L.indptr, laplacian(blob)[0].indptr)  # same sparsity as cotan


@pytest.mark.parametrize("kind", ["cotan", "mean_value"])
def test_linear_precision_on_planar_mesh(kind):
    """Cotan and mean-value weights both reproduce linear functions at interior vertices."""
    grid = planar_grid(9, jitter=0.3)
    L, _ = laplacian(grid, scheme=kind)
    interior = np.setdiff1d(np.arange(grid.n_vertices), grid.boundary_vertices)
    for coord in (0, 1):
        assert np.abs(L @ grid.vertices[:, coord])[interior].max() < 1e-12


@pytest.mark.parametrize("kind", ["voronoi", "barycentric", "fem"])
def test_mass_sums_to_area(blob, kind):
    assert mass_matrix(blob, kind).sum() == pytest.approx(blob.area, rel=1e-12)


# -- the sphere: eigenvalues l(l+1) with multiplicity 2l+1 -------------------------------------
def sphere_errors(subdivisions: int, mass: str) -> np.ndarray:
    mesh = icosphere(subdivisions)
    L, B = laplacian(mesh, mass=mass)
    vals = smallest_eigenvalues(L, B, 16)
    exact = np.repeat([0, 2, 6, 12], [1, 3, 5, 7]).astype(float)
    return np.abs(vals[1:] - exact[1:]) / exact[1:], vals


@pytest.mark.parametrize("mass", ["voronoi", "barycentric", "fem"])
def test_sphere_eigenvalues_converge(mass):
    results = [sphere_errors(s, mass) for s in (2, 3, 4)]  # each level solved once
    errs = [e.max() for e, _ in results]
    assert errs[0] > errs[1] > errs[2]  # converges under refinement
    assert errs[2] < 0.01  # within 1 % at 2562 vertices
    vals = results[2][1]
    assert abs(vals[0]) < 1e-8
    # multiplicity 2l+1: each cluster is tight compared with the gap to the next
    for lo, hi in ((1, 4), (4, 9), (9, 16)):
        assert np.ptp(vals[lo:hi]) < 0.02 * vals[lo]


# -- invariances -------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["cotan", "robust", "mean_value"])
def test_rigid_motion_invariance(blob, rng, kind):
    moved = blob.copy(blob.vertices @ random_rotation(rng).T + rng.normal(size=3) * 10)
    L0, B0 = laplacian(blob, scheme=kind)
    L1, B1 = laplacian(moved, scheme=kind)
    assert abs(L0 - L1).max() < 1e-9 * abs(L0).max()
    assert abs(B0 - B1).max() < 1e-9 * B0.max()


@pytest.mark.parametrize("kind", ["cotan", "robust", "mean_value"])
def test_permutation_equivariance(blob, rng, kind):
    perm = rng.permutation(blob.n_vertices)
    L0, B0 = laplacian(blob, scheme=kind)
    L1, B1 = laplacian(blob.permuted(perm), scheme=kind)
    assert abs(L0[perm][:, perm] - L1).max() < 1e-10 * abs(L0).max()
    assert abs(B0[perm][:, perm] - B1).max() < 1e-12


@pytest.mark.parametrize("alpha", [0.01, 7.0])
@pytest.mark.parametrize("mass", ["voronoi", "barycentric", "fem"])
def test_scaling(blob, alpha, mass):
    L0, B0 = laplacian(blob, mass=mass)
    L1, B1 = laplacian(blob.scaled(alpha), mass=mass)
    assert abs(L0 - L1).max() < 1e-10 * abs(L0).max()  # cotan weights are scale invariant
    assert abs(B1 - alpha**2 * B0).max() < 1e-10 * alpha**2 * B0.max()


def test_normalize_area(blob):
    unit = normalize_area(blob.scaled(3.0))
    assert unit.area == pytest.approx(1.0, rel=1e-12)
    assert np.allclose(laplacian(unit)[1].sum(), 1.0)


def test_bad_kinds(blob):
    with pytest.raises(ParameterError, match="unknown Laplacian scheme 'fancy'"):
        laplacian(blob, scheme="fancy")
    with pytest.raises(ParameterError, match="unknown mass scheme"):
        laplacian(blob, mass="lumped")


# -- real data ---------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "parts",
    [("tosca_hires_wolf", "wolf0.off"), ("tosca5k_dev", "cat0.off"), ("pyfm_cat_lion", "lion-00.off")],
)
def test_real_meshes(parts):
    from torchfmap import load_mesh

    mesh = load_mesh(data_path(*parts), allow_components=True)
    L, B = laplacian(mesh)
    assert abs(L - L.T).max() < 1e-9 * abs(L).max()
    assert np.abs(np.asarray(L.sum(axis=1))).max() < 1e-8 * abs(L).max()
    assert B.sum() == pytest.approx(mesh.area, rel=1e-10)
    vals = smallest_eigenvalues(L, B, 6)
    assert abs(vals[0]) < 1e-6 * vals[-1] and vals[1] > 0


def test_operators_unpack_and_factorization_solves(sphere2, rng):
    ops = laplacian(sphere2)
    assert isinstance(ops, Operators)
    L, B = ops
    assert L is ops.stiffness and B is ops.mass
    A = (L + 0.5 * B).tocsc()  # SPD
    fac = factorize(A, spd=True)
    assert isinstance(fac, Factorization)
    b = rng.normal(size=(sphere2.n_vertices, 3))
    # backward-stable direct solve: residual ~ eps·cond(A)·|b|; cond(L + B/2) here < 1e4
    for rhs in (b, b[:, 0]):
        x = fac.solve(rhs)
        assert x.shape == rhs.shape
        np.testing.assert_allclose(x, spla.spsolve(A, rhs), rtol=1e-9, atol=1e-12)


def test_point_cloud_laplacian(sphere3, rng):
    """Symmetric, constants in the kernel (round-off), mass = area of the sampled sphere up to
    an inscribed triangulation's O(h²) deficit, equivariant under relabelling the points."""
    L, B = point_cloud_laplacian(sphere3.vertices)
    n = sphere3.n_vertices
    assert abs(L - L.T).max() <= 1e-12 * abs(L).max()
    assert np.abs(L @ np.ones(n)).max() <= 1e-12 * abs(L).max()
    assert abs(B.sum() - 4 * np.pi) / (4 * np.pi) <= sphere3.edge_lengths.max() ** 2
    perm = rng.permutation(n)
    Lp, Bp = point_cloud_laplacian(sphere3.vertices[perm])
    np.testing.assert_allclose(Bp.diagonal(), B.diagonal()[perm], rtol=1e-10)
    with pytest.raises(MeshError, match="V>=4, 3"):
        point_cloud_laplacian(np.zeros((3, 3)))


def test_unreferenced_vertices_are_refused_by_operators_and_referenced_removes_them(sphere2):
    """Item 5: a mesh kept with allow_unreferenced=True loads, but operators (whose rows at such
    vertices would be all zero: singular solves) refuse it with the fix; ``referenced()`` gives
    the submesh and the ids that map results back, and the submesh matches like the original."""
    from torchfmap import Mesh, MeshError, match

    extra = np.vstack([sphere2.vertices[:7], [[5.0, 5.0, 5.0]], sphere2.vertices[7:]])
    faces = np.where(sphere2.faces >= 7, sphere2.faces + 1, sphere2.faces)  # vertex 7 is unused
    mesh = Mesh(extra, faces, allow_unreferenced=True)
    with pytest.raises(MeshError, match=r"not used by any face.*mesh.referenced\(\)"):
        laplacian(mesh)
    with pytest.raises(MeshError, match="not used by any face"):
        match(mesh, mesh, k=10)
    sub, ids = mesh.referenced()
    assert sub.n_vertices == sphere2.n_vertices and 7 not in ids
    np.testing.assert_array_equal(sub.vertices, sphere2.vertices)
    np.testing.assert_array_equal(sub.faces, sphere2.faces)
    np.testing.assert_array_equal(mesh.vertices[ids], sub.vertices)
    L_sub, L_ref = laplacian(sub), laplacian(sphere2)
    assert abs(L_sub.stiffness - L_ref.stiffness).max() == 0 and abs(L_sub.mass - L_ref.mass).max() == 0
