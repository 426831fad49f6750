import numpy as np
import pytest

from inverse.spacing import ribbon_spacing, stretch_from_spacing
from shellfem.errors import SelfshapeError


def test_seed_sigma2_max_from_mu2_equal_ribbon_length():
    # seed 5.3.4: mu2_max = l_r with s = 1.6, l_r = 15, w_r = 1.5 gives sigma2_max ~ 1.51;
    # closed form: 1.5 * 0.6 * x / (1.6 - x) = 15  ->  x = 24 / 15.9
    _, sigma2 = stretch_from_spacing(15.0, 15.0, 1.6, 15.0, 1.5)
    assert sigma2 == pytest.approx(24.0 / 15.9, rel=1e-12)
    assert round(float(sigma2), 2) == 1.51


def test_closed_form_values():
    mu1, mu2 = ribbon_spacing(1.1, 1.4, 1.6)
    assert mu1 == pytest.approx(15 * 0.6 * 1.1 / 0.5)
    assert mu2 == pytest.approx(1.5 * 0.6 * 1.4 / 0.2)
    # sigma = 1: no gap (dashes / ribbons touching)
    mu1, mu2 = ribbon_spacing(1.0, 1.0, 1.6, 12.0, 2.0)
    assert mu1 == pytest.approx(12.0) and mu2 == pytest.approx(2.0)


def test_round_trip_vectorised_and_contraction_model():
    rng = np.random.default_rng(0)
    s = 1.6
    sigma1 = rng.uniform(1.0, 1.59, 500)
    sigma2 = rng.uniform(1.0, 1.59, 500)
    mu1, mu2 = ribbon_spacing(sigma1, sigma2, s)
    assert mu1.shape == (500,) and mu2.shape == (500,)
    back1, back2 = stretch_from_spacing(mu1, mu2, s)
    np.testing.assert_allclose(back1, sigma1, rtol=1e-12)
    np.testing.assert_allclose(back2, sigma2, rtol=1e-12)
    # the seed's motif model: a motif mu contracts to l + (mu - l) / s, ratio = sigma
    np.testing.assert_allclose(mu1 / (15.0 + (mu1 - 15.0) / s), sigma1, rtol=1e-12)
    np.testing.assert_allclose(mu2 / (1.5 + (mu2 - 1.5) / s), sigma2, rtol=1e-12)


@pytest.mark.parametrize("args, needle", [
    (([1.2, 1.6], 1.3, 1.6), "sigma1[1]"),
    ((1.2, [1.3, 1.3, 0.99], 1.6), "sigma2[2]"),
    ((1.2, 1.3, 1.0), "pre-stretch s"),
    ((1.2, np.nan, 1.6), "sigma2"),
])
def test_impossible_stretch_is_an_error(args, needle):
    with pytest.raises(SelfshapeError) as err:
        ribbon_spacing(*args)
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_spacing_below_ribbon_size_is_an_error():
    with pytest.raises(SelfshapeError, match=r"mu2\[1\]"):
        stretch_from_spacing(20.0, [3.0, 1.0], 1.6)
    with pytest.raises(SelfshapeError, match="ribbon_width"):
        ribbon_spacing(1.1, 1.1, 1.6, 15.0, 0.0)
