"""Orthotropic log-barrier fabric membrane (seed Eq. 4.2-4.5).

    W = h A_rest Psi(eps),  eps = (e11, e22, 2 e12) the Green strain in the course frame,
    Psi = 1/2 eps^T C eps / (1 - nu^2) + f1(e11) + f2(e22),
    C = [[a1, sqrt(a1 a2) nu, 0], [sqrt(a1 a2) nu, a2, 0], [0, 0, a3 (1 - nu^2)]],
    f_i(e) = -phi_i(e) = b_i ((g_i - |e|) ln(1 - |e| / g_i) + |e|),

so dPsi/deps is the seed's Eq. 4.5 (its Eq. 4.2 omits the 1/2 that Eq. 4.5 implies). The
barrier keeps |e_ii| < g_i (W = +inf beyond). a1, a2, a3, b1, b2 in MPa, g1, g2 Green
strains; nu = Fabric.poisson; the course direction is Fabric.course_angle_deg from +x.
:func:`orthotropic_stress` is the same law as stress and tangent, for the calibration
(validation.fabric) that fits its parameters.
"""
from __future__ import annotations

import numpy as np

from shellfem.errors import SelfshapeError
from shellfem.materials.base import MembraneModel, Parameter, RestState, course_strain_map

#: Seed Table 4.1 orthotropic log-barrier parameters, converted from Pa to MPa.
TABLE_4_1_ORTHOTROPIC = {"a1": 0.024161, "a2": 0.090890, "a3": 0.063419,
                         "b1": 0.029676, "b2": 0.020512, "g1": 0.9626, "g2": 0.9637}

_UNITS = {"a1": "MPa", "a2": "MPa", "a3": "MPa", "b1": "MPa", "b2": "MPa", "g1": "1", "g2": "1"}
_DOCS = {"a1": "course stiffness", "a2": "wale stiffness", "a3": "shear stiffness",
         "b1": "course barrier strength", "b2": "wale barrier strength",
         "g1": "course Green-strain limit", "g2": "wale Green-strain limit"}


def log_barrier(e, beta, gamma):
    """f(e) = beta ((g - |e|) ln(1 - |e|/g) + |e|) with f', f'' (seed Eq. 4.3, sign flipped)."""
    ae = np.abs(e)
    inside = ae < gamma
    r = np.where(inside, 1 - ae / gamma, 1.0)
    lr = np.log(r)
    f = np.where(inside, beta * ((gamma - ae) * lr + ae), np.inf)
    f1 = -beta * np.sign(e) * lr
    f2 = beta / np.where(inside, gamma - ae, np.inf)
    return f, f1, f2


def orthotropic_density(eps, params: dict, nu: float):
    """Psi (n,) (MPa), stress dPsi/deps (n, 3) and tangent (n, 3, 3) at Voigt Green strains
    eps (n, 3) in the course frame; Psi = +inf (stress and tangent without the barrier)
    where |e_ii| >= g_i."""
    a1, a2, a3 = params["a1"], params["a2"], params["a3"]
    C = np.array([[a1, np.sqrt(a1 * a2) * nu, 0.0], [np.sqrt(a1 * a2) * nu, a2, 0.0],
                  [0.0, 0.0, a3 * (1 - nu ** 2)]]) / (1 - nu ** 2)
    Ce = eps @ C
    f1, d1, dd1 = log_barrier(eps[:, 0], params["b1"], params["g1"])
    f2, d2, dd2 = log_barrier(eps[:, 1], params["b2"], params["g2"])
    psi = 0.5 * np.einsum("mi,mi->m", eps, Ce) + f1 + f2
    sig = Ce.copy()
    sig[:, 0] += d1
    sig[:, 1] += d2
    K = np.broadcast_to(C, (len(eps), 3, 3)).copy()
    K[:, 0, 0] += np.where(np.isfinite(dd1), dd1, 0.0)
    K[:, 1, 1] += np.where(np.isfinite(dd2), dd2, 0.0)
    return psi, sig, K


def orthotropic_stress(eps, params: dict, nu: float):
    """Stress (n,3) and tangent (n,3,3) of the orthotropic log-barrier model (Eq. 4.5).

    eps: (n,3) Voigt Green strain (e11, e22, 2 e12) in the course frame; needs |e_ii| < g_i.
    """
    eps = np.atleast_2d(np.asarray(eps, dtype=float))
    return orthotropic_density(eps, params, nu)[1:]


def orthotropic(a, T, params, nu, h, area):
    """Seed Eq. 4.2-4.3 per triangle; returns W, dW/da, d2W/da2 (W = inf outside the barrier).
    T: the strain map of shellfem.materials.base.strain_map (eps = T a - (1/2, 1/2, 0))."""
    eps = np.einsum("mik,mk->mi", T, a) - np.array([0.5, 0.5, 0.0])
    psi, ge, He = orthotropic_density(eps, params, nu)
    c = h * area
    W = c * psi
    g = c[:, None] * np.einsum("mi,mik->mk", ge, T)
    H = c[:, None, None] * np.einsum("mik,mij,mjl->mkl", T, He, T)
    return W, g, H


class Orthotropic(MembraneModel):
    """Knit fabric with a course direction and a strain barrier (seed Ch. 4)."""
    name = "orthotropic"
    parameters = tuple(Parameter(k, v, _UNITS[k], _DOCS[k], lo=0.0, lo_open=True)
                       for k, v in TABLE_4_1_ORTHOTROPIC.items())

    def __init__(self, rest: RestState, fabric):
        self.T = course_strain_map(rest, fabric.course_angle_deg)
        self.area = rest.area
        self.params, self.nu, self.h = fabric.parameters[self.name], fabric.poisson, fabric.thickness

    def energy(self, a):
        return orthotropic(a, self.T, self.params, self.nu, self.h, self.area)

    @classmethod
    def check(cls, fabric) -> None:
        """The log barrier must admit the pre-stretched state: Green strain < g."""
        o = fabric.parameters[cls.name]
        for k, si in (("g1", max(fabric.stretch)), ("g2", max(fabric.stretch))):
            eps = 0.5 * (si * si - 1.0)
            if eps >= o[k]:
                raise SelfshapeError(f"fabric.orthotropic.{k} = {o[k]:g} is below the pre-stretch Green strain "
                                     f"{eps:.3f}; the log-barrier model cannot represent this stretch")
