"""geometry.reachable: the surface nearest a target that the stretch bounds admit."""
import numpy as np
import pytest
from scipy.optimize import brentq

from geometry.fields import curvature_line_field
from geometry.flattening import local_triangles
from geometry.meshops import lumped_mass
from geometry.reachable import reachable_surface, smooth_basis, stretch_excess
from geometry.target import sphere_cap
from shellfem.errors import SelfshapeError


def _cap(half_angle_deg, n_radial=10, radius=60.0):
    V, F = sphere_cap(radius, half_angle_deg, n_radial)
    return V, F, curvature_line_field(V, F).face_dirs


def _rms(X, V, F):
    """Area-weighted rms distance (mm) of corresponding vertices after the best translation."""
    m = lumped_mass(V, F)
    D = X - V
    D -= (m @ D) / m.sum()
    return float(np.sqrt(m @ (D ** 2).sum(1) / m.sum()))


def _dihedral_max(X, F):
    """Largest angle (deg) between the normals of two faces sharing an edge."""
    n = np.cross(X[F[:, 1]] - X[F[:, 0]], X[F[:, 2]] - X[F[:, 0]])
    n /= np.linalg.norm(n, axis=1)[:, None]
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    face = np.tile(np.arange(len(F)), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, face = e[order], face[order]
    pair = np.flatnonzero((e[1:] == e[:-1]).all(1))
    c = np.einsum("ij,ij->i", n[face[pair]], n[face[pair + 1]])
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))).max())


def test_a_target_inside_its_bounds_is_returned_as_it_is():
    """A 25-degree cap needs alpha / sin(alpha) = 1.032 of circumferential stretch: inside a box
    [1, 1.05] in both directions it is its own nearest admissible surface."""
    V, F, d1 = _cap(25.0)
    r = reachable_surface(V, F, d1, (1.0, 1.05, 1.0, 1.05))
    assert np.array_equal(r.S, V) and r.history == []
    assert r.out_of_bounds_pct <= 1.0 and r.distance_mm == (0.0, 0.0, 0.0, 0.0)


def test_a_cap_beyond_its_bounds_ends_inside_them_smooth_and_nearer_than_a_flatter_cap():
    """A 45-degree cap (R 60 mm) needs a stretch of 1.11 at its rim; in a box [1, 1.03] the
    surface found has every face's singular values (an independent SVD of each face's map to
    the flat mesh) inside the box to 0.01, is smooth (no crumpling: the free version reached
    dihedral angles of 61 degrees), and is nearer than the one admissible surface known in
    closed form: the flatter cap of the same geodesic radius with alpha' / sin(alpha') = 1.03."""
    b, R, alpha = 1.03, 60.0, 45.0
    V, F, d1 = _cap(alpha)
    r = reachable_surface(V, F, d1, (1.0, b, 1.0, b))
    assert r.out_of_bounds_pct <= 1.0
    _, _, Dinv, _ = local_triangles(r.S, F)
    J = np.stack([r.uv[F[:, 1]] - r.uv[F[:, 0]], r.uv[F[:, 2]] - r.uv[F[:, 0]]], axis=2) @ Dinv
    sv = np.linalg.svd(J, compute_uv=False)
    assert np.mean((sv[:, 1] >= 1.0 - 0.01) & (sv[:, 0] <= b + 0.01)) >= 0.99
    assert _dihedral_max(r.S, F) < 2.5 * _dihedral_max(V, F) + 10.0
    # the flatter cap: same apex, same geodesic distances from it, radius R' = rho / alpha'
    rho = R * np.deg2rad(alpha)
    a2 = brentq(lambda a: a / np.sin(a) - b, 1e-3, 1.5)
    R2 = rho / a2
    g = R * np.arccos(np.clip(1.0 - V[:, 2] / R, -1.0, 1.0))
    t = np.arctan2(V[:, 1], V[:, 0])
    C = np.column_stack([R2 * np.sin(g / R2) * np.cos(t), R2 * np.sin(g / R2) * np.sin(t), R2 * (1 - np.cos(g / R2))])
    assert np.mean(stretch_excess(C, F, np.column_stack([g * np.cos(t), g * np.sin(t)]), d1, (1.0, b, 1.0, b))
                   > 0.01) < 0.01                                   # the candidate is admissible
    rms_s, rms_c = _rms(r.S, V, F), _rms(C, V, F)
    assert 0.3 * rms_c < rms_s <= rms_c
    mean_there, max_there, mean_back, max_back = r.distance_mm
    assert 0 < mean_there < max_there and 0 < mean_back < max_back
    wider = reachable_surface(V, F, d1, (1.0, 1.06, 1.0, 1.06))       # wider bounds: nearer
    assert _rms(wider.S, V, F) < rms_s


def test_smooth_basis_is_mass_orthonormal_and_keeps_the_long_waves():
    V, F, _ = _cap(45.0, 8)
    B = smooth_basis(V, F, 30.0)
    M = lumped_mass(V, F)
    np.testing.assert_allclose(B.T @ (M[:, None] * B), np.eye(B.shape[1]), atol=1e-8)
    assert 3 <= B.shape[1] < len(V) // 4
    assert np.ptp(B[:, 0]) < 1e-6 * np.abs(B[:, 0]).max()          # the constant comes first
    assert smooth_basis(V, F, 15.0).shape[1] > B.shape[1]
    # the same bits on every call: ARPACK's own generator state carries over between calls in a
    # process (its start vector is seeded from the mesh instead)
    assert np.array_equal(smooth_basis(V, F, 30.0), B)


def test_bad_inputs_are_one_line_errors():
    V, F, d1 = _cap(45.0, 6)
    with pytest.raises(SelfshapeError, match="dir1 must have shape"):
        reachable_surface(V, F, d1[:-1], (1.0, 1.03, 1.0, 1.03))
    with pytest.raises(SelfshapeError, match="uv0 must have shape"):
        reachable_surface(V, F, d1, (1.0, 1.03, 1.0, 1.03), np.zeros((3, 2)))
    with pytest.raises(SelfshapeError, match="bounds"):
        reachable_surface(V, F, d1, (1.1, 1.0, 1.0, 1.03))
