"""Thickness sensitivities of the shell: dE/dp, d(dE/dq)/dp and the equilibrium's dq/dp and
adjoint dJ/dp against central finite differences."""
import numpy as np
import pytest

from shellfem.boundary import gauge_dofs, smooth_perturbation
from shellfem.errors import SelfshapeError
from shellfem.materials import Fabric, Plastic
from shellfem.model import ShellModel
from shellfem.newton import newton
from shellfem.sensitivity import (adjoint_gradient, equilibrium_factor, equilibrium_jacobian, thickness_form,
                                  thickness_gradient)
from shellfem.sheet import Sheet

FABRIC = Fabric(stretch=1.3, thickness=0.8, young_modulus=1.05)
PLASTIC = Plastic(young_modulus=80.0, poisson=0.45, rest_curvature=0.002)


def ribbon_sheet(thickness, sides=(1, -1, 1)):
    """30 x 12 mm sheet with three ribbons along x (rows of triangles), one parameter each."""
    base = Sheet.rectangle(30.0, 12.0, 15, 6)
    c = base.points[base.triangles].mean(1)
    param = np.full(base.n_triangles, -1)
    tf, tb = np.zeros(base.n_triangles), np.zeros(base.n_triangles)
    for j, (y0, side) in enumerate(zip((1.0, 5.0, 9.0), sides)):
        sel = (c[:, 1] > y0) & (c[:, 1] < y0 + 2.0) & (c[:, 0] > 3.0) & (c[:, 0] < 27.0)
        param[sel] = j
        (tf if side > 0 else tb)[sel] = thickness[j]
    return Sheet(base.points, base.triangles, thickness_front=tf, thickness_back=tb), param


def model_for(thickness, sides=(1, -1, 1)):
    sheet, param = ribbon_sheet(thickness, sides)
    return ShellModel.from_materials(sheet, FABRIC, PLASTIC, gravity=False), param


def deformed_state(model, seed=3):
    q = model.initial_state()
    x, th = model.split(q)
    rng = np.random.default_rng(seed)
    x[:, 2] += smooth_perturbation(model.sheet.points, seed, 1.5)
    x[:, :2] *= 0.9
    th[:] = rng.normal(scale=0.05, size=len(th))
    return q


def test_energy_and_gradient_derivatives_match_finite_differences():
    t = np.array([0.4, 0.6, 0.5])
    model, param = model_for(t)
    q = deformed_state(model)
    dE, G = thickness_gradient(model, thickness_form(model, FABRIC, PLASTIC), q, param)
    eps = 1e-6
    for j in range(3):
        e = np.zeros(3)
        e[j] = eps
        mp, mm = model_for(t + e)[0], model_for(t - e)[0]
        fd_E = (mp.energy(q) - mm.energy(q)) / (2 * eps)
        fd_g = (mp.gradient(q) - mm.gradient(q)) / (2 * eps)
        assert dE[j] == pytest.approx(fd_E, rel=1e-6)
        col = G[:, j].toarray().ravel()
        assert np.linalg.norm(col - fd_g) <= 1e-6 * np.linalg.norm(fd_g)
        assert np.linalg.norm(fd_g) > 0


def _equilibrium(model, q0=None, free=None):
    q = model.initial_state() if q0 is None else q0.copy()
    x, _ = model.split(q)
    if q0 is None:
        x[:, 2] += smooth_perturbation(model.sheet.points, 0, 0.3)
    if free is None:          # the same gauge for the perturbed solves (the same rigid frame)
        free = np.ones(model.n_dofs, bool)
        free[gauge_dofs(x, np.zeros(0, int))] = False
    r = newton(model, q, free, max_iterations=300, rtol=1e-12)
    assert r.converged, r.reason
    return r.q, free


def test_equilibrium_jacobian_and_adjoint_match_finite_differences():
    t = np.array([0.4, 0.6, 0.5])
    model, param = model_for(t)
    q, free = _equilibrium(model)
    _, G = thickness_gradient(model, thickness_form(model, FABRIC, PLASTIC), q, param)
    solve = equilibrium_factor(model, q, free)
    S = equilibrium_jacobian(solve, G, free)
    # the columns solved in blocks of 2 (a last block of 1) and one by one: the same Jacobian
    for block in (1, 2):
        assert np.allclose(equilibrium_jacobian(solve, G, free, block=block), S, rtol=1e-10,
                           atol=1e-12 * np.abs(S).max())
    # an objective of the positions: J = 1/2 |x - x_ref|^2 over the free position DOFs
    n = model.n_vertices
    rng = np.random.default_rng(1)
    ref = q + rng.normal(scale=0.5, size=len(q))
    pos = np.zeros(model.n_dofs, bool)
    pos[:3 * n] = True

    def J(qq):
        d = (qq - ref)[pos]
        return 0.5 * float(d @ d)

    dJ_dq = np.where(pos, q - ref, 0.0)
    grad = adjoint_gradient(solve, G, free, dJ_dq)
    assert grad == pytest.approx(S.T @ dJ_dq[free], rel=1e-9)
    eps = 1e-4
    for j in range(3):
        e = np.zeros(3)
        e[j] = eps
        qp, _ = _equilibrium(model_for(t + e)[0], q, free)
        qm, _ = _equilibrium(model_for(t - e)[0], q, free)
        fd = (qp - qm)[free] / (2 * eps)
        assert np.linalg.norm(S[:, j] - fd) <= 1e-4 * np.linalg.norm(fd)
        assert grad[j] == pytest.approx((J(qp) - J(qm)) / (2 * eps), rel=1e-4)


def test_both_faces_printed_is_a_clear_error():
    sheet, param = ribbon_sheet([0.4, 0.4, 0.4])
    both = Sheet(sheet.points, sheet.triangles, thickness_front=sheet.thickness_front + sheet.thickness_back,
                 thickness_back=sheet.thickness_front + sheet.thickness_back)
    model = ShellModel.from_materials(both, FABRIC, PLASTIC, gravity=False)
    with pytest.raises(SelfshapeError, match="both faces"):
        thickness_form(model, FABRIC, PLASTIC)
