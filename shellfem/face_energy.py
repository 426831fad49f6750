"""The energy of each triangle as a function of y = (a, h, psi), with exact derivatives.

z = (a, b) with b = b(h, psi) the discrete second fundamental form of shellfem.bending;
W(z) = the layered energy of shellfem.layers (kept as a sum of per-layer terms; quadratic in z
apart from the exact metric's third fundamental form c = b a^-1 b, whose exact gradient and
Hessian in z are added on the triangles that carry it) + an optional membrane term W_m(a)
(a fabric model of shellfem.materials). The chain rule
z(a, h, psi) -> y runs in one compiled loop over the faces with the quadratic (the
vectorised version's (m, 6, 9) products cost 20 of its 26 ms at 21k faces). The kernel
inlines compiled helpers of other modules (the bending module's edge coefficients,
shellfem.kinematics.sandwich_into, shellfem.layers.layer_terms), whose edits numba's on-disk cache does not see: touch
this file after changing them.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from shellfem.bending.midedge_tan import edge_coefficients, inadmissible
from shellfem.kinematics import C_OUTER, sandwich_into
from shellfem.layers import QuadraticForm, layer_scratch, layer_terms

_CHUNK = 512   # faces per parallel task: scratch arrays are allocated once per chunk


def face_energy(a, h, psi, quad: QuadraticForm, membrane=None, order: int = 2):
    """Energy per face and its derivatives w.r.t. y = (a11, a12, a22, h0, h1, h2, psi0..2).

    membrane: optional callable a -> (W, g, H) added to the a-part (fabric models).
    Returns W (m,), W_y (m, 9) (order >= 1) and W_yy (m, 9, 9) (order 2), None where not asked;
    W = +inf where an angle leaves |psi| < PSI_MAX (shellfem.bending.midedge_tan).
    """
    m = len(a)
    if membrane is not None:
        Wm, gm, Hm = membrane(a)
    else:
        Wm, gm, Hm = np.zeros(m), np.zeros((m, 3)), np.zeros((m, 3, 3))
    ptr, Qs, zbars, Rs, cbars, thick, zspan = quad.packed()
    W = np.empty(m)
    Wy = np.empty((m if order >= 1 else 0, 9))
    Wyy = np.empty((m if order >= 2 else 0, 9, 9))
    _face_energy_kernel(np.ascontiguousarray(a, dtype=float), np.ascontiguousarray(h, dtype=float),
                        np.ascontiguousarray(psi, dtype=float), ptr, Qs, zbars, Rs, cbars, thick, zspan, quad.Q,
                        np.asarray(Wm, float),
                        np.ascontiguousarray(gm, dtype=float), np.ascontiguousarray(Hm, dtype=float), C_OUTER, order,
                        W, Wy, Wyy)
    W = np.where(inadmissible(psi), np.inf, W)
    return W, (Wy if order >= 1 else None), (Wyy if order >= 2 else None)


@njit(cache=True, parallel=True)
def _face_energy_kernel(a, h, psi, ptr, Qs, zbars, Rs, cbars, thick, zspan, Qtot, Wm, gm, Hm, C, order, W, Wy, Wyy):
    m = a.shape[0]
    for chunk in prange((m + _CHUNK - 1) // _CHUNK):
        z = np.empty(6)
        Wz = np.empty(6)
        # edge coefficients of b = sum_i beta_i c_i c_i^T and their derivatives
        beta = np.empty(3)
        b_h = np.empty(3)
        b_psi = np.empty(3)
        b_hpsi = np.empty(3)
        b_psipsi = np.empty(3)
        gi = np.empty(3)
        Z = np.empty((6, 6))
        J = np.zeros((6, 9))
        K = np.empty((6, 9))
        work = layer_scratch()
        for f in range(chunk * _CHUNK, min(m, (chunk + 1) * _CHUNK)):
            for i in range(3):
                beta[i], b_h[i], b_psi[i], b_hpsi[i], b_psipsi[i] = edge_coefficients(h[f, i], psi[f, i])
            for k in range(3):
                z[k] = a[f, k]
                z[3 + k] = beta[0] * C[0, k] + beta[1] * C[1, k] + beta[2] * C[2, k]
            Wz[:] = 0.0
            if order == 2:
                for k in range(6):
                    for l in range(6):
                        Z[k, l] = Qtot[f, k, l]
            w = layer_terms(z, ptr[f], ptr[f + 1], Qs, zbars, Rs, cbars, thick[f], zspan[f, 0], zspan[f, 1], order,
                            Wz, Z, work)
            W[f] = w + Wm[f]
            if order == 0:
                continue
            for k in range(3):
                Wz[k] += gm[f, k]
            # dz_b,k/dh_i = b_h_i C_ik,  dz_b,k/dpsi_i = b_psi_i C_ik
            for i in range(3):
                gi[i] = Wz[3] * C[i, 0] + Wz[4] * C[i, 1] + Wz[5] * C[i, 2]
                Wy[f, i] = Wz[i]
                Wy[f, 3 + i] = b_h[i] * gi[i]
                Wy[f, 6 + i] = b_psi[i] * gi[i]
            if order == 1:
                continue
            for k in range(3):                  # J's a-block is the identity, the rest is set here
                J[k, k] = 1.0
                for i in range(3):
                    J[3 + k, 3 + i] = b_h[i] * C[i, k]
                    J[3 + k, 6 + i] = b_psi[i] * C[i, k]
            for k in range(3):
                for l in range(3):
                    Z[k, l] += Hm[f, k, l]
            H = Wyy[f]
            sandwich_into(J, Z, K, H)
            for i in range(3):                      # b is linear in h: no h-h term
                cross = b_hpsi[i] * gi[i]
                H[3 + i, 6 + i] += cross
                H[6 + i, 3 + i] += cross
                H[6 + i, 6 + i] += b_psipsi[i] * gi[i]
