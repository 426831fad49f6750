import numpy as np
import pytest

from geometry.curvature import principal_curvature
from geometry.meshops import rotation_between, vertex_normals
from geometry.target import cylinder_patch, grid_triangles, sphere_cap


def angle_deg(a, b):
    c = np.abs(np.einsum("ij,ij->i", a, b)) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(c, 0, 1)))


def test_sphere_cap_principal_curvatures_within_2pct():
    R = 40.0
    V, F = sphere_cap(R, 60.0, 10)                 # coarse: 4.5 mm edges, 600 faces
    c = principal_curvature(V, F)
    for k in (c.vertex_k1, c.vertex_k2, c.face_k1, c.face_k2):
        assert np.max(np.abs(k * R - 1.0)) < 0.02   # outward normals: k = +1/R
    # Max's vertex normals are exact on a sphere (away from the one-sided boundary)
    inner = np.linalg.norm(V[:, :2], axis=1) < 0.99 * R * np.sin(np.deg2rad(60))
    np.testing.assert_allclose(vertex_normals(V, F)[inner], ((V - [0, 0, R]) / R)[inner], atol=1e-12)


def cylinder_truth(R, P):
    a = np.arcsin(np.clip(P[:, 0] / R, -1, 1))
    return np.column_stack([np.cos(a), 0 * a, np.sin(a)])


def test_cylinder_k1_along_the_circle():
    R = 30.0
    V, F = cylinder_patch(R, 90.0, 60.0, 32, 24)   # 3 mm edges
    c = principal_curvature(V, F)
    assert np.max(np.abs(c.face_k1 * R - 1.0)) < 0.01
    assert np.max(np.abs(c.face_k2 * R)) < 0.005
    assert np.max(angle_deg(c.face_d1, cylinder_truth(R, V[F].mean(1)))) < 1.5
    assert np.max(angle_deg(c.vertex_d1, cylinder_truth(R, V))) < 3.0
    # d1, d2 orthonormal and tangent
    np.testing.assert_allclose(np.einsum("ij,ij->i", c.face_d1, c.face_d2), 0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", c.face_d1, c.face_normals), 0, atol=1e-12)


def test_quadric_beats_rusinkiewicz_at_the_boundary():
    """The reason for the default: one-sided boundary normals spoil Rusinkiewicz."""
    R = 30.0
    V, F = cylinder_patch(R, 90.0, 60.0, 16, 12)
    err = {m: np.max(np.abs(principal_curvature(V, F, m).vertex_k1 * R - 1)) for m in ("quadric", "rusinkiewicz")}
    assert err["quadric"] < 0.05 < 0.3 < err["rusinkiewicz"]


def test_rusinkiewicz_interior_is_accurate():
    R = 40.0
    V, F = sphere_cap(R, 60.0, 20)
    c = principal_curvature(V, F, "rusinkiewicz")
    inner = np.linalg.norm(V[:, :2], axis=1) < 0.7 * R * np.sin(np.deg2rad(60))
    assert np.max(np.abs(c.vertex_k1[inner] * R - 1)) < 0.02


def test_orientation_flips_sign_and_saddle_picks_max_magnitude():
    # z = x^2/(2a) - y^2/(2b): at the origin k = 1/a along x, -1/b along y (normal +z: k = -z'')
    a, b = 20.0, 40.0
    n = 24
    x = np.linspace(-10, 10, n + 1)
    X, Y = np.meshgrid(x, x, indexing="ij")
    V = np.column_stack([X.ravel(), Y.ravel(), (X**2 / (2 * a) - Y**2 / (2 * b)).ravel()])
    F = grid_triangles(n, n)
    centre = (n // 2) * (n + 1) + n // 2
    c = principal_curvature(V, F)
    assert c.vertex_normals[centre, 2] > 0.99
    # shape operator dN/dx: with normal +z and z = x^2/2a the normal tilts against x: k1 = -1/a
    assert c.vertex_k1[centre] == pytest.approx(-1 / a, rel=0.01)
    assert c.vertex_k2[centre] == pytest.approx(1 / b, rel=0.01)
    assert angle_deg(c.vertex_d1[[centre]], np.array([[1.0, 0, 0]]))[0] < 0.5
    flipped = principal_curvature(V, F[:, ::-1])
    assert flipped.vertex_k1[centre] == pytest.approx(-c.vertex_k1[centre], rel=1e-9)


def test_rotation_between_maps_and_is_orthogonal():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(50, 3))
    b = rng.normal(size=(50, 3))
    a /= np.linalg.norm(a, axis=1)[:, None]
    b /= np.linalg.norm(b, axis=1)[:, None]
    R = rotation_between(a, b)
    np.testing.assert_allclose(np.einsum("kij,kj->ki", R, a), b, atol=1e-12)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
