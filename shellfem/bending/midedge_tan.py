"""The tan mid-edge second fundamental form (Chen et al. 2018, libshell's MidedgeAngleTan).

    b = -2 sum_i tan(psi_i) h_i c_i c_i^T = sum_i beta_i c_i c_i^T,   beta_i = -2 tan(psi_i) h_i

with psi_i the tilt of the mid-edge normal of edge i (rad), h_i = 2 A / |e_i| the triangle's
height over that edge (mm) and c_i c_i^T the constant outer products of shellfem.kinematics
(C_OUTER, components (11, 12, 22) in the edge basis); see shellfem.kinematics for the
derivation and the sign convention. b is linear in h, so d2 beta / dh2 = 0.

The edge coefficient and its derivatives are written once, in :func:`edge_coefficients`:
compiled (numba) for the face-energy kernel, evaluated by numpy on whole arrays by
:func:`coefficients` (EdgeAngleProblem, the model's derived fields). numba's on-disk cache
does not notice edits in another file: after changing :func:`edge_coefficients`, delete
shellfem/__pycache__/face_energy*.nbi/.nbc (or touch shellfem/face_energy.py) so the face
kernel that inlines it is recompiled.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from shellfem.kinematics import C_OUTER

#: Mid-edge tilt angles must stay below this (tan(psi) blows up at pi / 2); beyond it the
#: energy is +inf.
PSI_MAX = 0.49 * np.pi


@njit(cache=True)
def edge_coefficients(h, psi):
    """(beta, dbeta/dh, dbeta/dpsi, d2beta/dh dpsi, d2beta/dpsi2) of one edge (scalars) or
    elementwise of arrays: beta = -2 tan(psi) h."""
    tp = np.tan(psi)
    sec2 = 1.0 + tp * tp
    return -2.0 * tp * h, -2.0 * tp, -2.0 * sec2 * h, -2.0 * sec2, -4.0 * sec2 * tp * h


def coefficients(h: np.ndarray, psi: np.ndarray):
    """:func:`edge_coefficients` of arrays h, psi (m, 3), evaluated by numpy."""
    return edge_coefficients.py_func(h, psi)


def from_coefficients(beta: np.ndarray) -> np.ndarray:
    """b (m, 3) = sum_i beta_i c_i c_i^T for edge coefficients beta (m, 3)."""
    return np.einsum("mi,ik->mk", beta, C_OUTER)


def second_fundamental_form(h: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """b (m, 3) = -2 sum_i tan(psi_i) h_i c_i c_i^T of edge heights h and angles psi (m, 3)."""
    return from_coefficients(coefficients(h, psi)[0])


def inadmissible(psi: np.ndarray) -> np.ndarray:
    """(m,) True where a triangle's tilt angles (m, 3) leave |psi| < PSI_MAX (energy +inf)."""
    return np.abs(psi).max(1) >= PSI_MAX
