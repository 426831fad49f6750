"""inverse.coverage: printed area fraction of known layouts, and Eq. 5.15's asked coverage."""
import numpy as np
import pytest
import shapely

from geometry.elements import Ribbon
from inverse.coverage import asked_coverage, printed_fraction, ribbon_union
from inverse.spacing import stretch_from_spacing
from shellfem.errors import SelfshapeError


def _stripes(w, mu, n=40, length=200.0):
    return [Ribbon(path=np.array([[-length / 2, (k + 0.5) * mu], [length / 2, (k + 0.5) * mu]]), width_mm=w)
            for k in range(-n, n)]


def test_parallel_stripes_square_window_exact():
    w, mu = 1.5, 5.0
    region = shapely.box(-60, -60, 60, 60)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-30, 30, size=(50, 2))
    cov = printed_fraction(_stripes(w, mu), region, pts, radius=10.0, window="square")   # side 20 = 4 mu
    np.testing.assert_allclose(cov, w / mu, rtol=0, atol=1e-12)


def test_parallel_stripes_disk_window_mean():
    w, mu = 1.5, 5.0
    region = shapely.box(-60, -60, 60, 60)
    # disk centres spread uniformly over one period across: the mean is w / mu
    pts = np.column_stack([np.zeros(200), np.linspace(0, mu, 200, endpoint=False)])
    cov = printed_fraction(ribbon_union(_stripes(w, mu)), region, pts, radius=10.0)
    assert abs(cov.mean() - w / mu) < 1e-3
    assert np.all(np.abs(cov - w / mu) < 0.1 * w / mu)     # the disk's window noise


def test_window_on_the_outline_counts_only_the_fabric():
    w, mu = 1.5, 5.0
    region = shapely.box(-60, 0, 60, 60)        # stripes at y = (k + 1/2) mu, fabric from y = 0
    cov = printed_fraction(_stripes(w, mu), region, [[0.0, 0.0], [0.0, -20.0]], radius=10.0, window="square")
    assert cov[0] == pytest.approx(w / mu, abs=1e-12)   # the half inside the fabric holds 2 periods
    assert np.isnan(cov[1])                              # the window misses the fabric


def test_staggered_dashes_square_window_exact():
    l, w, mu1, mu2 = 15.0, 1.5, 22.5, 5.0
    rib = []
    for r in range(-20, 20):
        y = (r + 0.5) * mu2
        for k in range(-10, 10):
            xc = (k + 0.5 + 0.5 * (r % 2)) * mu1
            rib.append(Ribbon(path=np.array([[xc - l / 2, y], [xc + l / 2, y]]), width_mm=w))
    region = shapely.box(-150, -80, 150, 80)
    # square of side 2 mu1 = 45 along and 9 mu2 across: 2 x 9 cells of one dash each
    pts = np.array([[0.0, 0.0], [3.3, 1.7], [-11.0, 4.0]])
    cov = printed_fraction(rib, region, pts, radius=22.5, window="square")
    # the window is 45 x 45 mm, i.e. 2 dash periods by 9 rows of 5 mm: exact
    np.testing.assert_allclose(cov, l * w / (mu1 * mu2), atol=1e-12)


def test_asked_coverage_is_eq_5_15():
    s = 1.6
    s1, s2 = stretch_from_spacing(22.5, 6.5, s)
    assert asked_coverage(s1, s2, s) == pytest.approx(15 * 1.5 / (22.5 * 6.5))
    assert asked_coverage(1.0, 1.0, s) == pytest.approx(1.0)       # dashes and rows touching


def test_bad_window():
    with pytest.raises(SelfshapeError):
        printed_fraction([], shapely.box(0, 0, 1, 1), [[0.5, 0.5]], 1.0, window="hex")
    with pytest.raises(SelfshapeError):
        printed_fraction([], shapely.box(0, 0, 1, 1), [[0.5, 0.5]], 0.0)
