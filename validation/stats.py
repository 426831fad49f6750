"""Statistics for the validation loop: seeded (grouped) K-fold splits, nonlinear
least squares with standard errors, profile-likelihood intervals, residual tests
against covariates with a stated family-wise false-positive rate, noise estimates.

All random choices take an explicit seed. Arrays in, arrays/dicts out.
"""
from __future__ import annotations

import numpy as np
from scipy import optimize, stats

from shellfem.errors import SelfshapeError

# ---------------------------------------------------------------------------
# splits and errors


def kfold(n, k, seed, groups=None):
    """Seeded K-fold split of n rows: list of (train_idx, test_idx). With ``groups``
    (one label per row) all rows of a group fall in the same fold."""
    rng = np.random.default_rng(seed)
    if groups is None:
        groups = np.arange(n)
    _, g = np.unique(np.asarray(groups).astype(str), return_inverse=True)
    n_groups = int(g.max()) + 1 if g.size else 0
    if n_groups < 2:
        raise SelfshapeError(f"a K-fold split needs at least 2 groups (specimens), got {n_groups} "
                             f"in {n} row(s)")
    k = int(max(2, min(k, n_groups)))
    fold_of_group = np.empty(n_groups, int)
    fold_of_group[rng.permutation(n_groups)] = np.arange(n_groups) % k
    fold = fold_of_group[g]
    return [(np.flatnonzero(fold != j), np.flatnonzero(fold == j)) for j in range(k)]


def rel_rms(predicted, measured) -> float:
    """Relative RMS error: RMS(predicted - measured) / RMS(measured)."""
    p, m = np.asarray(predicted, float), np.asarray(measured, float)
    return float(np.sqrt(np.mean((p - m) ** 2)) / np.sqrt(np.mean(m ** 2)))


def paired_gain(err_a, err_b):
    """Mean and standard error of err_a^2 - err_b^2 over rows (> 0: b predicts better)."""
    d = np.asarray(err_a, float) ** 2 - np.asarray(err_b, float) ** 2
    return float(d.mean()), float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else float("inf")


def information_criteria(ssr, n, p) -> dict:
    """AIC, corrected AIC and BIC of a Gaussian least-squares fit with p parameters."""
    ll = n * np.log(max(ssr, 1e-300) / n)
    aic = ll + 2 * p
    aicc = aic + (2 * p * (p + 1) / (n - p - 1) if n - p - 1 > 0 else np.inf)
    return {"aic": float(aic), "aicc": float(aicc), "bic": float(ll + p * np.log(n))}


# ---------------------------------------------------------------------------
# nonlinear least squares


def nls_fit(residual_fn, theta0, lower, upper, max_nfev=200, batch_fn=None):
    """Minimise sum(residual_fn(theta)^2) within bounds (scipy trf). ``batch_fn``
    (optional) maps a stack of parameter vectors (m, p) to residuals (m, n); the
    forward-difference Jacobian then costs one call. Returns dict: theta, se (from
    sigma^2 (J^T J)^+), cov, ssr, n, dof, sigma, success, residuals, at_bound.

    Honest errors: dof = n - p; with no residual degrees of freedom (dof <= 0) sigma,
    se and cov are NaN (not identifiable), never a number from a made-up dof. at_bound
    (per parameter) marks an estimate within 1e-6 of its search range's width from a
    bound: not a converged interior estimate (its se assumes one)."""
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    t0 = np.clip(np.asarray(theta0, float), lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    jac = "2-point"
    if batch_fn is not None:
        last = {}

        def fun(t):
            last["x"], last["f"] = t.copy(), residual_fn(t)
            return last["f"]

        def jac(t):
            h = 1e-7 * np.maximum(1.0, np.abs(t))
            h = np.where(t + h > hi, -h, h)  # stay inside the bounds
            f0 = last["f"] if "x" in last and np.array_equal(last["x"], t) else residual_fn(t)
            f = batch_fn(t[None, :] + np.diag(h))
            return ((f - f0[None, :]) / h[:, None]).T
    else:
        fun = residual_fn
    r = optimize.least_squares(fun, t0, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac",
                               max_nfev=max_nfev, xtol=1e-8, ftol=1e-8, gtol=1e-8)
    n, p = r.fun.size, t0.size
    ssr = float(r.fun @ r.fun)
    dof = n - p
    s2 = ssr / dof if dof > 0 else float("nan")
    cov = s2 * np.linalg.pinv(r.jac.T @ r.jac)
    width = np.where(np.isfinite(hi - lo), hi - lo, np.maximum(1.0, np.abs(r.x)))
    at_bound = (r.x <= lo + 1e-6 * width) | (r.x >= hi - 1e-6 * width)
    return {"theta": r.x, "cov": cov, "se": np.sqrt(np.maximum(np.diag(cov), 0.0)),
            "ssr": ssr, "n": n, "dof": dof, "sigma": float(np.sqrt(s2)), "success": bool(r.success),
            "residuals": r.fun, "at_bound": at_bound}


def profile_interval(ssr_of, t_hat, ssr_min, n, p, lo, hi, level=0.95):
    """Profile-likelihood interval of one parameter: the t with
    ssr_of(t) <= ssr_min (1 + F(1, n-p; level) / (n-p)), searched in [lo, hi]
    (``ssr_of`` re-optimises any other parameters). Returns (low, high); an end
    that does not close inside [lo, hi] is None (the data do not bound the parameter on
    that side). Needs n > p (raises ValueError otherwise: no interval without residual
    degrees of freedom)."""
    dof = n - p
    if dof <= 0:
        raise ValueError(f"profile_interval: no residual degrees of freedom (n = {n}, p = {p})")
    limit = ssr_min * (1 + stats.f.ppf(level, 1, dof) / dof)
    g = lambda t: ssr_of(t) - limit  # noqa: E731
    ends = []
    for end in (lo, hi):
        if not g(end) > 0:
            ends.append(None)
        else:
            ends.append(optimize.brentq(g, min(t_hat, end), max(t_hat, end), xtol=1e-10 * (1 + abs(t_hat))))
    return tuple(ends)


# ---------------------------------------------------------------------------
# residual structure


def holm(p_values):
    """Holm-Bonferroni adjusted p-values (family-wise error control)."""
    p = np.asarray(p_values, float)
    m = p.size
    if m == 0:
        return p
    order = np.argsort(p)
    adj = np.empty(m)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, (m - rank) * p[i])
        adj[i] = min(1.0, running)
    return adj


def groups_of(values, max_levels=8, n_bins=None):
    """Integer group labels for a covariate: its distinct values when there are at
    most ``max_levels``, else quantile bins (by rank, ties kept together)."""
    v = np.asarray(values)
    uniq, inv = np.unique(v.astype(str) if v.dtype == object else v, return_inverse=True)
    if uniq.size <= max_levels:
        return inv, "levels"
    n = v.size
    nb = n_bins or int(min(6, max(2, n // 10)))
    ranks = np.searchsorted(np.sort(v), v, side="left")  # ties share a rank
    return np.minimum(ranks * nb // n, nb - 1), f"{nb} quantile bins"


def _f_statistics(R, onehot):
    """One-way ANOVA F for each row of R (B x n) against groups (n x g one-hot)."""
    n, g = onehot.shape
    counts = onehot.sum(0)
    sums = R @ onehot
    grand = R.sum(1, keepdims=True) / n
    between = (sums ** 2 / counts).sum(1) - n * grand[:, 0] ** 2
    total = (R ** 2).sum(1) - n * grand[:, 0] ** 2
    within = np.maximum(total - between, 1e-300)
    return (between / (g - 1)) / (within / (n - g))


def permutation_f_test(residuals, labels, n_perm=999, seed=0):
    """Permutation p-value of the one-way F statistic of residuals on group labels.
    Exact false-positive rate under exchangeable residuals. Returns (F, p)."""
    r = np.asarray(residuals, float)
    _, lab = np.unique(labels, return_inverse=True)
    g = lab.max() + 1
    if g < 2 or g >= r.size:
        return float("nan"), 1.0
    onehot = np.zeros((r.size, g))
    onehot[np.arange(r.size), lab] = 1.0
    f_obs = _f_statistics(r[None, :], onehot)[0]
    rng = np.random.default_rng(seed)
    perms = np.argsort(rng.random((n_perm, r.size)), axis=1)
    f_perm = _f_statistics(r[perms], onehot)
    return float(f_obs), float((1 + np.count_nonzero(f_perm >= f_obs * (1 - 1e-12))) / (n_perm + 1))


def within_group_slope_test(residuals, x, groups, n_perm=999, seed=0):
    """Does x explain residual scatter inside groups? Statistic |corr| of the
    group-demeaned residuals and x; p-value by permuting x within groups (exact
    false-positive rate under within-group exchangeability). Returns (corr, p)."""
    r, x = np.asarray(residuals, float), np.asarray(x, float)
    _, g = np.unique(np.asarray(groups), return_inverse=True)
    cnt = np.bincount(g)
    rd = r - (np.bincount(g, r) / cnt)[g]
    xd = x - (np.bincount(g, x) / cnt)[g]
    if xd @ xd <= 0 or rd @ rd <= 0:
        return 0.0, 1.0
    stat = lambda xv: abs(rd @ xv) / np.sqrt((rd @ rd) * (xv @ xv))  # noqa: E731
    obs = stat(xd)
    rng = np.random.default_rng(seed)
    home = np.argsort(g, kind="stable")
    hits = 0
    for _ in range(n_perm):
        xp = np.empty_like(xd)
        xp[home] = xd[np.lexsort((rng.random(g.size), g))]
        hits += stat(xp) >= obs * (1 - 1e-12)
    return float(obs), float((1 + hits) / (n_perm + 1))


def residual_tests(residuals, covariates, alpha=0.05, n_perm=999, seed=0, within=None):
    """Test residuals for structure against each covariate.

    covariates: {name: values} (NaN entries are left out of that covariate's test).
    Each varying covariate is grouped (levels, or quantile bins when continuous) and
    tested by a permutation F test; p-values are Holm-adjusted over the covariates
    tested, so the family-wise false-positive rate is ``alpha``. ``within``:
    optional (groups, {name: values}) of per-row covariates tested inside groups
    (within_group_slope_test), in the same Holm family. Returns a list of dicts:
    name, tested, method, F or corr, p, p_holm, significant (or why not tested)."""
    out = []
    for j, (name, vals) in enumerate(covariates.items()):
        v = np.asarray(vals)
        keep = ~np.isnan(v.astype(float)) if v.dtype != object else np.ones(v.size, bool)
        rr, vv = np.asarray(residuals, float)[keep], v[keep]
        if rr.size < 6:
            out.append({"name": name, "tested": False, "reason": "fewer than 6 values"})
            continue
        labels, method = groups_of(vv)
        if np.unique(labels).size < 2:
            out.append({"name": name, "tested": False, "reason": "constant in the data"})
            continue
        f, p = permutation_f_test(rr, labels, n_perm=n_perm, seed=seed + 7919 * (j + 1))
        out.append({"name": name, "tested": True, "method": f"permutation F test, {method}",
                    "F": f, "p": p})
    if within is not None:
        groups, extra = within
        for j, (name, vals) in enumerate(extra.items()):
            v = np.asarray(vals, float)
            keep = np.isfinite(v)
            c, p = within_group_slope_test(np.asarray(residuals, float)[keep], v[keep], np.asarray(groups)[keep],
                                           n_perm=n_perm, seed=seed + 104729 * (j + 1))
            out.append({"name": f"{name} within replicate groups", "tested": True,
                        "method": "permutation test of the within-group correlation", "corr": c, "p": p})
    tested = [o for o in out if o["tested"]]
    adj = holm([o["p"] for o in tested])
    for o, a in zip(tested, adj):
        o["p_holm"] = float(a)
        o["significant"] = bool(a < alpha)
    return out


def noise_level(values, groups, min_dof=5):
    """Pure-error noise estimate from replicate groups: pooled within-group standard
    deviation of ``values`` (e.g. measured curvatures or residuals). Returns
    {"sigma", "dof", "method"} or None when the replicates give < min_dof."""
    v = np.asarray(values, float)
    _, g = np.unique(np.asarray(groups).astype(str), return_inverse=True)
    counts = np.bincount(g)
    means = np.bincount(g, v) / counts
    dof = int(v.size - counts.size)
    if dof < min_dof:
        return None
    ss = float(((v - means[g]) ** 2).sum())
    return {"sigma": float(np.sqrt(ss / dof)), "dof": dof, "method": "pooled replicate standard deviation"}
