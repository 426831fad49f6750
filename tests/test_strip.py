"""Bilayer strips: the reduced uniform-state model, Timoshenko, and the full shell."""
import numpy as np
import pytest

from shellfem.boundary import gauge_dofs, smooth_perturbation
from shellfem.materials import Fabric, Plastic
from shellfem.model import ShellModel
from shellfem.sheet import Sheet
from shellfem.solver import newton
from shellfem.strip import strip_curvature, timoshenko_curvature


@pytest.mark.parametrize("hp,ratio", [(0.3, 3200.0), (0.45, 1000.0), (0.2, 50.0)])
def test_reduced_model_equals_timoshenko_at_small_misfit(hp, ratio):
    s = 1.0005
    k = strip_curvature(hp, 0.8, s, ratio, plastic_poisson=0.3, fabric_poisson=0.3)
    assert k == pytest.approx(timoshenko_curvature(hp, 0.8, ratio, s - 1), rel=2e-3)


def test_plastic_set_adds_to_the_bend():
    k0 = strip_curvature(0.3, 0.8, 1.35, 1000.0)
    k1 = strip_curvature(0.3, 0.8, 1.35, 1000.0, rest_curvature=0.01)
    assert k1 > k0
    # plastic alone (vanishing fabric) relaxes to its own rest curvature
    assert strip_curvature(0.3, 1e-4, 1.0, 1e9, rest_curvature=0.02) == pytest.approx(0.02, rel=1e-3)


def _free_strip(s, L=40.0, W=4.0, nx=40, ny=4, ratio=3200.0, poisson=0.3):
    sh = Sheet.rectangle(L, W, nx, ny)
    sh = Sheet(sh.points, sh.triangles, thickness_front=np.full(sh.n_triangles, 0.3))
    M = ShellModel.from_materials(sh, Fabric(stretch=s), Plastic(young_modulus=1.05 * ratio, poisson=poisson))
    q = M.initial_state()
    x, _ = M.split(q)
    x[:, 2] += smooth_perturbation(sh.points, 0, 0.01 * L)
    free = np.ones(M.n_dofs, bool)
    free[gauge_dofs(x, np.zeros(0, int))] = False
    r = newton(M, q, free, max_iterations=400)
    return sh, M, r


def test_free_narrow_strip_matches_timoshenko_at_small_misfit():
    s = 1.001
    sh, M, r = _free_strip(s)
    assert r.converged, r.reason
    k, _, _ = M.curvatures(r.q)
    c = sh.points[sh.triangles].mean(1)
    inner = (c[:, 0] > 10) & (c[:, 0] < 30)
    # front plastic: centre of curvature on the fabric side (-z), so k < 0 in the engine's sign
    kappa = -np.median(k[inner], axis=0)
    ref = timoshenko_curvature(0.3, 0.8, 3200.0, s - 1)
    assert kappa[0] == pytest.approx(ref, rel=0.02)
    assert kappa[1] == pytest.approx(ref, rel=0.02)
