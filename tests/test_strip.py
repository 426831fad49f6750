"""Bilayer strips: the reduced uniform-state model, Timoshenko, and the full shell."""
import numpy as np
import pytest

from shellfem.boundary import gauge_dofs, gauge_reaction, smooth_perturbation
from shellfem.materials import Fabric, Plastic
from shellfem.model import ShellModel
from shellfem.sheet import Sheet
from shellfem.newton import newton
from shellfem.strip import strip_curvature, strip_state, timoshenko_curvature


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


def _free_strip(s, L=40.0, W=4.0, nx=40, ny=4, ratio=3200.0, poisson=0.3, gauge_out=None):
    sh = Sheet.rectangle(L, W, nx, ny)
    sh = Sheet(sh.points, sh.triangles, thickness_front=np.full(sh.n_triangles, 0.3))
    M = ShellModel.from_materials(sh, Fabric(stretch=s), Plastic(young_modulus=1.05 * ratio, poisson=poisson))
    q = M.initial_state()
    x, _ = M.split(q)
    x[:, 2] += smooth_perturbation(sh.points, 0, 0.01 * L)
    free = np.ones(M.n_dofs, bool)
    gauge = gauge_dofs(x, np.zeros(0, int))
    free[gauge] = False
    if gauge_out is not None:
        gauge_out.extend(gauge)
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


def test_free_narrow_strip_matches_layered_model_at_large_misfit():
    """s = 1.35, 40 x 2 mm: the full shell's curvature tensor in the strip's middle half
    equals the uniform state of the through-thickness-integrated layered energy (issue 2
    asks for 6 %; measured 0.3 %), isotropic as it must be for a narrow strip. The gauge
    must carry no load (an earlier gauge held a far vertex along its offset: the strip was
    held stretched, the curvatures came out 0.0106 / 0.0206 and Newton crawled)."""
    s, ratio = 1.35, 3200.0
    gauge = []
    sh, M, r = _free_strip(s, L=40.0, W=2.0, nx=80, ny=4, ratio=ratio, poisson=0.5, gauge_out=gauge)
    assert r.converged, r.reason
    assert r.iterations < 80
    assert gauge_reaction(M, r.q, np.array(gauge)) < 1e-9 * r.energy
    a, b = M.cartesian_forms(r.q)
    c = sh.points[sh.triangles].mean(1)
    inner = np.abs(c[:, 0] - 20.0) < 10.0
    S = np.median(np.linalg.solve(a[inner], b[inner]), axis=0)
    z = strip_state(0.3, 0.8, s, ratio, plastic_poisson=0.5, mode="narrow")
    ref = -z[3] / z[0]
    assert -S[0, 0] == pytest.approx(ref, rel=0.01)
    assert -S[1, 1] == pytest.approx(ref, rel=0.01)
    assert abs(S[0, 1]) < 0.01 * ref
    assert np.median(a[inner][:, 0, 0]) == pytest.approx(z[0], rel=1e-3)


def test_many_strips_are_solved_in_bounded_chunks(monkeypatch):
    """strip_state solves at most CHUNK strips at once (a calibration of 100,000 rows asked for
    1.9 GB in one (n, 6, 6) array, issue 19); the chunks give the one-batch answer."""
    import shellfem.strip as strip
    rng = np.random.default_rng(3)
    hp, s, ratio = rng.uniform(0.1, 0.5, 37), rng.uniform(1.05, 1.6, 37), rng.uniform(200, 3000, 37)
    whole = strip.strip_state(hp, 0.8, s, ratio, rest_curvature=0.01)
    monkeypatch.setattr(strip, "CHUNK", 5)
    chunked = strip.strip_state(hp, 0.8, s, ratio, rest_curvature=0.01)
    np.testing.assert_allclose(chunked, whole, rtol=1e-12, atol=1e-15)
    assert strip.strip_state(hp.reshape(37, 1), 0.8, s[:3], 1000.0).shape == (37, 3, 6)
