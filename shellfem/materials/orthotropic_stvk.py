"""Orthotropic St.Venant-Kirchhoff fabric membrane: linear orthotropic elasticity in the
Green strain (plane stress, course frame).

    W = h A_rest 1/2 eps^T Q eps,  eps = (e11, e22, 2 e12) the Green strain in the course frame,
    Q = 1 / (1 - nu12 nu21) [[E1, nu12 E2, 0], [nu12 E2, E2, 0], [0, 0, G12 (1 - nu12 nu21)]],
    nu21 = nu12 E2 / E1,

so the second Piola-Kirchhoff stress is S = Q eps: in uniaxial stress along the course
S11 = E1 e11 and e22 = -nu12 e11; along the wale S22 = E2 e22. E1, E2, G12 in MPa; the
course direction is Fabric.course_angle_deg from +x; h = Fabric.thickness. Q is positive
definite for E1, E2, G12 > 0 and nu12^2 < E1 / E2. W = +inf where a triangle is inverted
or degenerate (det a <= 0), where St.Venant-Kirchhoff would otherwise admit a second,
mirrored minimum. The defaults are illustrative, of the order of the neo-Hookean
default (1.05 MPa), not a calibrated fabric.
"""
from __future__ import annotations

import numpy as np

from shellfem.errors import SelfshapeError
from shellfem.materials.base import MembraneModel, Parameter, RestState, course_strain_map


def stvk_stiffness(params: dict) -> np.ndarray:
    """Q (3, 3), MPa: S = Q eps for Voigt Green strain eps = (e11, e22, 2 e12)."""
    E1, E2, G12, nu12 = params["e1_mpa"], params["e2_mpa"], params["g12_mpa"], params["nu12"]
    d = 1.0 - nu12 * nu12 * E2 / E1
    return np.array([[E1 / d, nu12 * E2 / d, 0.0], [nu12 * E2 / d, E2 / d, 0.0], [0.0, 0.0, G12]])


class OrthotropicStVK(MembraneModel):
    """A fabric with different course and wale moduli, without a strain barrier."""
    name = "orthotropic-stvk"
    parameters = (
        Parameter("e1_mpa", 0.8, "MPa", "Young's modulus along the course", lo=0.0, lo_open=True),
        Parameter("e2_mpa", 1.3, "MPa", "Young's modulus along the wale", lo=0.0, lo_open=True),
        Parameter("g12_mpa", 0.3, "MPa", "in-plane shear modulus", lo=0.0, lo_open=True),
        Parameter("nu12", 0.3, "1", "Poisson's ratio: wale contraction per course extension", lo=-0.99, hi=0.99),
    )

    def __init__(self, rest: RestState, fabric):
        self.T = course_strain_map(rest, fabric.course_angle_deg)
        self.Q = stvk_stiffness(fabric.parameters[self.name])
        self.c = fabric.thickness * rest.area

    def energy(self, a):
        T, c = self.T, self.c
        eps = np.einsum("mik,mk->mi", T, a) - np.array([0.5, 0.5, 0.0])
        S = eps @ self.Q
        W = c * 0.5 * np.einsum("mi,mi->m", eps, S)
        g = c[:, None] * np.einsum("mi,mik->mk", S, T)
        H = c[:, None, None] * np.einsum("mik,ij,mjl->mkl", T, self.Q, T)
        W = np.where(a[:, 0] * a[:, 2] - a[:, 1] ** 2 <= 0, np.inf, W)
        return W, g, H

    @classmethod
    def check(cls, fabric) -> None:
        """Q must be positive definite: nu12^2 < E1 / E2."""
        p = fabric.parameters[cls.name]
        if p["nu12"] ** 2 >= p["e1_mpa"] / p["e2_mpa"]:
            raise SelfshapeError(f"fabric.{cls.name}.nu12 = {p['nu12']:g} must satisfy nu12^2 < e1_mpa / e2_mpa "
                                 f"= {p['e1_mpa'] / p['e2_mpa']:.3g} (the stiffness is not positive definite)")
