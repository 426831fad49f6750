"""Heavy elastica: a cantilever clamped horizontally, bending under its own weight.

Nondimensional problem (arc length s in [0, 1], theta the angle below horizontal):

    theta'' = -Gamma (1 - s) cos(theta),   theta(0) = 0,   theta'(1) = 0,

with the gravito-bending parameter Gamma = w L^3 / k_B (w areal weight N/mm^2, L free
length mm, k_B bending stiffness N mm = moment per unit width per unit curvature).
The observable is the aspect ratio of the bounding rectangle of the hanging part,
height / width = (tip drop) / (horizontal reach of the tip); theta stays in [0, pi/2)
so x and the drop are monotone along s and the tip defines the rectangle.

The master curve Gamma -> height/width (Romero et al. 2021) is computed without
shooting: scaling the distance from the tip, tau = Gamma^(1/3) (1 - s), turns the
problem into ONE universal initial value problem per tip angle,

    d^2 theta / d tau^2 = -tau cos(theta),  theta(0) = theta_tip,  theta'(0) = 0,

integrated until theta = 0 (the clamp) at tau*, which gives Gamma = tau*^3. Near the
vertical (large Gamma) the angle from the vertical phi = pi/2 - theta is integrated
instead, scaled by phi_tip so that tips within 1e-130 of vertical stay representable.
"""
from __future__ import annotations

import functools

import numpy as np
from scipy.integrate import solve_bvp, solve_ivp
from scipy.interpolate import PchipInterpolator
from scipy.optimize import least_squares

from shellfem.errors import SelfshapeError

#: Gamma range covered by the tabulated master curve; below it the linear
#: cantilever limit height/width = Gamma/8 is used (relative error < 2e-5).
GAMMA_MIN = 1e-3
GAMMA_MAX = 3e4

_RTOL = 1e-10


def _from_tip_theta(theta_tip: float) -> tuple[float, float]:
    """(Gamma, height/width) of the solution whose tip angle below horizontal is theta_tip."""
    def rhs(t, y):
        c = np.cos(y[0])
        return [y[1], -t * c, c, np.sin(y[0])]

    def clamp(t, y):
        return y[0]
    clamp.terminal, clamp.direction = True, -1
    sol = solve_ivp(rhs, (0.0, 1e4), [theta_tip, 0.0, 0.0, 0.0], events=clamp,
                    rtol=_RTOL, atol=1e-14, method="DOP853")
    t, y = sol.t_events[0][0], sol.y_events[0][0]
    return t ** 3, y[3] / y[2]


def _from_tip_phi(phi_tip: float) -> tuple[float, float]:
    """(Gamma, height/width) of the solution whose tip is phi_tip from the vertical.

    State z = phi / phi_tip (z(0) = 1, growing), so tiny phi_tip never underflows.
    """
    p = phi_tip

    def rhs(t, y):
        sp = np.sin(p * y[0]) / p
        return [y[1], t * sp, sp, np.cos(p * y[0])]

    def clamp(t, y):
        return p * y[0] - 0.5 * np.pi
    clamp.terminal, clamp.direction = True, 1
    sol = solve_ivp(rhs, (0.0, 1e4), [1.0, 0.0, 0.0, 0.0], events=clamp,
                    rtol=_RTOL, atol=1e-12, method="DOP853")
    t, y = sol.t_events[0][0], sol.y_events[0][0]
    return t ** 3, y[3] / (p * y[2])


def _sample_branch(solve, tips: np.ndarray, max_step: float) -> np.ndarray:
    """Rows (Gamma, height/width) for tips, refined (geometric midpoints of tips)
    until consecutive log Gamma differ by at most max_step. tips must give increasing Gamma."""
    tips = np.asarray(tips, dtype=float)
    rows = np.array([solve(t) for t in tips])
    for _ in range(20):
        gaps = np.flatnonzero(np.diff(np.log(rows[:, 0])) > max_step)
        if gaps.size == 0:
            return rows
        mids = np.sqrt(tips[gaps] * tips[gaps + 1])
        new = np.array([solve(t) for t in mids])
        tips = np.insert(tips, gaps + 1, mids)
        rows = np.insert(rows, gaps + 1, new, axis=0)
    raise RuntimeError("heavy elastica table refinement did not converge")


@functools.lru_cache(maxsize=1)
def master_curve_table() -> tuple[np.ndarray, np.ndarray]:
    """Dense table (Gamma, height/width), increasing in both, covering [GAMMA_MIN, GAMMA_MAX].

    Computed once per process (~1-2 s) and cached; log-spacing of Gamma <= 0.1.
    """
    step = 0.1
    # tip angle theta_tip ~ Gamma / 6 for small Gamma: log-spaced tips give log-spaced Gamma
    low = _sample_branch(_from_tip_theta, np.geomspace(GAMMA_MIN / 12.0, np.pi / 4, 90), step)
    # nearer the vertical, log(phi_tip) ~ -(2/3) sqrt(Gamma) (WKB): invert that for the spacing
    g_targets = np.exp(np.arange(np.log(6.0), np.log(1.1 * GAMMA_MAX), step))
    phi_tips = (np.pi / 4) * np.exp(-(2.0 / 3.0) * (np.sqrt(g_targets) - np.sqrt(6.0)))
    high = _sample_branch(_from_tip_phi, np.concatenate([[np.pi / 4], phi_tips[1:]]), step)
    g, r = np.vstack([low, high[1:]]).T
    if not (np.all(np.diff(g) > 0) and np.all(np.diff(r) > 0) and g[0] <= GAMMA_MIN and g[-1] >= GAMMA_MAX
            and np.diff(np.log(g)).max() <= step):
        raise RuntimeError("heavy elastica table is not monotone or does not cover its range")
    return g, r


@functools.lru_cache(maxsize=1)
def _interpolants():
    g, r = master_curve_table()
    lg, lr = np.log(g), np.log(r)
    return (PchipInterpolator(lg, lr, extrapolate=False),
            PchipInterpolator(lr, lg, extrapolate=False),
            PchipInterpolator(lg, lr, extrapolate=False).derivative())


def master_curve(gamma) -> np.ndarray:
    """height/width of the hanging part for gravito-bending parameter(s) Gamma = w L^3 / k_B.

    Vectorised; monotone increasing. Gamma below GAMMA_MIN uses the linear limit
    Gamma/8; Gamma above GAMMA_MAX raises SelfshapeError.
    """
    g = np.asarray(gamma, dtype=float)
    if np.any(~np.isfinite(g)) or np.any(g < 0):
        raise SelfshapeError("master_curve: Gamma must be finite and >= 0")
    if np.any(g > GAMMA_MAX):
        raise SelfshapeError(f"master_curve: Gamma {g.max():.3g} above the tabulated range ({GAMMA_MAX:g})")
    fwd, _, _ = _interpolants()
    small = g < GAMMA_MIN
    out = np.where(small, g / 8.0, 0.0)
    big = ~small
    out[big] = np.exp(fwd(np.log(g[big])))
    return out if out.ndim else float(out)


def master_curve_slope(gamma) -> np.ndarray:
    """d log(height/width) / d log(Gamma) (1 in the linear limit)."""
    g = np.asarray(gamma, dtype=float)
    _, _, dfwd = _interpolants()
    small = g < GAMMA_MIN
    out = np.ones_like(g)
    out[~small] = dfwd(np.log(g[~small]))
    return out if out.ndim else float(out)


def master_curve_inverse(height_over_width) -> np.ndarray:
    """Gamma giving the aspect ratio(s) height/width (inverse of master_curve)."""
    r = np.asarray(height_over_width, dtype=float)
    g_tab, r_tab = master_curve_table()
    if np.any(~np.isfinite(r)) or np.any(r <= 0):
        raise SelfshapeError("master_curve_inverse: height/width must be finite and > 0")
    if np.any(r > r_tab[-1]):
        raise SelfshapeError(f"master_curve_inverse: height/width {r.max():.4g} above the tabulated "
                             f"range ({r_tab[-1]:.4g}, Gamma = {GAMMA_MAX:g})")
    _, inv, _ = _interpolants()
    small = r < r_tab[0]
    out = np.where(small, 8.0 * r, 0.0)
    out[~small] = np.exp(inv(np.log(r[~small])))
    return out if out.ndim else float(out)


def solve_heavy_elastica(gamma: float, n: int = 201) -> dict:
    """Shape of the heavy elastica by collocation (scipy solve_bvp) with continuation in Gamma.

    Independent of the master-curve table (used to check it). Returns s, theta, x, y
    (nondimensional, y downwards) and height_over_width = y[-1] / x[-1].
    """
    gamma = float(gamma)
    if not (np.isfinite(gamma) and 0 < gamma <= 1e4):
        raise SelfshapeError(f"solve_heavy_elastica: Gamma must be in (0, 1e4], got {gamma!r}")
    s = np.linspace(0.0, 1.0, n)
    y = np.zeros((4, n))
    y[2] = s

    def bc(a, b):
        return np.array([a[0], b[1], a[2], a[3]])

    steps = np.geomspace(min(gamma, 1.0), gamma, max(2, int(np.ceil(np.log(max(gamma, 1.0)) / np.log(1.5))) + 1))
    for g in steps:
        def rhs(t, u, g=g):
            c = np.cos(u[0])
            return np.vstack([u[1], -g * (1.0 - t) * c, c, np.sin(u[0])])
        sol = solve_bvp(rhs, bc, s, y, tol=1e-9, max_nodes=200000)
        if not sol.success:
            raise RuntimeError(f"heavy elastica collocation failed at Gamma = {g:g}: {sol.message}")
        s, y = sol.x, sol.y
    return {"s": s, "theta": y[0], "x": y[2], "y": y[3], "height_over_width": y[3, -1] / y[2, -1]}


def fit_bending_stiffness(free_length_mm, areal_weight_n_per_mm2, height_over_width) -> dict:
    """Least-squares k_B (N mm) placing the points (w L^3 / k_B, y/x) on the master curve.

    Residuals are log(master_curve(Gamma_i)) - log(y/x_i) (relative errors, so short and
    long ribbons weigh alike). Standard error from the Jacobian: se(log k_B) =
    sqrt(s^2 / J^T J), s^2 = SSR / (n - 1). Needs at least 2 points.
    """
    L = np.asarray(free_length_mm, dtype=float)
    w = np.asarray(areal_weight_n_per_mm2, dtype=float)
    h = np.asarray(height_over_width, dtype=float)
    if not (L.shape == w.shape == h.shape) or L.ndim != 1:
        raise SelfshapeError("fit_bending_stiffness: inputs must be 1-D arrays of equal length")
    if L.size < 2:
        raise SelfshapeError("fit_bending_stiffness: needs at least 2 free lengths for a standard error")
    load = w * L ** 3
    k0 = load / master_curve_inverse(h)  # one estimate per point; raises on bad h
    g_lo = min(GAMMA_MIN, master_curve_inverse(h.min()))
    # keep every Gamma inside the table during the search
    u_lo = np.log(load.max() / GAMMA_MAX) + 1e-9
    u_hi = np.log(load.min() / g_lo) + 5.0
    u0 = float(np.clip(np.median(np.log(k0)), u_lo + 1e-6, u_hi - 1e-6))
    lh = np.log(h)

    def resid(u):
        return np.log(master_curve(load / np.exp(u[0]))) - lh

    def jac(u):
        return -master_curve_slope(load / np.exp(u[0]))[:, None]

    sol = least_squares(resid, [u0], jac=jac, bounds=([u_lo], [u_hi]), xtol=1e-14, ftol=1e-14)
    u = sol.x[0]
    r = resid(sol.x)
    J = jac(sol.x)
    s2 = float(r @ r) / (L.size - 1)
    se_u = np.sqrt(s2 / float(J[:, 0] @ J[:, 0]))
    k = float(np.exp(u))
    return {"k_b": k, "se": k * se_u, "rms_log": float(np.sqrt(np.mean(r ** 2))),
            "gamma": load / k, "residuals_log": r}
