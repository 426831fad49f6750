"""Energy densities and the assembled shell energy: gradient and Hessian against finite
differences on random states, for every material term."""
import numpy as np
import pytest

import scipy.sparse as sp

from shellfem import layers
from shellfem.assembly import BlockScatter
from shellfem.materials import MEMBRANE_MODELS, Fabric, Plastic, RestState
from shellfem.materials.base import strain_map
from shellfem.materials.neo_hookean import neo_hookean
from shellfem.materials.orthotropic import orthotropic
from shellfem.model import ShellModel
from shellfem.sheet import Sheet
from fd import central_difference   # tests/fd.py


def _sheet(seed=1):
    rng = np.random.default_rng(seed)
    sh = Sheet.rectangle(10, 6, 4, 3)
    m = sh.n_triangles
    tf = np.where(rng.random(m) < 0.4, 0.3, 0.0)
    tb = np.where(rng.random(m) < 0.3, 0.2, 0.0)
    return Sheet(sh.points, sh.triangles, thickness_front=tf, thickness_back=tb)


@pytest.mark.parametrize("model_name", sorted(MEMBRANE_MODELS))
def test_total_energy_gradient_and_hessian(model_name):
    rng = np.random.default_rng(2)
    sh = _sheet()
    fab = Fabric(model=model_name, course_angle_deg=20, areal_weight=1e-5, stretch=(1.3, 1.2))
    M = ShellModel.from_materials(sh, fab, Plastic(rest_curvature=0.01))
    q = M.initial_state()
    x, th = M.split(q)
    x[:, :2] *= 0.85
    x += rng.normal(scale=0.05, size=x.shape)
    th += rng.normal(scale=0.2, size=th.shape)
    E, g, (Hf, Hh) = M.hessian_blocks(q)
    assert np.isfinite(E)
    H = BlockScatter([M.face_dofs, M.hinge_dofs], M.n_dofs, np.ones(M.n_dofs, bool)).matrix([Hf, Hh]).toarray()
    gn, Hn = central_difference(M.energy, q), central_difference(M.gradient, q)
    assert np.abs(g - gn).max() < 1e-6 * np.abs(g).max()
    assert np.abs(H - Hn).max() < 1e-6 * np.abs(H).max()
    assert np.abs(H - H.T).max() < 1e-10 * np.abs(H).max()


def test_hessian_blocks_into_buffers_and_scatter_are_repeatable():
    """Blocks written into reused buffers equal fresh ones; the scatter sums every CSR slot in
    a fixed order (bitwise the same matrix twice; upper triangle = the full matrix's)."""
    rng = np.random.default_rng(4)
    M = ShellModel.from_materials(_sheet(), Fabric(stretch=(1.3, 1.2)), Plastic(rest_curvature=0.01))
    q = M.initial_state()
    q[:3 * M.n_vertices] += rng.normal(scale=0.05, size=3 * M.n_vertices)
    _, _, (Hf, Hh) = M.hessian_blocks(q)
    buffers = M.block_buffers()
    _, _, (Bf, Bh) = M.hessian_blocks(q, out=buffers)
    assert Bf is buffers[0] and Bh is buffers[1]
    assert np.array_equal(Bf, Hf) and np.array_equal(Bh, Hh)
    with pytest.raises(ValueError, match="output buffer"):
        M.hessian_blocks(q, out=(buffers[0][:-1], buffers[1]))
    free = np.ones(M.n_dofs, bool)
    free[:6] = False
    full = BlockScatter([M.face_dofs, M.hinge_dofs], M.n_dofs, free).matrix([Hf, Hh])
    upper = BlockScatter([M.face_dofs, M.hinge_dofs], M.n_dofs, free, upper=True)
    U1, U2 = upper.matrix([Hf, Hh]), upper.matrix([Hf, Hh])
    assert np.array_equal(U1.data, U2.data)
    assert abs(U1 - sp.triu(full)).max() < 1e-12 * abs(full).max()


def test_edge_angle_problem_matches_the_full_model_and_finite_differences():
    """E(theta) at frozen positions: energy differences, gradient and Hessian equal the full
    model's theta part; gradient and Hessian also against finite differences."""
    rng = np.random.default_rng(3)
    M = ShellModel.from_materials(_sheet(), Fabric(stretch=(1.3, 1.2)), Plastic(rest_curvature=0.01))
    q = M.initial_state()
    x, th = M.split(q)
    x[:, :2] *= 0.85
    x += rng.normal(scale=0.05, size=x.shape)
    th += rng.normal(scale=0.2, size=th.shape)
    n, ne = M.n_vertices, M.n_edges
    P = M.edge_angle_problem(q)
    e, g, blocks = P.evaluate(th)
    H = BlockScatter([M.topo.face_edges], ne, np.ones(ne, bool)).matrix([blocks]).toarray()
    _, g_full, (Hf, Hh) = M.hessian_blocks(q)
    free = np.zeros(M.n_dofs, bool)
    free[3 * n:] = True
    H_full = BlockScatter([M.face_dofs, M.hinge_dofs], M.n_dofs, free).matrix([Hf, Hh]).toarray()
    assert np.abs(g - g_full[3 * n:]).max() < 1e-12 * np.abs(g).max()
    assert np.abs(H - H_full).max() < 1e-12 * np.abs(H).max()
    dth = rng.normal(scale=0.05, size=ne)
    q2 = q.copy()
    q2[3 * n:] += dth
    assert P.evaluate(th + dth, 0)[0] - e == pytest.approx(M.energy(q2) - M.energy(q), rel=1e-9)
    gn = central_difference(lambda t: P.evaluate(t, 0)[0], th)
    Hn = central_difference(lambda t: P.evaluate(t, 1)[1], th)
    assert np.abs(g - gn).max() < 1e-6 * np.abs(g).max()
    assert np.abs(H - Hn).max() < 1e-6 * np.abs(H).max()
    assert P.evaluate(th + 2.0, 0)[0] == np.inf          # |psi| beyond 0.49 pi: inadmissible


def test_membrane_models_derivatives():
    rng = np.random.default_rng(7)
    m = 15
    abar = np.tile([1.0, 0.3, 1.2], (m, 1))
    a0 = abar * 1.2 + rng.normal(scale=0.05, size=(m, 3))
    T = strain_map(np.tile(np.array([[1.0, 0.3], [0.0, 1.0]]), (m, 1, 1)))
    params = Fabric().parameters["orthotropic"]
    rest = np.tile(np.array([[0.0, 0.0], [1.0, 0.0], [0.3, 1.0]]), (m, 1, 1))
    rest_metric = np.tile([1.0, 0.3, 1.09], (m, 1))
    state = RestState(points=rest, metric=rest_metric, area=layers.rest_area(rest_metric))
    fab = Fabric(course_angle_deg=25.0)
    registered = [MEMBRANE_MODELS[name](state, fab).energy for name in sorted(MEMBRANE_MODELS)]
    for fun in [lambda a: neo_hookean(a, abar, 1.05, 0.3, 0.8),
                lambda a: orthotropic(a, T, params, 0.3, 0.8, np.ones(m))] + registered:
        W, g, H = fun(a0)
        eps = 1e-7
        for k in range(3):
            ap, am = a0.copy(), a0.copy()
            ap[:, k] += eps
            am[:, k] -= eps
            assert np.allclose((fun(ap)[0] - fun(am)[0]) / (2 * eps), g[:, k], rtol=1e-5, atol=1e-9)
            assert np.allclose((fun(ap)[1] - fun(am)[1]) / (2 * eps), H[:, :, k], rtol=1e-5, atol=1e-9)


def test_layer_integral_matches_quadrature():
    """The closed-form through-thickness integral equals numerical quadrature."""
    rng = np.random.default_rng(0)
    abar = np.array([[1.0, 0.2, 0.9]])
    bbar = np.array([[0.01, 0.0, -0.02]])
    E, nu, z0, z1 = 3.0, 0.35, 0.4, 0.75
    Q, zbar = layers.layer_quadratic(abar, bbar, E, nu, z0, z1)
    qf = layers.QuadraticForm(1)
    qf.add(Q, zbar)
    z = np.concatenate([abar * 1.1, bbar + 0.05], 1) + rng.normal(scale=0.01, size=(1, 6))
    W = qf.evaluate(z)[0][0]
    ainv = np.linalg.inv(layers.sym_to_mat(abar)[0])
    A = ainv @ layers.sym_to_mat(z[:, :3])[0] - np.eye(2)
    B = ainv @ layers.sym_to_mat(z[:, 3:] - bbar)[0]
    zs, w = np.polynomial.legendre.leggauss(6)
    zz = 0.5 * (z1 - z0) * zs + 0.5 * (z1 + z0)
    total = 0.0
    for zi, wi in zip(zz, w):
        eps = 0.5 * A - zi * B
        total += wi * 0.5 * (z1 - z0) * E / 2 * (nu / (1 - nu ** 2) * np.trace(eps) ** 2 + np.trace(eps @ eps) / (1 + nu))
    assert W == pytest.approx(total * layers.rest_area(abar)[0], rel=1e-12)
