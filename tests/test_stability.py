"""The distance of an equilibrium from a fold (shellfem.stability): the smallest eigenvalue of the
position stiffness per unit area against a dense reference, and its thickness sensitivity
against finite differences of re-solved equilibria."""
import numpy as np
import pytest
import scipy.linalg as sla

from ribbon_sheets import ribbon_checkerboard, sheet_at
from shellfem.assembly import symmetric_matvec
from shellfem.boundary import gauge_dofs, smooth_perturbation
from shellfem.materials import Fabric, Plastic
from shellfem.model import ShellModel, nodal_loads
from shellfem.newton import newton
from shellfem.sensitivity import equilibrium_factor, free_hessian, thickness_form, thickness_gradient
from shellfem.stability import lowest_mode, mode_sensitivity

FABRIC = Fabric(stretch=1.3)
PLASTIC = Plastic(young_modulus=1180.0)
P0 = np.array([0.5, 0.7, 0.6, 0.8])


def two_by_two():
    """A 24 x 24 mm sheet with four 8 x 2 mm front ribbons (2 x 2 checkerboard of directions);
    one parameter per ribbon."""
    return ribbon_checkerboard(24.0, 12, 2, 4.0)


def model_at(base, param, p):
    return ShellModel.from_materials(sheet_at(base, param, p), FABRIC, PLASTIC)


def equilibrium(model, q0, free):
    r = newton(model, q0, free, max_iterations=300, rtol=1e-12)
    assert r.converged, r.reason
    return r.q


@pytest.fixture(scope="module")
def state():
    base, param = two_by_two()
    model = model_at(base, param, P0)
    q = model.initial_state()
    x, _ = model.split(q)
    x[:, 2] += smooth_perturbation(base.points, 0, 0.3)
    free = np.ones(model.n_dofs, bool)
    free[gauge_dofs(x, np.zeros(0, int))] = False
    return base, param, free, equilibrium(model, q, free)


def test_the_lowest_mode_is_the_dense_schur_complements_smallest_eigenvalue(state):
    base, param, free, q = state
    model = model_at(base, param, P0)
    lam, u = lowest_mode(model, q, free, tol=1e-10)
    n = base.n_vertices
    Hu = free_hessian(model, q, free).toarray()
    H = Hu + Hu.T - np.diag(np.diag(Hu))
    idx = np.flatnonzero(free)
    xs = idx < 3 * n
    K = H[np.ix_(xs, xs)] - H[np.ix_(xs, ~xs)] @ np.linalg.solve(H[np.ix_(~xs, ~xs)], H[np.ix_(~xs, xs)])
    m = np.repeat(nodal_loads(base, 1.0), 3)[idx[xs]]
    ref = sla.eigh(K, np.diag(m), eigvals_only=True, subset_by_index=[0, 0])[0]
    assert ref > 0
    assert lam == pytest.approx(ref, rel=1e-7)
    # the mode: H u = (lambda M v, 0) on the free DOFs, v^T M v = 1, zero on held DOFs
    r = symmetric_matvec(Hu, u[free])
    v = u[free][xs]
    assert v @ (m * v) == pytest.approx(1.0, rel=1e-10)
    assert np.linalg.norm(r[xs] - lam * m * v) < 1e-6 * np.linalg.norm(lam * m * v)
    assert np.linalg.norm(r[~xs]) < 1e-6 * np.linalg.norm(lam * m * v)
    assert np.all(u[~free] == 0)


def test_the_modes_thickness_sensitivity_equals_finite_differences_of_re_solved_equilibria(state):
    """dlambda/dp by the adjoint formula against central differences (p_j +- 1e-4 mm, each
    equilibrium re-solved to 1e-12 and its lowest eigenvalue recomputed)."""
    base, param, free, q = state
    model = model_at(base, param, P0)
    solve = equilibrium_factor(model, q, free)
    lam, u = lowest_mode(model, q, free, solve, tol=1e-12)
    form = thickness_form(model, FABRIC, PLASTIC)
    d = mode_sensitivity(model, q, free, u, lambda s: thickness_gradient(model, form, s, param, 4)[1], solve)
    h = 1e-4
    fd = np.zeros(4)
    for j in range(4):
        vals = []
        for sgn in (1, -1):
            p = P0.copy()
            p[j] += sgn * h
            mj = model_at(base, param, p)
            qj = equilibrium(mj, q, free)
            vals.append(lowest_mode(mj, qj, free, tol=1e-12, v0=u)[0])
        fd[j] = (vals[0] - vals[1]) / (2 * h)
    assert np.max(np.abs(fd)) > 1e-3 * lam         # the thicknesses do move the mode
    assert np.allclose(d, fd, rtol=2e-3, atol=2e-3 * np.max(np.abs(fd)))
