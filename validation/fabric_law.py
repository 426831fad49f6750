"""The engine's orthotropic log-barrier law (shellfem.materials.orthotropic) in the fabric's
uniaxial tests: the response of a specimen cut at an angle to the course (strain rotated into the
course frame, transverse strain and shear solved so that the lateral and shear stresses vanish),
and the fit of the law's parameters to the 0 and 90 degree curves (MPa, Green strains)."""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from shellfem.materials.orthotropic import orthotropic_stress
from validation.fabric_curves import B_MAX, GAP_MAX, fit_barrier_curve

# ----------------------------------------------------------------------------- the model

def strain_rotation(angle_deg: float) -> np.ndarray:
    """T with eps_course = T @ eps_specimen (Voigt, engineering shear) for a specimen
    axis at angle_deg from the course direction; stresses map back with T^T."""
    t = np.radians(angle_deg)
    c, s = np.cos(t), np.sin(t)
    return np.array([[c * c, s * s, -c * s], [s * s, c * c, c * s], [2 * c * s, -2 * c * s, c * c - s * s]])


def _central_free_strains(e, T, g):
    """Free strains (transverse Green strain, 2 e12) of each row that put the course-frame
    normal strains closest to zero relative to their barriers (least squares of e_ii / g_i):
    the most interior point of the convex set the law admits (|e_ii| < g_i), so a start that
    is feasible whenever any state at this axial strain is. Off-axis (0 < angle < 90 deg) it
    makes both normal strains zero; at 0 or 90 deg the axial strain is the course (wale)
    strain itself and the transverse one is zero."""
    W = T[:2] / g[:, None]                              # scaled normal strains = W @ (e, x0, x1)
    x, *_ = np.linalg.lstsq(W[:, 1:], -np.outer(W[:, 0], e), rcond=None)
    return x.T


def uniaxial_response(e_axial, angle_deg: float, params: dict, nu: float):
    """Model stress along a strip cut at angle_deg, stretched to axial Green strain(s) e_axial,
    in uniaxial stress (lateral and shear stress zero, solved by damped Newton; the problem
    is the minimisation of a convex energy over the two free strains on the convex set the
    barrier admits, |e_11|, |e_22| < g_1, g_2 in the course frame).

    Start: the seed's uniaxial guess (transverse -nu e, no shear) pulled towards the most
    interior admissible state until it is admissible, so every axial strain that any state
    of the law admits gets a stress (the test data need not stay inside the barriers of the
    starting guess: a strip cut off-axis reaches course strains beyond g through its shear).
    Returns (axial stress MPa (n,), free strains (n,2) = transverse Green strain and 2 e12).
    NaN only where no admissible state exists (the axial strain beyond the barrier at 0 or
    90 deg).
    """
    e = np.atleast_1d(np.asarray(e_axial, dtype=float))
    T = strain_rotation(angle_deg)
    g = np.array([params["g1"], params["g2"]], dtype=float)

    def course(ee, xx):
        return np.column_stack([ee, xx]) @ T.T

    def margin(ee, xx):
        """Largest |e_ii| / g_i in the course frame (< 1: admissible)."""
        return np.max(np.abs(course(ee, xx)[:, :2]) / g, axis=1)

    centre = _central_free_strains(e, T, g)
    guess = np.column_stack([-nu * e, np.zeros_like(e)])
    m0 = margin(e, centre)
    ok = m0 < 1.0
    # convex admissible set: the segment centre -> guess stays admissible up to its first exit
    t = np.ones(e.size)
    for _ in range(60):
        bad = ok & (margin(e, centre + t[:, None] * (guess - centre)) >= 1.0 - 0.05 * (1.0 - m0))
        if not bad.any():
            break
        t[bad] *= 0.5
    x = centre + t[:, None] * (guess - centre)
    eo = e[ok]
    for _ in range(100):
        if not ok.any():
            break
        xo = x[ok]
        sig, K = orthotropic_stress(course(eo, xo), params, nu)
        ss = sig @ T
        Ks = np.einsum("ji,njk,kl->nil", T, K, T)
        R = ss[:, 1:]
        if np.abs(R).max(initial=0.0) < 1e-13 * max(1.0, np.abs(ss[:, 0]).max(initial=0.0)):
            break
        dx = np.linalg.solve(Ks[:, 1:, 1:], -R[..., None])[..., 0]
        step = np.ones(dx.shape[0])
        for _ in range(60):
            bad = margin(eo, xo + step[:, None] * dx) >= 1.0
            if not bad.any():
                break
            step[bad] *= 0.5
        x[ok] = xo + step[:, None] * dx
    out = np.full(e.size, np.nan)
    if ok.any():
        sig, _ = orthotropic_stress(course(eo, x[ok]), params, nu)
        out[ok] = (sig @ T)[:, 0]
    x[~ok] = np.nan
    return out, x


def fit_orthotropic_uniaxial(e0, S0, e90, S90, nu: float, a3: float, start: dict | None = None) -> dict:
    """Model-consistent fit of a1, a2, b1, b2, g1, g2 on the 0 and 90 deg unloading curves.

    Residuals are the model's own uniaxial-stress response (uniaxial_response: the lateral
    stress vanishes, the transverse strain and barrier included) minus the measured stress,
    so the engine reproduces the two tests it is fitted on. (The seed's Eq. 4.6-4.7 instead
    impose e22 = -nu e11, which is not the model's uniaxial state.) a3 does not enter at
    0/90 deg (no shear strain by symmetry). Start: the Eq. 4.6 fits (a1 ~ A1, a2 ~ A2, the
    small-strain uniaxial slopes of the model). SE from the Jacobian, s^2 = SSR/(n-6).
    ``at_bound``: the parameters that ended on the search box (not determined by the curves).
    """
    e0, S0, e90, S90 = (np.asarray(v, dtype=float) for v in (e0, S0, e90, S90))
    em0, em9 = float(e0.max()), float(e90.max())
    if start is None:
        f0, f9 = fit_barrier_curve(e0, S0), fit_barrier_curve(e90, S90)
        start = {"a1": f0["A"], "a2": f9["A"], "b1": f0["b"], "b2": f9["b"], "g1": f0["g"], "g2": f9["g"]}
    tiny = 1e-9 * max(float(np.abs(S0).max()), float(np.abs(S90).max()), 1e-12)

    def unpack(x):
        return {"a1": np.exp(x[0]), "a2": np.exp(x[1]), "a3": a3, "b1": np.exp(x[2]), "b2": np.exp(x[3]),
                "g1": em0 + np.exp(x[4]), "g2": em9 + np.exp(x[5])}

    def resid(x):
        p = unpack(x)
        r0 = uniaxial_response(e0, 0.0, p, nu)[0] - S0
        r9 = uniaxial_response(e90, 90.0, p, nu)[0] - S90
        r = np.concatenate([r0, r9])
        return np.where(np.isfinite(r), r, 1e3 * float(np.abs(S0).max() + np.abs(S90).max()))

    x0 = [np.log(max(start["a1"], tiny)), np.log(max(start["a2"], tiny)), np.log(max(start["b1"], tiny)),
          np.log(max(start["b2"], tiny)), np.log(max(start["g1"] - em0, 1e-6)), np.log(max(start["g2"] - em9, 1e-6))]
    # search box: moduli and barrier coefficients from `tiny` to B_MAX x the largest stress per
    # unit strain, the barriers from 1e-12 to GAP_MAX x e_max above the data (beyond them the
    # curves do not determine the parameter; a fit that ends there is reported, not trusted)
    big = np.log(B_MAX * max(float(np.abs(S0).max()), float(np.abs(S90).max()), 1e-12) / min(em0, em9))
    lo = np.array([np.log(tiny)] * 4 + [np.log(1e-12 * em0), np.log(1e-12 * em9)])
    hi = np.array([big] * 4 + [np.log(GAP_MAX * em0), np.log(GAP_MAX * em9)])
    x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)
    sol = least_squares(resid, x0, bounds=(lo, hi), x_scale="jac", xtol=1e-12, ftol=1e-12, max_nfev=400)
    at_bound = [k for k, v, a, b in zip(("a1", "a2", "b1", "b2", "g1", "g2"), sol.x, lo, hi)
                if v <= a + 1e-6 or v >= b - 1e-6]
    p = unpack(sol.x)
    r = sol.fun
    s2 = float(r @ r) / max(r.size - 6, 1)
    cov_x = s2 * np.linalg.pinv(sol.jac.T @ sol.jac)
    scale = np.array([p["a1"], p["a2"], p["b1"], p["b2"], p["g1"] - em0, p["g2"] - em9])
    se = np.sqrt(np.clip(np.diag(cov_x), 0, None)) * scale
    names = ("a1", "a2", "b1", "b2", "g1", "g2")
    return {"params": {k: float(v) for k, v in p.items()}, "se": dict(zip(names, map(float, se))),
            "rms": float(np.sqrt(np.mean(r * r))), "converged": bool(sol.success), "at_bound": at_bound}
