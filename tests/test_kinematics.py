"""Discrete fundamental forms: exact derivatives (finite differences) and exact geometry."""
import numpy as np
import pytest

from shellfem.kinematics import build_topology, face_heights, first_fundamental_form, hinge_angles
from shellfem.model import ShellModel
from shellfem.sheet import Sheet


def _fd(fun, x, eps=1e-6):
    X = x.reshape(len(x), -1)
    v, g, H = fun(x)
    gn, Hn = np.zeros_like(g), np.zeros_like(H)
    for d in range(X.shape[1]):
        Xp, Xm = X.copy(), X.copy()
        Xp[:, d] += eps
        Xm[:, d] -= eps
        vp, gp, _ = fun(Xp.reshape(x.shape))
        vm, gm, _ = fun(Xm.reshape(x.shape))
        gn[..., d] = (vp - vm) / (2 * eps)
        Hn[..., d] = (gp - gm) / (2 * eps)
    return g, gn, H, Hn


def test_dihedral_angle_derivatives_match_finite_differences():
    x = np.random.default_rng(3).normal(size=(20, 4, 3))
    g, gn, H, Hn = _fd(hinge_angles, x)
    assert np.abs(g - gn).max() < 1e-7 * np.abs(g).max()
    assert np.abs(H - Hn).max() < 1e-6 * np.abs(H).max()


def test_height_derivatives_match_finite_differences():
    x = np.random.default_rng(4).normal(size=(20, 3, 3))
    g, gn, H, Hn = _fd(face_heights, x)
    assert np.abs(g - gn).max() < 1e-7 * np.abs(g).max()
    assert np.abs(H - Hn).max() < 1e-6 * np.abs(H).max()


def test_first_fundamental_form_jacobian():
    x = np.random.default_rng(5).normal(size=(10, 3, 3))
    a, J = first_fundamental_form(x)
    eps = 1e-6
    X = x.reshape(10, 9)
    for d in range(9):
        Xp = X.copy()
        Xp[:, d] += eps
        ap, _ = first_fundamental_form(Xp.reshape(10, 3, 3))
        assert np.allclose((ap - a) / eps, J[:, :, d], atol=1e-5)


def test_valley_hinge_has_negative_angle():
    # both opposite vertices raised: concave up, centre of curvature on the +normal side
    x = np.array([[[0, 0, 0], [1, 0, 0], [0.5, 1, 0.3], [0.5, -1, 0.3]]], float)
    assert hinge_angles(x)[0][0] < 0


@pytest.mark.parametrize("n", [10, 20])
def test_cylinder_curvature_is_exact_in_the_interior(n):
    R = 10.0
    sh = Sheet.rectangle(2 * R, 2 * R, 2 * n, n)
    M = ShellModel.homogeneous(sh, 1.0, 0.3, 0.1)
    q = M.initial_state()
    x, _ = M.split(q)
    X, Y = sh.points.T
    ang = (X - R) / R
    x[:, 0], x[:, 1], x[:, 2] = R * np.sin(ang), Y, R * (1 - np.cos(ang))
    k, H, K = M.curvatures(q)
    interior = M.topo.interior[M.topo.face_edges].all(1)
    assert np.allclose(k[interior, 0], 1 / R, rtol=2e-3)   # valley: centre on +z side, k > 0
    assert np.allclose(k[interior, 1], 0.0, atol=1e-12)


def test_topology_flaps_and_orientation():
    sh = Sheet.rectangle(2, 1, 2, 1)
    topo = build_topology(sh.triangles)
    assert topo.n_edges == len(sh.triangles) * 3 // 2 + (topo.edge_faces[:, 1] < 0).sum() // 2
    inner = topo.flaps >= 0
    assert inner.sum() == 2 * len(topo.hinge)
