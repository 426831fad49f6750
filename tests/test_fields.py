import pathlib

import numpy as np
import pytest
from scipy.spatial import Delaunay

from geometry.curvature import principal_curvature
from geometry.fields import (connection_laplacian, curvature_line_field, line_field_roughness,
                             smoothest_line_field)
from geometry.target import cylinder_patch, load_target, plane_patch, sphere_cap, triangulate_disk
from inverse.design import design
from shellfem.errors import SelfshapeError


def angle_deg(a, b):
    c = np.abs(np.einsum("ij,ij->i", a, b)) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(c, 0, 1)))


def test_cylinder_field_follows_the_circle():
    R = 30.0
    V, F = cylinder_patch(R, 90.0, 60.0, 32, 24)
    lf = curvature_line_field(V, F)
    P = V[F].mean(1)
    a = np.arcsin(P[:, 0] / R)
    truth = np.column_stack([np.cos(a), 0 * a, np.sin(a)])
    assert np.max(angle_deg(lf.face_dirs, truth)) < 1.5
    np.testing.assert_allclose(np.linalg.norm(lf.face_dirs, axis=1), 1.0, atol=1e-12)
    assert not lf.smoothest


def test_sphere_cap_field_is_smoother_than_raw_directions():
    V, F = sphere_cap(40.0, 45.0, 12)
    curv = principal_curvature(V, F)
    raw = line_field_roughness(V, F, curv.face_d1).mean()
    field = line_field_roughness(V, F, curvature_line_field(V, F, 0.0, curv).face_dirs).mean()
    smooth = line_field_roughness(V, F, smoothest_line_field(V, F).face_dirs).mean()
    # umbilic everywhere: raw k1 is discretisation noise; lambda = 0 smooths it (measured
    # 7.95 -> 4.75 deg mean jump across edges); the smoothest field is ~0.4 deg
    assert field < 0.7 * raw
    assert smooth < 1.0 < field


def test_plane_gives_constant_smoothest_field():
    V, F = plane_patch()
    lf = curvature_line_field(V, F)
    assert lf.smoothest
    assert line_field_roughness(V, F, lf.face_dirs).max() < 1e-6


def test_lambda_trades_smoothness_for_alignment():
    path = pathlib.Path(__file__).resolve().parents[1] / "meshes" / "targets" / "hat.obj"
    V, F = load_target(path)
    curv = principal_curvature(V, F)
    w = np.abs(curv.face_k1) - np.abs(curv.face_k2)
    dev, rough, ts = [], [], []
    for lam in (0.0, -0.01, -0.1, -1.0):
        lf = curvature_line_field(V, F, lam, curv)
        dev.append(np.sum(w * angle_deg(lf.face_dirs, curv.face_d1)) / w.sum())
        rough.append(line_field_roughness(V, F, lf.face_dirs).mean())
        ts.append(lf.t)
    assert all(a > b for a, b in zip(dev, dev[1:]))        # less smoothing -> closer to k1
    assert all(a < b for a, b in zip(rough, rough[1:]))    # ... and rougher
    assert all(a < b for a, b in zip(ts, ts[1:])) and 0 < ts[0] and ts[-1] < 1


def test_deterministic_and_bad_lambda():
    V, F = sphere_cap(40.0, 30.0, 6)
    a = curvature_line_field(V, F, -0.01).face_dirs
    b = curvature_line_field(V, F, -0.01).face_dirs
    assert np.array_equal(a, b)
    with pytest.raises(SelfshapeError, match="lambda"):
        curvature_line_field(V, F, 0.5)


def test_connection_laplacian_hermitian_psd_and_flat_on_plane():
    V, F = sphere_cap(40.0, 45.0, 6)
    A = connection_laplacian(V, F, 2)
    assert abs(A - A.conj().T).max() < 1e-12
    rng = np.random.default_rng(1)
    x = rng.normal(size=(len(V), 8)) + 1j * rng.normal(size=(len(V), 8))
    assert np.min(np.einsum("ij,ij->j", x.conj(), A @ x).real) > 0
    # on a plane the constant field (in the common frame) has zero energy
    V, F = plane_patch(10, 10, 4, 4)
    A = connection_laplacian(V, F, 2)
    u = np.full(len(V), np.exp(0.3j))
    assert abs(np.vdot(u, A @ u)) < 1e-10


# ----------------------------------------------------------------------------- every target of the class
# Delaunay triangulations of scattered points (how scanned and sampled targets come) have boundary
# triangles with angles near 180 deg, i.e. large negative cotangent weights. With the holonomy of
# the discrete transport they make the connection Laplacian indefinite where the surface is
# developable, and lambda = 0 lay above its spectrum: the factorisation failed (meshes of a few
# thousand vertices and more) or small meshes got the field turned by 90 degrees.

def delaunay_ccw(P):
    """Delaunay triangles of the points P (n, 2), counter-clockwise."""
    F = Delaunay(P).simplices.astype(np.int64)
    a, b = P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]]
    cw = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0] < 0
    F[cw] = F[cw][:, [0, 2, 1]]
    return F


def scattered_points(nx, ny, width=100.0, height=80.0, seed=0):
    """A grid of (nx+1) x (ny+1) points on a width x height mm rectangle, every point jittered by up
    to 0.3 cells: its Delaunay hull has slivers along the whole boundary."""
    s, y = np.meshgrid(np.linspace(-width / 2, width / 2, nx + 1), np.linspace(-height / 2, height / 2, ny + 1),
                       indexing="ij")
    P = np.column_stack([s.ravel(), y.ravel()])
    return P + np.random.default_rng(seed).uniform(-0.3, 0.3, P.shape) * [width / nx, height / ny]


def zigzag_points(nx, ny, width=100.0, height=80.0, seed=0):
    """The grid with its interior points jittered by up to 0.2 cells and its boundary points 3e-4
    cells alternately outside and inside the rectangle: the Delaunay hull skips every other one
    (boundary angles of ~179.9 deg) but no edge is longer than two cells."""
    hx, hy = width / nx, height / ny
    i, j = (a.ravel() for a in np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), indexing="ij"))
    P = np.column_stack([-width / 2 + i * hx, -height / 2 + j * hy])
    inner = (i > 0) & (i < nx) & (j > 0) & (j < ny)
    P[inner] += np.random.default_rng(seed).uniform(-0.2, 0.2, (inner.sum(), 2)) * [hx, hy]
    side_x = ((i == 0) | (i == nx)) & ~inner & (j > 0) & (j < ny)
    side_y = ((j == 0) | (j == ny)) & ~inner & (i > 0) & (i < nx)
    P[side_x, 0] += np.sign(P[side_x, 0]) * np.where(j[side_x] % 2, -3e-4, 3e-4) * hx
    P[side_y, 1] += np.sign(P[side_y, 1]) * np.where(i[side_y] % 2, -3e-4, 3e-4) * hy
    return P


VAULT_R = 60.0


def vault(P):
    """Cylindrical vault of radius 60 mm, axis along y, from developed points P (n, 2) (arc length,
    axial mm) and their Delaunay triangles; returns V, F and the unit circumferential direction
    at the face centroids (the curved direction, |k1| = 1/R)."""
    F = delaunay_ccw(P)
    a = P[:, 0] / VAULT_R
    V = np.column_stack([VAULT_R * np.sin(a), P[:, 1], VAULT_R * (1.0 - np.cos(a))])
    ac = P[F, 0].mean(axis=1) / VAULT_R
    return V, F, np.column_stack([np.cos(ac), 0 * ac, np.sin(ac)])


@pytest.mark.parametrize("points", [zigzag_points(20, 16), zigzag_points(70, 56), scattered_points(80, 64)],
                         ids=["zigzag-357", "zigzag-4047", "scattered-5265"])
def test_developable_vault_field_follows_the_curved_direction(points):
    V, F, circ = vault(points)
    curv = principal_curvature(V, F)
    lf = curvature_line_field(V, F, 0.0, curv)
    dev = angle_deg(lf.face_dirs, circ)
    # before: 0 % within 3 deg (zigzag-357: the field turned by 90 deg), an exception for the others;
    # measured now 100 % on all three, maximum 1.1 / 0.3 / 2.2 deg (raw d1: 100 / 100 / 98.3 %)
    assert np.mean(dev < 3.0) >= 0.95 and np.median(dev) < 1.0
    np.testing.assert_allclose(np.linalg.norm(lf.face_dirs, axis=1), 1.0, atol=1e-12)
    assert lf.clamped and not lf.smoothest          # the indefinite case, solved without the negative weights
    # lambda = 0 is the smoothest limit here: t ~ 0, far below a doubly curved target's (sphere cap 0.025)
    assert 0.0 < lf.t < 1e-4


@pytest.mark.parametrize("mesh", ["disk", "scattered", "scattered-tilted"])
def test_plane_gives_a_finite_constant_unit_field(mesh):
    if mesh == "disk":
        P, F = triangulate_disk(30)
        V = np.column_stack([50.0 * P, np.zeros(len(P))])
    else:
        P = scattered_points(80, 64)
        F = delaunay_ccw(P)
        V = np.column_stack([P, np.zeros(len(P))])
        if mesh == "scattered-tilted":                  # curvature is round-off: the guidance is noise
            c, s = np.cos(0.6), np.sin(0.6)
            V = V @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]).T + [3.0, 4.0, 5.0]
    lf = curvature_line_field(V, F)
    assert np.isfinite(lf.face_dirs).all()
    np.testing.assert_allclose(np.linalg.norm(lf.face_dirs, axis=1), 1.0, atol=1e-12)
    # a parallel field: the same direction everywhere (measured max jump 1e-4 deg tilted, 0 flat)
    assert line_field_roughness(V, F, lf.face_dirs).max() < 1e-3
    assert lf.smoothest == (mesh != "scattered-tilted")


@pytest.mark.parametrize("mesh", ["disk", "scattered"])
def test_sphere_cap_gives_a_finite_unit_field_unchanged_by_the_fallback(mesh):
    R = 40.0
    if mesh == "disk":
        V, F = sphere_cap(R, 60.0, 30)
    else:                                               # scattered points on a 55-deg cap, hull slivers
        P = scattered_points(60, 60, 76.0, 76.0)
        P = P[np.linalg.norm(P, axis=1) < 38.0]
        F = delaunay_ccw(P)[:, [0, 2, 1]]
        r = np.linalg.norm(P, axis=1)
        u = P / np.maximum(r, 1e-12)[:, None]
        V = np.column_stack([R * np.sin(r / R) * u[:, 0], R * np.sin(r / R) * u[:, 1], R * (1 - np.cos(r / R))])
    curv = principal_curvature(V, F)
    lf = curvature_line_field(V, F, 0.0, curv)
    assert np.isfinite(lf.face_dirs).all()
    np.testing.assert_allclose(np.linalg.norm(lf.face_dirs, axis=1), 1.0, atol=1e-12)
    # doubly curved: lambda_min(A, M) > 0, the system is solved as given (lambda - 1e-10 s)
    assert not lf.clamped and -1e-6 < lf.sigma < 0.0
    assert 0.001 < lf.t < 0.1                           # measured 0.010 (disk), 0.017 (scattered)
    raw = line_field_roughness(V, F, curv.face_d1).mean()
    assert line_field_roughness(V, F, lf.face_dirs).mean() < 0.7 * raw


def smoothstep(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


@pytest.mark.parametrize("surface", ["developable-then-dome", "cubic-saddle"])
def test_mixed_target_field_follows_k1_where_it_is_distinct(surface):
    P = scattered_points(80, 64)
    F = delaunay_ccw(P)
    x, y = P[:, 0], P[:, 1]
    if surface == "developable-then-dome":
        # x < 0: parabolic cylinder (K = 0, |k1 - k2| = 1/100..1/60 per mm); x > 40: k2 = 1/300 (K > 0)
        z = x ** 2 / 120 + smoothstep(x / 40) * y ** 2 / 600
    else:                                               # z = a x^2 - b y^2 + c x^3: K < 0, k1 along x
        z = x ** 2 / 120 - y ** 2 / 400 + x ** 3 / 30000
    V = np.column_stack([P, z])
    curv = principal_curvature(V, F)
    lf = curvature_line_field(V, F, 0.0, curv)
    np.testing.assert_allclose(np.linalg.norm(lf.face_dirs, axis=1), 1.0, atol=1e-12)
    dev = angle_deg(lf.face_dirs, curv.face_d1)
    if surface == "developable-then-dome":
        # before: an exception; measured now 96.9 % of the developable half within 5 deg of d1
        part = V[F, 0].mean(axis=1) < 0.0
    else:
        # where |k1 - k2| exceeds half its 90th percentile (86 % of the faces): measured 99.3 %
        dk = np.abs(curv.face_k1 - curv.face_k2)
        part = dk > 0.5 * np.percentile(dk, 90)
    assert np.mean(dev[part] < 5.0) >= 0.95


def test_design_of_a_scanned_vault_lays_ribbons_along_the_curved_direction():
    V, F, circ = vault(zigzag_points(70, 56))
    d = design(V, F, diagonal_mm=None, edge_mm=None)    # before: an exception in the field
    assert np.mean(angle_deg(d.field.face_dirs, circ) < 3.0) >= 0.95
    assert len(d.ribbons) > 50
    # the ribbons bend with the vault: normal curvature along them |k| = 1/R (the axial one is 0);
    # measured median |kappa1| R = 1.0005, every ribbon's mean |kappa| R within 1.000..1.001
    assert abs(np.median(d.kappa1)) * VAULT_R == pytest.approx(1.0, abs=0.02)
    k = np.array([r.meta["kappa_mean_abs"] for r in d.ribbons]) * VAULT_R
    assert k.min() > 0.95 and k.max() < 1.05


def test_degenerate_meshes_are_refused_in_one_line():
    V, F = sphere_cap(40.0, 45.0, 6)
    V1 = V.copy()
    V1[F[5, 1]] = V1[F[5, 0]]                           # a collapsed edge: two zero-area faces
    with pytest.raises(SelfshapeError, match="field: face 5 has zero area"):
        curvature_line_field(V1, F)
    with pytest.raises(SelfshapeError, match="belongs to no face"):
        smoothest_line_field(np.vstack([V, [[1e3, 0.0, 0.0]]]), F)
    V2 = V.copy()
    V2[3, 2] = np.nan
    with pytest.raises(SelfshapeError, match="vertex 3 has a non-finite coordinate"):
        curvature_line_field(V2, F)
