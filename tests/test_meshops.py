"""Shared mesh operations (geometry.meshops) against exact values."""
import math

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.linalg import eigh

from geometry.meshops import (NotPositiveDefiniteError, boundary_loop_count, corner_cotangents, cotan_weights,
                              definite_factor, face_areas, face_frames, face_normals, factorize, halfedges,
                              lumped_mass, mesh_edges,
                              remove_unreferenced, rotation_between, signed_areas, smallest_eigenvector,
                              smallest_ritz_pairs,
                              tangent_frames, triangle_angles, unique_edges, vertex_normals)
from geometry.target import grid_triangles, plane_patch, sphere_cap
from shellfem.errors import SelfshapeError


def right_triangle():
    V = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 4.0, 0.0]])
    return V, np.array([[0, 1, 2]])


def test_face_normals_areas_and_frames_of_a_right_triangle():
    V, F = right_triangle()
    assert face_areas(V, F).tolist() == [6.0]
    assert face_normals(V, F).tolist() == [[0.0, 0.0, 1.0]]
    assert signed_areas(V[:, :2], F).tolist() == [6.0]
    assert signed_areas(V[:, :2], F[:, [0, 2, 1]]).tolist() == [-6.0]
    U, W, N = face_frames(V, F)
    assert U.tolist() == [[1.0, 0.0, 0.0]] and W.tolist() == [[0.0, 1.0, 0.0]] and N.tolist() == [[0.0, 0.0, 1.0]]
    np.testing.assert_allclose(triangle_angles(V, F), [[90.0, math.degrees(math.atan2(4, 3)),
                                                        math.degrees(math.atan2(3, 4))]], rtol=1e-14)
    # cot at the right angle is 0, at the 3-4-5 corners 3/4 and 4/3
    np.testing.assert_allclose(corner_cotangents(V, F), [[0.0, 3 / 4, 4 / 3]], atol=1e-15)
    # half-edge c (F[c] -> F[c+1]) is weighted by half the cot of the corner opposite to it
    np.testing.assert_allclose(cotan_weights(V, F), [0.5 * 4 / 3, 0.0, 0.5 * 3 / 4], atol=1e-15)


def test_degenerate_face_has_a_zero_normal():
    V = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    assert face_normals(V, np.array([[0, 1, 2]])).tolist() == [[0.0, 0.0, 0.0]]


@pytest.mark.parametrize("weighting", ["max", "area"])
def test_vertex_normals_on_a_sphere_cap_point_away_from_the_centre(weighting):
    R = 40.0
    V, F = sphere_cap(R, 45.0, 10)
    N = vertex_normals(V, F, weighting)
    radial = (V - [0.0, 0.0, R]) / R                 # outward radial direction
    np.testing.assert_allclose(np.linalg.norm(N, axis=1), 1.0, rtol=1e-14)
    assert np.min(np.einsum("ij,ij->i", N, radial)) > 0.99
    if weighting == "max":                           # Max's weights are exact on a sphere's interior
        interior = np.linalg.norm(V[:, :2], axis=1) < 0.9 * np.linalg.norm(V[:, :2], axis=1).max()
        np.testing.assert_allclose(N[interior], radial[interior], atol=1e-12)
    raw = vertex_normals(V, F, weighting, unit_length=False)
    np.testing.assert_allclose(raw / np.linalg.norm(raw, axis=1)[:, None], N, atol=1e-15)
    with pytest.raises(ValueError, match="weighting"):
        vertex_normals(V, F, "angle")


@pytest.mark.parametrize("seed", ["least_aligned", "x_or_y"])
def test_tangent_frames_are_orthonormal_and_right_handed(seed):
    rng = np.random.default_rng(0)
    N = rng.normal(size=(500, 3))
    N = np.vstack([N / np.linalg.norm(N, axis=1)[:, None], np.eye(3), -np.eye(3)])
    e1, e2 = tangent_frames(N, seed)
    for a, b in ((e1, e1), (e2, e2), (N, N)):
        np.testing.assert_allclose(np.einsum("ij,ij->i", a, b), 1.0, rtol=1e-14)
    for a, b in ((e1, e2), (e1, N), (e2, N)):
        np.testing.assert_allclose(np.einsum("ij,ij->i", a, b), 0.0, atol=1e-15)
    np.testing.assert_allclose(np.cross(e1, e2), N, atol=1e-15)


def test_rotation_between_maps_a_to_b():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    a /= np.linalg.norm(a, axis=1)[:, None]
    b /= np.linalg.norm(b, axis=1)[:, None]
    R = rotation_between(a, b)
    np.testing.assert_allclose(np.einsum("kij,kj->ki", R, a), b, atol=1e-13)
    np.testing.assert_allclose(np.einsum("kji,kjl->kil", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-13)


def test_edges_of_a_grid_and_their_faces():
    nx, ny = 5, 4
    F = grid_triangles(nx, ny)
    n = (nx + 1) * (ny + 1)
    E, he2e, counts = unique_edges(F)
    # disk: V - E + F = 1; boundary edges 2 (nx + ny), each with one face; interior edges two
    assert len(E) == n + len(F) - 1
    assert (counts == 1).sum() == 2 * (nx + ny) and set(counts.tolist()) == {1, 2}
    assert (E[:, 0] < E[:, 1]).all() and (np.diff(E[:, 0] * n + E[:, 1]) > 0).all()
    H = halfedges(F)
    assert np.array_equal(np.sort(H, axis=1), E[he2e])
    E2, face_edge, forward = mesh_edges(F, n)
    assert np.array_equal(E2, E) and np.array_equal(face_edge.ravel(), he2e)
    assert np.array_equal(forward.ravel(), H[:, 0] < H[:, 1])
    assert boundary_loop_count(F, n) == 1


def test_boundary_loops_of_an_annulus_and_unreferenced_vertices():
    F = grid_triangles(4, 4)                          # 5 x 5 vertices, the centre one is 12
    holed = F[~(F == 12).any(axis=1)]                 # its fan removed: a hole
    assert boundary_loop_count(F, 25) == 1 and boundary_loop_count(holed, 25) == 2
    V = np.arange(25.0 * 3).reshape(25, 3)
    V2, F2, used = remove_unreferenced(V, holed)
    assert used.tolist() == [v for v in range(25) if v != 12]
    assert np.array_equal(V2[F2], V[holed])


def test_cotangent_laplacian_is_exact_on_linear_functions_and_mass_sums_to_area():
    V, F = plane_patch(30.0, 20.0, 6, 5)
    rng = np.random.default_rng(4)
    V[:, :2] += rng.uniform(-0.5, 0.5, (len(V), 2)) * (np.abs(V[:, :2]) < [14.9, 9.9])   # jiggle the interior
    E, he2e, counts = unique_edges(F)
    w = np.bincount(he2e, weights=cotan_weights(V, F), minlength=len(E))
    n = len(V)
    L = sp.coo_matrix((np.r_[w, w, -w, -w], (np.r_[E[:, 0], E[:, 1], E[:, 0], E[:, 1]],
                                               np.r_[E[:, 1], E[:, 0], E[:, 0], E[:, 1]])), shape=(n, n)).tocsr()
    interior = np.setdiff1d(np.arange(n), E[counts == 1])
    f = 2.0 * V[:, 0] - 3.0 * V[:, 1] + 1.0
    np.testing.assert_allclose((L @ f)[interior], 0.0, atol=1e-12)
    assert lumped_mass(V, F).sum() == pytest.approx(600.0, rel=1e-14)


def path_laplacian(n, complex_twist=0.0):
    """1D connection Laplacian (twist rad per edge) plus a potential rising along the path:
    Hermitian positive definite, a non-constant smallest mode; small enough for a dense check."""
    i = np.arange(n - 1)
    r = np.exp(1j * complex_twist * np.ones(n - 1))
    off = -r if complex_twist else -np.ones(n - 1)
    diag = np.bincount(i, minlength=n) + np.bincount(i + 1, minlength=n) + np.linspace(0.0, 0.05, n) ** 2
    return sp.csc_matrix((np.r_[diag, off, np.conj(off)], (np.r_[np.arange(n), i + 1, i], np.r_[np.arange(n), i, i + 1])),
                         shape=(n, n))


@pytest.mark.parametrize("twist", [0.0, 0.3])
@pytest.mark.parametrize("mode", ["block", "vector"])
def test_smallest_eigenvector_matches_a_dense_solve(twist, mode):
    n = 60
    A = path_laplacian(n, twist)
    mass = np.linspace(1.0, 2.0, n)
    lam_ref, X_ref = eigh(A.toarray(), np.diag(mass))
    if mode == "block":
        start = np.random.default_rng(0).standard_normal((n, 4)).astype(A.dtype)
        x, lam, it = smallest_eigenvector(A, mass, start, rtol=1e-13, max_iter=500, stop="eigenvalue",
                                          ordering="amd")
    else:
        x, lam, it = smallest_eigenvector(A, mass, np.ones(n, dtype=A.dtype), rtol=1e-14, max_iter=2000,
                                          stop="vector")
    assert it < (500 if mode == "block" else 2000)
    assert np.vdot(x, mass * x).real == pytest.approx(1.0, rel=1e-12)
    assert lam == pytest.approx(max(lam_ref[0], 0.0), abs=1e-9)
    overlap = abs(np.vdot(X_ref[:, 0], mass * x))            # same M-unit vector up to a phase
    assert overlap == pytest.approx(1.0, abs=1e-6)


def test_smallest_ritz_pairs_returns_the_block_and_obeys_an_extra_stopping_test():
    n = 60
    A = path_laplacian(n, 0.3)
    mass = np.linspace(1.0, 2.0, n)
    lam_ref = eigh(A.toarray(), np.diag(mass), eigvals_only=True)
    start = np.random.default_rng(0).standard_normal((n, 4)).astype(A.dtype)
    ritz, X, it = smallest_ritz_pairs(A, mass, start, rtol=1e-13, max_iter=500, ordering="amd")
    assert np.all(np.diff(ritz) >= 0)
    assert ritz[0] == pytest.approx(lam_ref[0], rel=1e-9)
    assert ritz[1] == pytest.approx(lam_ref[1], rel=1e-6)              # converges at lambda_2 / lambda_5
    np.testing.assert_allclose(X.conj().T @ (mass[:, None] * X), np.eye(4), atol=1e-10)
    x, lam, it1 = smallest_eigenvector(A, mass, start, rtol=1e-13, max_iter=500, ordering="amd")
    assert it1 == it and lam == ritz[0]
    np.testing.assert_allclose(x, X[:, 0] / np.sqrt(np.vdot(X[:, 0], mass * X[:, 0]).real), atol=1e-15)
    calls = []
    *_, it2 = smallest_ritz_pairs(A, mass, start, rtol=1e-13, max_iter=500, ordering="amd",
                                  converged=lambda r, Y: calls.append(len(r)) or len(calls) >= it + 3)
    assert it2 == it + 3 and calls == [4] * it2


def test_factorize_solves_and_an_unknown_stopping_rule_is_refused():
    A = path_laplacian(5) + sp.eye(5)
    b = np.arange(5.0)
    np.testing.assert_allclose(A @ factorize(A)(b), b, atol=1e-12)
    np.testing.assert_allclose(A @ factorize(A, "amd")(b), b, atol=1e-12)
    with pytest.raises(ValueError, match="stop"):
        smallest_eigenvector(A, np.ones(5), np.ones(5), rtol=1e-6, max_iter=5, stop="residual")


def test_factorize_refuses_a_singular_matrix():
    pytest.importorskip("sksparse.cholmod", reason="optional CHOLMOD; the SuperLU fallback does not test definiteness")
    with pytest.raises(NotPositiveDefiniteError, match="not positive definite"):
        factorize(sp.diags([1.0, 0.0, 2.0, 3.0]))               # a zero pivot


def test_check_definite_refuses_an_indefinite_matrix_at_any_size():
    pytest.importorskip("sksparse.cholmod", reason="optional CHOLMOD")
    A = sp.diags([1.0, -1.0, 2.0, 3.0])
    factorize(A)                                  # CHOLMOD's simplicial LDL^T factors it
    with pytest.raises(NotPositiveDefiniteError, match="not positive definite"):
        factorize(A, check_definite=True)
    np.testing.assert_allclose(factorize(A + 2 * sp.eye(4), check_definite=True)(np.ones(4)), [1 / 3, 1, 1 / 4, 1 / 5])


@pytest.mark.parametrize("potential", [0.0, -0.05, -3.0])
def test_definite_factor_steps_just_below_the_smallest_eigenvalue(potential):
    """A singular (potential 0) or indefinite Hermitian A: s = lambda_min - margin, and the factor
    solves A - s M; a positive definite A keeps sigma."""
    n = 120
    i = np.arange(n - 1)
    diag = (np.bincount(i, minlength=n) + np.bincount(i + 1, minlength=n)
            + potential * np.exp(-((np.arange(n) - n / 2) / 5.0) ** 2)).astype(complex)
    off = -np.exp(0.3j) * np.ones(n - 1) if potential == -3.0 else -np.ones(n - 1, dtype=complex)
    A = sp.csc_matrix((np.r_[diag, off, np.conj(off)], (np.r_[np.arange(n), i + 1, i], np.r_[np.arange(n), i, i + 1])),
                      shape=(n, n))
    mass = np.linspace(1.0, 2.0, n)
    lam_min = eigh(A.toarray(), np.diag(mass), eigvals_only=True)[0]
    solve, s = definite_factor(A, mass, 0.0, 1e-8)
    assert lam_min - s == pytest.approx(1e-8, rel=1e-3)          # measured 1.000e-8 each
    b = np.arange(n, dtype=complex)
    np.testing.assert_allclose((A - s * sp.diags(mass)) @ solve(b), b, rtol=1e-6, atol=1e-6 * np.abs(b).max())
    solve, s = definite_factor(A, mass, lam_min - 0.1, 1e-8)     # below the spectrum already
    assert s == lam_min - 0.1


def test_definite_factor_refuses_non_finite_entries():
    A = sp.csc_matrix(np.diag([1.0, np.nan, 2.0]))
    with pytest.raises(SelfshapeError, match="non-finite"):
        definite_factor(A, np.ones(3), 0.0, 1e-8)
