"""Reference answers of the shell-engine verification cases (mm, N, MPa): published values and
closed-form solutions, each with its source, against which tests/test_shell_benchmarks.py and the
studies (studies/sze.py, studies/natural_curvature.py, studies/convergence.py) compare the engine.

- Sze, Liu & Lo (2004), "Popular benchmark problems for geometric nonlinear analysis of shells",
  Finite Elements in Analysis and Design 40: the cantilever of sections 3.1-3.2 and the slit
  annular plate of section 3.3 (problem data and published tip displacements).
- The inextensible elastica: tip of a clamped beam under a dead tip force (collocation BVP) and
  under a tip moment (circular arc).
- The uniform-curvature Ritz model of a free disk with isotropic natural curvature (as Masters &
  Salamon 1994, Freund 2000): the sphere-to-cylinder threshold and the stable curvatures.
- The closed-form narrow-strip curvature of a bilayer (shellfem.strip).
"""
from __future__ import annotations

import numpy as np

from shellfem.strip import strip_curvature

# --------------------------------------------------------------------------- Sze et al. (2004)

SZE_E, SZE_H, SZE_B = 1.2e6, 0.1, 1.0           # cantilever strip of sections 3.1-3.2
SZE_END_SHEAR = {"L": 10.0, "P_max": 4.0, "tip_u": 3.289, "tip_w": 6.700}
SZE_END_MOMENT = {"L": 12.0, "M_max": 50 * np.pi / 3,
                  "tip": {0.25: (4.361, 7.639), 0.5: (12.000, 7.639), 1.0: (12.000, 0.000)}}
#: Sze, Liu & Lo (2004) sec. 3.3: slit annular plate, line force q (per unit length) on one
#: slit edge, q_max = 0.8; w at the inner (A) and outer (B) corner of the loaded edge at q_max.
SZE_SLIT = {"r_in": 6.0, "r_out": 10.0, "t": 0.03, "E": 21e6, "nu": 0.0, "q_max": 0.8,
            "w_A": 13.891, "w_B": 17.528}


# --------------------------------------------------------------------------- elastica


def elastica_end_moment(L: float, kappa):
    """Tip (-u, w) (mm) of a clamped inextensible beam of length L bent by a tip moment to
    uniform curvature kappa = M / EI (1/mm): circular arc."""
    k = np.maximum(np.asarray(kappa, float), 1e-300)
    return L - np.sin(k * L) / k, (1 - np.cos(k * L)) / k


def elastica_end_shear(L: float, alpha) -> tuple[np.ndarray, np.ndarray]:
    """Tip (-u, w) (mm) of a clamped inextensible elastica of length L under a transverse
    dead tip load with alpha = P L^2 / EI (array, increasing from small values):
    theta'' = -alpha cos(theta) on s in [0, 1], theta(0) = 0, theta'(1) = 0, solved with
    scipy's collocation BVP solver, continued in alpha."""
    from scipy.integrate import solve_bvp
    s = np.linspace(0, 1, 101)
    y = np.zeros((4, s.size))          # theta, theta', x, z (per unit length)
    y[2] = s
    u, w = [], []
    for a in np.atleast_1d(np.asarray(alpha, float)):
        def rhs(_, Y, a=a):
            return np.vstack([Y[1], -a * np.cos(Y[0]), np.cos(Y[0]), np.sin(Y[0])])

        def bc(Y0, Y1):
            return np.array([Y0[0], Y1[1], Y0[2], Y0[3]])

        sol = solve_bvp(rhs, bc, s, y, tol=1e-8, max_nodes=100000)
        if not sol.success:
            raise RuntimeError(f"elastica at alpha = {a}: {sol.message}")
        y = sol.sol(s)
        u.append(L * (1 - y[2, -1]))
        w.append(L * y[3, -1])
    return np.array(u), np.array(w)


# --------------------------------------------------------------------------- natural-curvature disk


def disk_ritz_threshold(nu: float) -> float:
    """kappa0 R^2 / h at which the spherical state of a free disk with isotropic natural
    curvature kappa0 loses stability, in the uniform-curvature Ritz model (w = (k1 x^2 +
    k2 y^2) / 2; stretching energy pi E h K^2 R^6 / 384 of a free disk of Gaussian curvature
    K = k1 k2; as Masters & Salamon 1994, Freund 2000): 8 / (1 + nu)^(3/2); the spherical
    curvature there is (1 + nu) / 2 kappa0."""
    return 8.0 / (1.0 + nu) ** 1.5


def disk_ritz_curvatures(kappa0_R2_over_h: float, nu: float) -> tuple[float, float]:
    """Stable principal curvatures (k1 >= k2) / kappa0 of the uniform-curvature Ritz model:
    minimise (u1-1)^2 + (u2-1)^2 + 2 nu (u1-1)(u2-1) + lam u1^2 u2^2,
    lam = (1 - nu^2) (kappa0 R^2 / h)^2 / 16, from a slightly anisotropic start."""
    from scipy.optimize import minimize
    lam = (1 - nu * nu) * kappa0_R2_over_h ** 2 / 16

    def f(u):
        a, b = u[0] - 1, u[1] - 1
        return a * a + b * b + 2 * nu * a * b + lam * (u[0] * u[1]) ** 2

    u = minimize(f, [1.0, 0.9], method="BFGS", options={"gtol": 1e-12}).x
    return float(max(u)), float(min(u))


# --------------------------------------------------------------------------- bilayer strip


def narrow_curvature(fabric, plastic, plastic_thickness: float) -> float:
    """Closed-form narrow-strip curvature (1/mm) of shellfem.strip for these materials
    (shellfem.materials.Fabric, Plastic) and plastic thickness (mm)."""
    return float(strip_curvature(plastic_thickness, fabric.thickness, fabric.stretch[0],
                                 plastic.young_modulus / fabric.young_modulus,
                                 plastic_poisson=plastic.poisson, fabric_poisson=fabric.poisson))
