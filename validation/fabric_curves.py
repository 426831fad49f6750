"""The fabric's test curves turned into material numbers (mm, N, MPa; Green strains): uniaxial
Green strain and 2nd Piola-Kirchhoff stress of the tensile tests (seed Eq. 4.4), the stabilised
unloading branch, the seed's barrier curve sigma = A e - b log(1 - e/g) (Eq. 4.6-4.7) and its fit,
the release tangent, the in-plane stiffness from two uniaxial slopes, and the shear modulus of
the clamped-square test."""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares, nnls

from shellfem.errors import SelfshapeError

# ----------------------------------------------------------------------------- tensile

GAP_MAX = 1e2   # barrier strain searched up to e_max (1 + GAP_MAX) (fit_barrier_curve)
B_MAX = 1e6     # barrier coefficient b searched up to B_MAX x the largest stress

def green_strain(extension_mm, gauge_mm: float) -> np.ndarray:
    """Uniaxial Green strain e = d/L + d^2/(2 L^2) (Eq. 4.4)."""
    r = np.asarray(extension_mm, dtype=float) / gauge_mm
    return r + 0.5 * r * r


def second_pk_stress(load_n, extension_mm, width_mm: float, gauge_mm: float, thickness_mm: float) -> np.ndarray:
    """Uniaxial 2nd Piola-Kirchhoff stress S = f L / (w (d + L)) / thickness, MPa (Eq. 4.4)."""
    d = np.asarray(extension_mm, dtype=float)
    return np.asarray(load_n, dtype=float) * gauge_mm / (width_mm * (d + gauge_mm)) / thickness_mm


def barrier_curve(e, A: float, b: float, g: float) -> np.ndarray:
    """sigma(e) = A e - b log(1 - e/g) for 0 <= e < g (Eq. 4.6-4.7)."""
    return A * e - b * np.log1p(-np.asarray(e, dtype=float) / g)


def _barrier_jacobian(e, A, b, g):
    return np.column_stack([e, -np.log1p(-e / g), -b * e / (g * (g - e))])


def fit_barrier_curve(e, S) -> dict:
    """Least-squares fit of S = A e - b log(1 - e/g) with A >= 0, b >= 0 and g > max(e).

    For fixed g the model is linear in (A, b): g is found on a profile grid first (robust
    to the flat barrier of low stretches; (A, b) by non-negative least squares), then all
    three are refined together within the physical domain. The sign constraints matter
    when the test stops far below the barrier: the curve is then nearly A e + (b/g) e, the
    three parameters trade off, and an unconstrained fit wanders to a negative modulus.
    Returns A, b, g, cov (3x3 from the Jacobian, s^2 = SSR/(n-3)), se, rms, n, e_max and
    barrier_found (False when b or g ended on its search bound: the barrier is not seen).
    """
    e = np.asarray(e, dtype=float)
    S = np.asarray(S, dtype=float)
    if e.size < 6:
        raise SelfshapeError(f"fit_barrier_curve: needs at least 6 points, got {e.size}")
    em = float(e.max())
    if em <= 0:
        raise SelfshapeError("fit_barrier_curve: strains must reach above 0")

    def linear_ab(g):
        X = np.column_stack([e, -np.log1p(-e / g)])
        coef, _ = nnls(X, S)
        r = X @ coef - S
        return coef, float(r @ r)

    gaps = em * np.geomspace(1e-4, 1e2, 121)
    ssr = [linear_ab(em + d)[1] for d in gaps]
    d0 = gaps[int(np.argmin(ssr))]
    (A0, b0), _ = linear_ab(em + d0)
    # unknowns: A >= 0, log b, log(g - em): keeps b > 0 and g above the data
    x0 = [A0, np.log(max(b0, 1e-12 * max(abs(S).max(), 1e-12))), np.log(d0)]

    def resid(x):
        return barrier_curve(e, x[0], np.exp(x[1]), em + np.exp(x[2])) - S

    def jac(x):
        b, d = np.exp(x[1]), np.exp(x[2])
        J = _barrier_jacobian(e, x[0], b, em + d)
        return np.column_stack([J[:, 0], J[:, 1] * b, J[:, 2] * d])

    # the barrier searched up to GAP_MAX x e_max above the data, b up to B_MAX x the largest
    # stress: beyond, the curve is a straight line and (b, g) are not determined
    s_max = max(float(np.abs(S).max()), 1e-300)
    lo = [0.0, -np.inf, np.log(1e-12 * em)]
    hi = [np.inf, np.log(B_MAX * s_max), np.log(GAP_MAX * em)]
    x0 = np.clip(x0, np.array(lo) + 1e-9, np.array(hi) - 1e-9)
    sol = least_squares(resid, x0, jac=jac, bounds=(lo, hi),
                        method="trf", x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=2000)
    A, b, g = sol.x[0], float(np.exp(sol.x[1])), em + float(np.exp(sol.x[2]))
    barrier_found = bool(sol.x[2] < hi[2] - 1e-6 and sol.x[1] < hi[1] - 1e-6)
    r = barrier_curve(e, A, b, g) - S
    J = _barrier_jacobian(e, A, b, g)
    dof = max(e.size - 3, 1)
    s2 = float(r @ r) / dof
    cov = s2 * np.linalg.pinv(J.T @ J)
    return {"A": float(A), "b": b, "g": g, "cov": cov, "se": np.sqrt(np.clip(np.diag(cov), 0, None)),
            "rms": float(np.sqrt(np.mean(r * r))), "n": int(e.size), "e_max": em, "barrier_found": barrier_found}


def release_tangent(fit: dict, e_release: float | None = None) -> tuple[float, float]:
    """Slope dS/de of a fitted unloading curve at release (default: its largest strain), with SE."""
    e = fit["e_max"] if e_release is None else float(e_release)
    A, b, g = fit["A"], fit["b"], fit["g"]
    grad = np.array([1.0, 1.0 / (g - e), -b / (g - e) ** 2])
    return float(A + b / (g - e)), float(np.sqrt(max(grad @ fit["cov"] @ grad, 0.0)))


def tensile_curve(table: dict, meta: dict, cycles, branch: str = "unload") -> tuple[np.ndarray, np.ndarray]:
    """(Green strain, 2nd PK stress MPa) of the given cycles' branch, in file order."""
    m = np.isin(table["cycle"], list(cycles)) & (table["branch"] == branch)
    d, f = table["extension_mm"][m], table["load_N"][m]
    L = meta["tensile_gauge_length_mm"]
    return green_strain(d, L), second_pk_stress(f, d, meta["tensile_width_mm"], L, meta["fabric_thickness_mm"])


def stabilised_cycles(table: dict, meta: dict, name: str = "tensile") -> tuple[list, str]:
    """Cycles whose unloading branch represents the stabilised material, and why.

    The first cycle (preconditioning: fibres rearrange, the textile is not yet
    stabilised) is always dropped when there are several. Of the rest, the last cycle is
    the reference; going backwards, a cycle is kept while its unloading branch agrees
    with the reference fit within noise (RMS <= 1.5 x the reference's residual RMS and
    mean offset <= 4 standard errors of a difference of two noisy curves); the first disagreeing cycle and all before it are dropped.
    """
    cycles = sorted(int(c) for c in np.unique(table["cycle"]))
    for c in cycles:
        n = int(np.sum((table["cycle"] == c) & (table["branch"] == "unload")))
        if n < 6:
            raise SelfshapeError(f"{name}: cycle {c} has {n} unload rows (need >= 6)")
    if len(cycles) == 1:
        return cycles, "single cycle in the file: used as is (stabilisation cannot be checked)"
    ref = cycles[-1]
    ref_fit = fit_barrier_curve(*tensile_curve(table, meta, [ref]))
    sigma = max(ref_fit["rms"], 1e-15)
    kept = [ref]
    for c in reversed(cycles[1:-1]):
        e, S = tensile_curve(table, meta, [c])
        if e.max() >= ref_fit["g"]:
            break
        r = S - barrier_curve(e, ref_fit["A"], ref_fit["b"], ref_fit["g"])
        # the mean offset compares two noisy curves: its SE is ~ sqrt(2) sigma / sqrt(n)
        if np.sqrt(np.mean(r * r)) > 1.5 * sigma or abs(r.mean()) > 4.0 * np.sqrt(2.0) * sigma / np.sqrt(r.size):
            break
        kept.append(c)
    kept.sort()
    dropped = [c for c in cycles if c not in kept]
    why = (f"cycle {cycles[0]} dropped as preconditioning" +
           (f"; cycle(s) {dropped[1:]} differ from the last cycle beyond noise" if len(dropped) > 1 else "") +
           f"; cycles {kept} agree with the last cycle within noise and are pooled")
    return kept, why


def stiffness_from_uniaxial(A1: float, A2: float, nu: float) -> tuple[float, float]:
    """a1, a2 from the uniaxial slopes A1 = (a1 - sqrt(a1 a2) nu^2)/(1-nu^2), A2 likewise.

    With r = sqrt(a2/a1), P = A1 (1-nu^2), Q = A2 (1-nu^2): P r^2 - nu^2 (P - Q) r - Q = 0,
    positive root, then a1 = P / (1 - nu^2 r), a2 = r^2 a1.
    """
    P, Q = A1 * (1 - nu * nu), A2 * (1 - nu * nu)
    if P <= 0 or Q <= 0:
        raise SelfshapeError(f"uniaxial slopes must be positive to define a1, a2 (got A1 = {A1:.4g}, A2 = {A2:.4g} MPa)")
    n2 = nu * nu
    r = (n2 * (P - Q) + np.sqrt(n2 * n2 * (P - Q) ** 2 + 4 * P * Q)) / (2 * P)
    if not (np.isfinite(r) and r > 0) or 1 - n2 * r <= 0 or 1 - n2 / r <= 0:
        raise SelfshapeError(f"uniaxial slopes A1 = {A1:.4g}, A2 = {A2:.4g} MPa admit no a1, a2 with nu = {nu:g}")
    a1 = P / (1 - n2 * r)
    return float(a1), float(r * r * a1)


def stiffness_with_se(A1, se1, A2, se2, nu):
    a = np.array(stiffness_from_uniaxial(A1, A2, nu))
    J = np.empty((2, 2))
    for k, (h, base) in enumerate(((1e-6 * abs(A1), (A1, A2)), (1e-6 * abs(A2), (A1, A2)))):
        up, dn = list(base), list(base)
        up[k] += h
        dn[k] -= h
        J[:, k] = (np.array(stiffness_from_uniaxial(*up, nu)) - np.array(stiffness_from_uniaxial(*dn, nu))) / (2 * h)
    cov = J @ np.diag([se1 ** 2, se2 ** 2]) @ J.T
    return a, np.sqrt(np.diag(cov))


# ----------------------------------------------------------------------------- shear

def shear_stress_strain(displacement_mm, load_n, side_mm: float, thickness_mm: float):
    """Kinematics of the square clamped on two parallel edges: gamma = u / side (the clamp
    separation equals the side), tau = F / (side * thickness) MPa. For simple shear
    F = [[1, gamma], [0, 1]] the Green strain has 2 e12 = gamma exactly (and e22 = gamma^2/2)."""
    u = np.asarray(displacement_mm, dtype=float)
    return u / side_mm, np.asarray(load_n, dtype=float) / (side_mm * thickness_mm)


def fit_shear_modulus(gamma, tau) -> dict:
    """Initial shear slope a3 of tau(gamma), two linear least-squares fits.

    main ("odd-cubic"): tau = c0 + a3 gamma + c gamma^3. The model's sigma12 is linear in 2 e12,
    so a3 is the slope at zero; the measured lateral force also carries the stretching term
    gamma * S22 (e22 = gamma^2/2), odd and cubic in gamma, which the cubic absorbs (a quadratic
    term would break the symmetry gamma -> -gamma).
    seed ("linear"): tau = c0 + a gamma over the whole range (the seed's straight line).
    Each with SE from (X^T X)^-1 s^2.
    """
    g = np.asarray(gamma, dtype=float)
    t = np.asarray(tau, dtype=float)
    if g.size < 5 or np.ptp(g) <= 0:
        raise SelfshapeError(f"shear fit needs >= 5 points over a range of displacement, got {g.size}")
    out = {}
    for key, X in (("odd_cubic", np.column_stack([np.ones_like(g), g, g ** 3])),
                   ("linear", np.column_stack([np.ones_like(g), g]))):
        coef, *_ = np.linalg.lstsq(X, t, rcond=None)
        r = t - X @ coef
        s2 = float(r @ r) / max(g.size - X.shape[1], 1)
        cov = s2 * np.linalg.pinv(X.T @ X)
        out[key] = {"slope": float(coef[1]), "se": float(np.sqrt(cov[1, 1])), "coef": coef,
                    "rms": float(np.sqrt(np.mean(r * r)))}
    return out
