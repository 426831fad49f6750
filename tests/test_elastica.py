"""Heavy elastica master curve: limits, a published point, the table against collocation,
and recovery of k_B from synthetic cantilever data."""
import numpy as np
import pytest

from shellfem.errors import SelfshapeError
from validation import elastica as E


def test_small_gamma_is_the_linear_cantilever():
    # linear beam: tip deflection w L^4 / (8 EI), reach L  ->  y/x = Gamma / 8
    for g in (1e-4, 1e-3, 0.05):
        assert E.master_curve(g) == pytest.approx(g / 8, rel=2e-5)
    sol = E.solve_heavy_elastica(0.01)
    assert sol["y"][-1] == pytest.approx(0.01 / 8, rel=1e-4)
    assert sol["theta"][-1] == pytest.approx(0.01 / 6, rel=1e-4)  # tip slope w L^3 / (6 EI)
    # geometric nonlinearity lowers the curve below the linear one
    assert E.master_curve(0.5) < 0.5 / 8


def test_large_gamma_hangs_vertically_with_tension_boundary_layer():
    # tension-dominated bend at the clamp: reach x ~ sqrt(2 / Gamma), drop ~ 1, so y/x ~ sqrt(Gamma / 2)
    err = [abs(E.master_curve(g) / np.sqrt(g / 2) - 1) for g in (1e3, 1e4, 3e4)]
    assert err[1] < 0.02 and err[2] < err[1] < err[0]
    assert E.master_curve_slope(3e4) == pytest.approx(0.5, abs=0.01)
    sol = E.solve_heavy_elastica(1e3)
    assert sol["theta"][-1] == pytest.approx(np.pi / 2, abs=1e-3)
    assert E.master_curve(1e4) > 60


def test_published_point_astm_d1388_cantilever():
    # ASTM D1388 option A / Peirce (1930): the tip of a fabric strip reaches the 41.5 deg incline
    # when the overhang is twice the bending length c = (k_B / w)^(1/3), i.e. Gamma = 2^3 = 8.
    angle = np.degrees(np.arctan(E.master_curve(8.0)))
    assert angle == pytest.approx(41.5, abs=0.25)


@pytest.mark.parametrize("gamma", [0.0123, 0.7, 3.3, 5.9, 6.3, 47.0, 333.0, 900.0])
def test_table_matches_independent_collocation(gamma):
    ref = E.solve_heavy_elastica(gamma)["height_over_width"]
    assert E.master_curve(gamma) == pytest.approx(ref, rel=1e-5)


def test_monotone_vectorised_and_invertible():
    g = np.geomspace(1e-4, E.GAMMA_MAX, 400)
    r = E.master_curve(g)
    assert r.shape == g.shape and np.all(np.diff(r) > 0)
    assert np.allclose(E.master_curve_inverse(r), g, rtol=1e-5)
    assert isinstance(E.master_curve(2.0), float)
    with pytest.raises(SelfshapeError):
        E.master_curve_inverse(-1.0)
    with pytest.raises(SelfshapeError):
        E.master_curve(10 * E.GAMMA_MAX)


def test_bending_stiffness_recovered_from_noisy_cantilever_data():
    rng = np.random.default_rng(7)
    L = np.array([20.0, 30, 40, 50, 60, 80, 100])
    w = np.full(L.size, 1.9e-6)
    for k_true in (0.011, 0.019, 0.032):
        h = E.master_curve(w * L ** 3 / k_true) * (1 + 0.03 * rng.standard_normal(L.size))
        fit = E.fit_bending_stiffness(L, w, h)
        assert fit["k_b"] == pytest.approx(k_true, rel=0.03)
        assert 0 < fit["se"] < 0.03 * k_true
    # noiseless data: exact
    fit = E.fit_bending_stiffness(L, w, E.master_curve(w * L ** 3 / 0.02))
    assert fit["k_b"] == pytest.approx(0.02, rel=1e-7)


def test_bending_fit_rejects_bad_input():
    with pytest.raises(SelfshapeError):
        E.fit_bending_stiffness([20.0], [1e-6], [0.1])
    with pytest.raises(SelfshapeError):
        E.fit_bending_stiffness([20.0, 30.0], [1e-6, 1e-6], [0.1, -0.2])
