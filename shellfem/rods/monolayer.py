"""The effective monolayer of a plastic-on-fabric arm (seed Eq. 3.4-3.13): rest curvature
and stiffnesses of the rod that stands for a printed arm.

Derivation (seed section 3.2.3). Layer 1 = plastic (E1, h1, rest metric a_r1 = 1: printed
without residual strain), layer 2 = fabric (E2, h2, a_r2 = 1/s^2: pre-stretched by s),
bonded at the interface z = 0, plastic on z in [0, h1], fabric on [-h2, 0]. Eq. 3.9 gives
each layer the energy (1D along the arm, per unit width)

    E_i [ h_i/8 A_i^2 + h_i^3/24 B^2 +- h_i^2/8 A_i B ],   A_i = a_c / a_ri - 1,  B = b_c - b_bar

which is exactly  int over the layer of  E_i / 2 (A_i / 2 + z B / 2)^2 dz : the strain at
height z is A_i/2 + z B/2, so in this normalisation B/2 is the curvature and b = 2 kappa.
(Read with b = kappa, Eq. 3.13/3.17 give twice the Timoshenko curvature; checked in
tests/test_rods.py against Timoshenko and shellfem.strip.) The ansatz Eq. 3.4
(a_r1 = a_r + alpha_1 (b_r - b_bar), a_r2 = a_r - alpha_2 (b_r - b_bar)) makes the bilayer
and the monolayer of Eq. 3.10 agree up to a constant when alpha_1, alpha_2 solve Eq. 3.11,
i.e. Eq. 3.12, and then (Eq. 3.13)

    b_r - b_bar = 6 h1 h2 E1 E2 (h1 + h2) / D4 (a_r1 - a_r2),
    D4 = h1^4 E1^2 + 2 h1 h2 E1 E2 (2 h1^2 + 3 h1 h2 + 2 h2^2) + h2^4 E2^2.

With b = 2 kappa and a_r1 - a_r2 = 1 - 1/s^2 the rest curvature of the arm is

    kappa = 3 h1 h2 E1 E2 (h1 + h2) / D4 (1 - 1/s^2) + kappa_bar              (1/mm)

(kappa_bar the plastic set, Fig. 3.4), which for a small misfit eps = s - 1 (1 - 1/s^2 =
2 eps + O(eps^2)) is Timoshenko's bilayer curvature 6 E1 E2 h1 h2 (h1 + h2) eps / D4; for
E1 >> E2 it tends to Eq. 3.17 / 2 = 3 h2 (h1 + h2) E2 / (h1^3 E1) (1 - 1/s^2). The centre
of curvature is on the fabric side.

Stiffnesses of the monolayer: eliminating the membrane strain from Eq. 3.10 (minimising
over a_c at fixed b_c; the coupling term (E1 h1^2 - E2 h2^2)/8 is the offset of the
neutral axis from the interface) leaves the bending stiffness per unit width

    D = D4 / (12 (E1 h1 + E2 h2))                (N mm: the composite beam's EI / w)

(E1 h1^3 / 12 for E1 >> E2), and the axial stiffness per width is E1 h1 + E2 h2 (N/mm).
A rod of width w gets B1 = D w (about its width axis), EA = (E1 h1 + E2 h2) w,
B2 = (E1 h1 + E2 h2) w^3 / 12 (in-plane) and, as in the seed's Eq. 3.3, the torsional
stiffness T = mu1 (I1 + I2) / 2 of the plastic section (mu1 = E1 / (2 (1 + nu1)),
I1 = h1^3 w / 12, I2 = w^3 h1 / 12).

This is beam theory (uniaxial stress, each layer free to contract sideways), the regime of
narrow arms (w ~ h); a wide strip with unequal Poisson ratios bends differently (the
layered strip model of shellfem.strip: 28 % less at nu 0.5 / 0.3, s = 1.001, h 0.3 / 0.8,
E1/E2 = 3200), equal Poisson ratios agree within 0.2 % (tests/test_rods.py).
Units: mm, MPa (N/mm^2), N.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ArmSection:
    """Rod parameters of one printed arm: rest_curvature 1/mm (> 0, centre of curvature on
    the fabric side), EA N, B1, B2, T N mm^2."""
    rest_curvature: np.ndarray
    EA: np.ndarray
    B1: np.ndarray
    B2: np.ndarray
    T: np.ndarray


def monolayer_curvature(plastic_thickness, fabric_thickness, plastic_modulus, fabric_modulus, stretch,
                        plastic_set=0.0):
    """Rest curvature (1/mm) of the effective monolayer (module docstring; seed Eq. 3.13
    with b = 2 kappa). Thicknesses mm, moduli MPa (only their ratio matters), stretch s >= 1,
    plastic_set 1/mm. Arrays broadcast."""
    h1, h2, E1, E2, s, kb = (np.asarray(v, float) for v in (plastic_thickness, fabric_thickness, plastic_modulus,
                                                            fabric_modulus, stretch, plastic_set))
    return 3 * h1 * h2 * E1 * E2 * (h1 + h2) / _d4(h1, h2, E1, E2) * (1 - 1 / (s * s)) + kb


def monolayer_bending_stiffness(plastic_thickness, fabric_thickness, plastic_modulus, fabric_modulus):
    """Bending stiffness per unit width D = D4 / (12 (E1 h1 + E2 h2)) (N mm) of the bilayer
    about its neutral axis."""
    h1, h2, E1, E2 = (np.asarray(v, float) for v in (plastic_thickness, fabric_thickness, plastic_modulus,
                                                      fabric_modulus))
    return _d4(h1, h2, E1, E2) / (12 * (E1 * h1 + E2 * h2))


def arm_section(plastic_thickness, width, fabric_thickness, plastic_modulus, fabric_modulus, stretch,
                plastic_poisson=0.5, plastic_set=0.0) -> ArmSection:
    """The rod of an arm of plastic thickness h1 and width w (mm) on fabric of thickness h2:
    rest curvature, EA, B1, B2, T (module docstring). Arrays broadcast."""
    h1, w, h2, E1, E2 = (np.asarray(v, float) for v in (plastic_thickness, width, fabric_thickness, plastic_modulus,
                                                         fabric_modulus))
    axial = E1 * h1 + E2 * h2
    mu1 = E1 / (2 * (1 + plastic_poisson))
    return ArmSection(monolayer_curvature(h1, h2, E1, E2, stretch, plastic_set), axial * w,
                      monolayer_bending_stiffness(h1, h2, E1, E2) * w, axial * w ** 3 / 12,
                      mu1 * (h1 ** 3 * w + w ** 3 * h1) / 24)


def offset_arm_section(plastic_thickness, width, fabric_thickness, plastic_modulus, plastic_poisson=0.5,
                       plastic_set=0.0) -> tuple:
    """The rod of an arm printed ON the fabric (shellfem.rods.energy's offset): the plastic
    alone, EA = E1 h1 w, B1 = E1 h1^3 w / 12 about its own centre line, B2 = E1 h1 w^3 / 12,
    T as arm_section, rest curvature the plastic set only, and its centre line's height above
    the fabric's mid-surface (h1 + h2) / 2 (mm). The fabric, under the arm as around it, is the
    bare fabric of the mesh, pulling at the mid-surface: the bilayer effect of the arm's own
    strip (arm_section's rest curvature) then comes from the mesh's fabric through the offset
    (Timoshenko's bilayer, tests/test_rods.py), and so does the moment of the surrounding
    fabric's pull, which the seed's collocated rods (offset 0) do not feel.
    Returns (ArmSection, offset)."""
    h1, w, h2, E1 = (np.asarray(v, float) for v in (plastic_thickness, width, fabric_thickness, plastic_modulus))
    mu1 = E1 / (2 * (1 + plastic_poisson))
    sec = ArmSection(np.asarray(plastic_set, float) + 0 * h1, E1 * h1 * w, E1 * h1 ** 3 * w / 12,
                     E1 * h1 * w ** 3 / 12, mu1 * (h1 ** 3 * w + w ** 3 * h1) / 24)
    return sec, 0.5 * (h1 + h2)


def _d4(h1, h2, E1, E2):
    return h1 ** 4 * E1 ** 2 + 2 * h1 * h2 * E1 * E2 * (2 * h1 ** 2 + 3 * h1 * h2 + 2 * h2 ** 2) + h2 ** 4 * E2 ** 2
