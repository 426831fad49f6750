import pathlib

import numpy as np
import pytest

from geometry.curvature import principal_curvature
from geometry.fields import (connection_laplacian, curvature_line_field, line_field_roughness,
                             smoothest_line_field)
from geometry.target import cylinder_patch, load_target, plane_patch, sphere_cap
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
