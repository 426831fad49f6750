import numpy as np
import pytest
from scipy.spatial import Delaunay

from shellfem.corotational import RotationPath, rotate


@pytest.fixture(scope="module")
def mesh():
    rng = np.random.default_rng(3)
    P = rng.uniform(0, 10, (150, 2))
    t = Delaunay(P).simplices
    x = np.c_[P, 0.2 * np.sin(P[:, 0])]
    return x, t, RotationPath(t, len(x))


@pytest.mark.parametrize("alpha", [0.3, 1.0, 4.0])
def test_infinitesimal_rotation_becomes_the_exact_finite_rotation(mesh, alpha):
    x, t, rp = mesh
    w = np.array([0.3, -0.2, 0.5])
    c = x.mean(axis=0)
    d = np.cross(w, x - c) + np.array([0.1, 0.2, -0.3])     # rotation + translation
    y = rp.path(x, d, alpha)
    exact = rotate((x - c)[None], (alpha * w)[None])[0] + c + alpha * np.array([0.1, 0.2, -0.3])
    assert np.abs(y - exact).max() < 1e-10
    E0 = np.linalg.norm(x[t[:, 1]] - x[t[:, 0]], axis=1)
    E1 = np.linalg.norm(y[t[:, 1]] - y[t[:, 0]], axis=1)
    assert np.abs(E1 - E0).max() < 1e-10                      # no spurious stretch, unlike x + alpha d


def test_path_is_tangent_to_the_step(mesh):
    x, t, rp = mesh
    d = np.random.default_rng(0).normal(size=x.shape)
    for h in (1e-4, 1e-5):
        err = np.abs((rp.path(x, d, h) - x) / h - d).max()
        assert err < 50 * h * np.abs(d).max() ** 2 + 1e-6     # first order: O(h) deviation


def test_free_strip_rolls_in_few_newton_iterations():
    """Seed Eq. 3.17 strip (examples/strip_narrow.toml) curls into a ring: the straight-line
    Newton needed 60 iterations; along rotation-corrected paths it needs < 30, same state."""
    import os

    from geometry.meshing import mesh_pattern
    from geometry.patterns import load_pattern
    from forward.simulate import simulate_sheet
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    pat = load_pattern(os.path.join(here, "examples", "strip_narrow.toml"))
    sheet = mesh_pattern(pat)
    sim = simulate_sheet(sheet, pat.fabric, pat.plastic, pat.supports, seed=pat.seed)
    assert sim.result.converged
    assert sim.result.iterations < 30
    assert sim.result.energy == pytest.approx(4.4007696, rel=1e-6)
