"""validation.stats against exact answers: linear least squares, t intervals,
Holm's procedure, permutation-test false-positive rates, pooled replicate noise."""
import numpy as np
import pytest
from scipy import stats as sps

from validation import stats


def test_kfold_partitions_seeded_and_grouped():
    groups = np.repeat(np.arange(12), 3)  # 12 specimens measured 3 times
    folds = stats.kfold(groups.size, 5, seed=3, groups=groups)
    test = np.concatenate([te for _, te in folds])
    assert sorted(test) == list(range(groups.size))  # every row held out exactly once
    for tr, te in folds:
        assert not set(groups[tr]) & set(groups[te])  # a specimen never straddles folds
        assert len(set(tr) | set(te)) == groups.size
    again = stats.kfold(groups.size, 5, seed=3, groups=groups)
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(folds, again))
    other = stats.kfold(groups.size, 5, seed=4, groups=groups)
    assert any(not np.array_equal(a[1], b[1]) for a, b in zip(folds, other))
    assert len(stats.kfold(4, 10, seed=0)) == 4  # at most one fold per group


def test_nls_fit_matches_linear_regression():
    rng = np.random.default_rng(0)
    x = np.linspace(0, 1, 40)
    X = np.stack([np.ones_like(x), x], 1)
    y = 1.5 - 2.0 * x + 0.1 * rng.standard_normal(x.size)
    beta, res, *_ = np.linalg.lstsq(X, y, rcond=None)
    s2 = res[0] / (x.size - 2)
    se = np.sqrt(np.diag(s2 * np.linalg.inv(X.T @ X)))
    fun = lambda t: X @ t - y  # noqa: E731
    batch = lambda T: T @ X.T - y  # noqa: E731
    for b in (None, batch):
        r = stats.nls_fit(fun, [0.0, 0.0], [-10, -10], [10, 10], batch_fn=b)
        assert np.allclose(r["theta"], beta, atol=1e-7)
        assert np.allclose(r["se"], se, rtol=1e-5)


def test_profile_interval_equals_t_interval_for_linear_model():
    rng = np.random.default_rng(1)
    x = np.linspace(0.5, 2, 25)
    y = 3.0 * x + 0.2 * rng.standard_normal(x.size)  # one-parameter model y = b x
    b = x @ y / (x @ x)
    ssr = lambda t: float(((y - t * x) ** 2).sum())  # noqa: E731
    n = x.size
    se = np.sqrt(ssr(b) / (n - 1) / (x @ x))
    half = sps.t.ppf(0.975, n - 1) * se
    lo, hi = stats.profile_interval(ssr, b, ssr(b), n, 1, 0.0, 10.0)
    assert lo == pytest.approx(b - half, rel=1e-8)
    assert hi == pytest.approx(b + half, rel=1e-8)


def test_holm_adjustment():
    # textbook example: p = (0.01, 0.04, 0.03, 0.005), m = 4
    adj = stats.holm([0.01, 0.04, 0.03, 0.005])
    assert np.allclose(adj, [0.03, 0.06, 0.06, 0.02])
    assert np.allclose(stats.holm([0.5, 0.9]), [1.0, 1.0])


def test_permutation_f_test_false_positive_rate_and_power():
    rng = np.random.default_rng(2)
    labels = np.repeat(np.arange(4), 10)
    p_null = np.array([stats.permutation_f_test(rng.standard_normal(40), labels, n_perm=199, seed=k)[1]
                       for k in range(300)])
    rate = np.mean(p_null < 0.05)
    assert 0.02 < rate < 0.09  # nominal 5 %; binomial(300, 0.05) 99.9 % range
    shifted = rng.standard_normal(40) + 0.8 * (labels == 2)
    f, p = stats.permutation_f_test(shifted, labels, n_perm=1999, seed=0)
    ref = sps.f_oneway(*[shifted[labels == g] for g in range(4)])
    assert f == pytest.approx(ref.statistic)
    assert abs(p - ref.pvalue) < 0.03  # normal residuals: the permutation and F distributions agree
    assert stats.permutation_f_test(shifted + 1.5 * (labels == 2), labels, n_perm=499, seed=0)[1] < 0.01


def test_residual_tests_holm_and_skips():
    rng = np.random.default_rng(3)
    n = 60
    cov = {"const": np.full(n, 2.0), "noise": rng.standard_normal(n), "step": np.repeat([0.0, 1.0], n // 2),
           "partial": np.where(np.arange(n) < 40, rng.standard_normal(n), np.nan)}
    r = rng.standard_normal(n) * 0.1 + 0.3 * cov["step"]
    out = {o["name"]: o for o in stats.residual_tests(r, cov, n_perm=499, seed=0)}
    assert not out["const"]["tested"] and "constant" in out["const"]["reason"]
    assert out["step"]["significant"]
    assert not out["noise"]["significant"]
    assert out["noise"]["method"].endswith("quantile bins")
    tested = [o for o in out.values() if o["tested"]]
    assert np.allclose(sorted(o["p_holm"] for o in tested), sorted(stats.holm([o["p"] for o in tested])))


def test_noise_level_pooled_replicates():
    v = np.array([1.0, 2.0, 3.0, 10.0, 12.0, 5.0, 5.0, 5.0, 7.0])
    g = np.array([0, 0, 0, 1, 1, 2, 2, 2, 2])
    ss = 2.0 + 2.0 + 3.0  # within-group sums of squares: 2, 2, 3
    r = stats.noise_level(v, g, min_dof=5)
    assert r["dof"] == 6 and r["sigma"] == pytest.approx(np.sqrt(ss / 6))
    assert stats.noise_level(v, np.arange(9)) is None


def test_errors_and_gains():
    assert stats.rel_rms([1.1, 1.9], [1.0, 2.0]) == pytest.approx(np.sqrt(0.01) / np.sqrt(2.5))
    m, se = stats.paired_gain([1.0, 2.0, 3.0], [0.0, 0.0, 0.0])
    assert m == pytest.approx(14 / 3) and se == pytest.approx(np.std([1, 4, 9], ddof=1) / np.sqrt(3))
    ic = stats.information_criteria(2.0, 10, 2)
    assert ic["aic"] == pytest.approx(10 * np.log(0.2) + 4)
    assert ic["bic"] == pytest.approx(10 * np.log(0.2) + 2 * np.log(10))
