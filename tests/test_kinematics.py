"""Discrete fundamental forms: exact derivatives (finite differences) and exact geometry."""
import numpy as np
import pytest

from shellfem.kinematics import build_topology, face_chain, face_metrics, hinge_angles
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


def test_face_metrics_are_the_edge_metric_and_the_heights():
    x = np.random.default_rng(4).normal(size=(20, 3, 3))
    a, h = face_metrics(x)
    E1, E2 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]
    assert np.allclose(a, np.stack([(E1 * E1).sum(1), (E1 * E2).sum(1), (E2 * E2).sum(1)], 1), rtol=1e-14)
    area2 = np.linalg.norm(np.cross(E1, E2), axis=1)
    lengths = np.stack([np.linalg.norm(x[:, p] - x[:, q], axis=1) for p, q in ((2, 1), (0, 2), (1, 0))], 1)
    assert np.allclose(h, area2[:, None] / lengths, rtol=1e-14)


def test_face_chain_matches_finite_differences():
    """W(y) = c.y + 1/2 y^T M y per face, y = (a, h, psi = sigma theta) on faces without
    hinges: face_chain's W_q and W_qq against finite differences of W(y(q))."""
    rng = np.random.default_rng(5)
    m = 6
    sign = rng.choice([-1.0, 1.0], size=(m, 3))
    c = rng.normal(size=(m, 9))
    M = rng.normal(size=(m, 9, 9))
    M = M + np.swapaxes(M, 1, 2)
    no_hinge, cols, gphi = -np.ones((m, 3), np.int64), np.zeros((m, 3, 12), np.int64), np.zeros((0, 12))

    def y_of(q):
        a, h = face_metrics(q[:, :9].reshape(m, 3, 3))
        return np.concatenate([a, h, sign * q[:, 18:]], 1)

    def energy(q):
        y = y_of(q)
        return (c * y).sum(1) + 0.5 * np.einsum("mi,mij,mj->m", y, M, y)

    def chain(q, hessian=True):
        y = y_of(q)
        Wy = c + np.einsum("mij,mj->mi", M, y)
        return face_chain(q[:, :9].reshape(m, 3, 3), sign, no_hinge, cols, gphi, Wy, M if hessian else None)

    q = rng.normal(size=(m, 21))
    g, H = chain(q)
    eps = 1e-6
    for d in list(range(9)) + [18, 19, 20]:
        qp, qm = q.copy(), q.copy()
        qp[:, d] += eps
        qm[:, d] -= eps
        assert np.allclose((energy(qp) - energy(qm)) / (2 * eps), g[:, d], rtol=1e-6, atol=1e-6 * np.abs(g).max())
        Hd = (chain(qp, False)[0] - chain(qm, False)[0]) / (2 * eps)
        assert np.abs(Hd - H[:, :, d]).max() < 1e-6 * np.abs(H).max()
    assert np.abs(g[:, 9:18]).max() == 0 and np.abs(H[:, 9:18]).max() == 0     # no hinges: flaps unused
    assert np.array_equal(H, np.swapaxes(H, 1, 2))


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
