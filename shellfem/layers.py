"""Layered Kirchhoff shell energies: quadratic forms of the fundamental forms (N, mm, MPa).

State per triangle: z = (a11, a12, a22, b11, b12, b22), the first and second fundamental
forms in the triangle's edge basis (see shellfem.kinematics for the convention).

Layered Kirchhoff shell (seed Eq. 3.9/4.1, integrated exactly through each layer):
a layer of Young's modulus E, Poisson's ratio nu, occupying z in [z0, z1] about the mesh
surface, with rest metric abar and rest curvature bbar, has Green strain

    eps(z) = 1/2 (abar^-1 a - I) - z abar^-1 (b - bbar)

and energy  int (E/2) ||eps(z)||^2 dz dA_rest, with the elastic norm of seed Eq. 3.8,

    ||M||^2 = nu/(1-nu^2) tr(M)^2 + 1/(1+nu) tr(M^2).

Integrating gives  E [ m0/8 ||A||^2 - m1/2 <A, B> + m2/2 ||B||^2 ] with A = abar^-1 a - I,
B = abar^-1 (b - bbar), m0 = z1 - z0, m1 = (z1^2 - z0^2)/2, m2 = (z1^3 - z0^3)/3.
For a layer centred on the surface this is the standard  E [h/8 ||A||^2 + h^3/24 ||B||^2].
Mapping to the seed: its Eq. 3.9 equals 1/2 of this energy written with b_seed = 2 b for
layers [0, h1] and [-h2, 0]; the seed's stencil "(n_j - n_i).(v_j - v_i)" is b/2, so its
formula only has the stated meaning with b_seed = 4 x stencil. The narrow-strip tests
(tests/test_strip.py) check that this energy gives Timoshenko's bilayer curvature.

Every layered energy is quadratic in z:  W = 1/2 z^T Q z - q^T z + c  with Q, q, c
precomputed per triangle. Fabric bending in bare fabric is the same with only the bending
block, D = k_B:  1/2 k_B [nu tr(B)^2 + (1 - nu) tr(B^2)]. The bare fabric's membrane
energy is not quadratic; it is a membrane model of shellfem.materials.
"""
from __future__ import annotations

import numpy as np

#: The symmetric 2x2 basis matrices of the components (11, 12, 22).
SYM_BASIS = np.array([[[1.0, 0.0], [0.0, 0.0]], [[0.0, 1.0], [1.0, 0.0]], [[0.0, 0.0], [0.0, 1.0]]])


def sym_to_mat(s: np.ndarray) -> np.ndarray:
    """(…, 3) components (11, 12, 22) -> (…, 2, 2) symmetric matrices."""
    return np.stack([np.stack([s[..., 0], s[..., 1]], -1), np.stack([s[..., 1], s[..., 2]], -1)], -2)


def rest_area(abar: np.ndarray) -> np.ndarray:
    """Area (mm^2) of a triangle whose edge-basis metric is abar (m, 3)."""
    return 0.5 * np.sqrt(abar[:, 0] * abar[:, 2] - abar[:, 1] ** 2)


def elastic_norm_matrix(abar: np.ndarray, nu) -> np.ndarray:
    """K (m, 3, 3) with ||abar^-1 S||^2 = s^T K s for S with components s = (11, 12, 22)."""
    ainv = np.linalg.inv(sym_to_mat(abar))
    M = np.einsum("mij,kjl->mkil", ainv, SYM_BASIS)          # abar^-1 B_k
    t = np.einsum("mkii->mk", M)
    P = np.einsum("mjab,mkba->mjk", M, M)
    nu = np.broadcast_to(np.asarray(nu, float), (len(abar),))
    return (nu / (1 - nu ** 2))[:, None, None] * t[:, :, None] * t[:, None, :] + P / (1 + nu)[:, None, None]


def layer_quadratic(abar, bbar, E, nu, z0, z1, area=None):
    """Q (m,6,6), rest state zbar (m,6) of one layer: W = 1/2 (z - zbar)^T Q (z - zbar)."""
    m = len(abar)
    E, z0, z1 = (np.broadcast_to(np.asarray(v, float), (m,)) for v in (E, z0, z1))
    m0, m1, m2 = z1 - z0, (z1 ** 2 - z0 ** 2) / 2, (z1 ** 3 - z0 ** 3) / 3
    return _moment_quadratic(abar, bbar, E, nu, m0, m1, m2, area)


def layer_quadratic_derivative(abar, bbar, E, nu, z0, z1, dz0, dz1, area=None):
    """dQ/dp (m,6,6) and zbar (m,6) of one layer whose bounds move with a parameter p at rates
    dz0/dp, dz1/dp (mm per unit of p; e.g. a front plastic layer [hf/2, hf/2 + t] has
    dz0/dt = 0, dz1/dt = 1). Q is linear in the moments m_k = (z1^(k+1) - z0^(k+1)) / (k+1),
    so dQ/dp is the same expression with dm_k = z1^k dz1 - z0^k dz0, and
    dW/dp = 1/2 (z - zbar)^T dQ/dp (z - zbar) exactly (zbar does not depend on p)."""
    m = len(abar)
    E, z0, z1, dz0, dz1 = (np.broadcast_to(np.asarray(v, float), (m,)) for v in (E, z0, z1, dz0, dz1))
    dm0, dm1, dm2 = dz1 - dz0, z1 * dz1 - z0 * dz0, z1 ** 2 * dz1 - z0 ** 2 * dz0
    return _moment_quadratic(abar, bbar, E, nu, dm0, dm1, dm2, area)


def _moment_quadratic(abar, bbar, E, nu, m0, m1, m2, area):
    """Q (m,6,6) = E A [[m0/4 K, -m1/2 K], [-m1/2 K, m2 K]] and zbar = (abar, bbar)."""
    m = len(abar)
    K = elastic_norm_matrix(abar, nu)
    A = rest_area(abar) if area is None else area
    w = (A * E)[:, None, None]
    Q = np.zeros((m, 6, 6))
    Q[:, :3, :3] = w * (m0 / 4)[:, None, None] * K
    Q[:, :3, 3:] = Q[:, 3:, :3] = -w * (m1 / 2)[:, None, None] * K
    Q[:, 3:, 3:] = w * m2[:, None, None] * K
    return Q, np.concatenate([abar, bbar], 1)


def bending_quadratic(abar, D, nu, area=None):
    """Q (m,6,6) of the pure bending energy 1/2 D [nu tr(B)^2 + (1-nu) tr(B^2)], bbar = 0."""
    m = len(abar)
    K = elastic_norm_matrix(abar, nu)
    A = rest_area(abar) if area is None else area
    nu = np.broadcast_to(np.asarray(nu, float), (m,))
    Q = np.zeros((m, 6, 6))
    Q[:, 3:, 3:] = (A * np.broadcast_to(D, (m,)) * (1 - nu ** 2))[:, None, None] * K
    return Q, np.concatenate([abar, np.zeros((m, 3))], 1)


class QuadraticForm:
    """Sum of layer quadratics W(z) = sum_l 1/2 (z - zbar_l)^T Q_l (z - zbar_l) per triangle.

    Kept as a sum of non-negative squares, layer by layer: expanding it into
    1/2 z^T Q z - q^T z + c cancels catastrophically (terms ~ E h ~ 10^3 N/mm against
    equilibrium energies many orders smaller) and would stall Newton at round-off."""

    def __init__(self, m: int):
        self.m = m
        self.Q = np.zeros((m, 6, 6))   # total Hessian (constant)
        self._terms = []               # (index array, Q_l, zbar_l)
        self._packed = None

    def add(self, Q, zbar, mask=None):
        idx = np.arange(self.m) if mask is None else np.flatnonzero(mask)
        if len(idx) == 0:
            return
        self.Q[idx] += Q[idx]
        self._terms.append((idx, Q[idx], zbar[idx]))
        self._packed = None

    def packed(self):
        """The terms grouped by triangle, in the order added: (ptr (m+1,), Q (K, 6, 6),
        zbar (K, 6)); triangle f's terms are ptr[f]:ptr[f+1] (for compiled kernels)."""
        if self._packed is None:
            if self._terms:
                idx = np.concatenate([t[0] for t in self._terms])
                order = np.argsort(idx, kind="stable")
                Q = np.ascontiguousarray(np.concatenate([t[1] for t in self._terms])[order])
                zbar = np.ascontiguousarray(np.concatenate([t[2] for t in self._terms])[order])
                counts = np.bincount(idx, minlength=self.m)
            else:
                Q, zbar, counts = np.zeros((0, 6, 6)), np.zeros((0, 6)), np.zeros(self.m, np.int64)
            self._packed = (np.concatenate([[0], np.cumsum(counts)]).astype(np.int64), Q, zbar)
        return self._packed

    def evaluate(self, z):
        W = np.zeros(self.m)
        g = np.zeros((self.m, 6))
        for idx, Q, zbar in self._terms:
            d = z[idx] - zbar
            Qd = (Q @ d[:, :, None])[:, :, 0]
            W[idx] += 0.5 * np.einsum("mi,mi->m", d, Qd)
            g[idx] += Qd
        return W, g, self.Q

    def minimiser(self, keep=None):
        """Per-triangle minimiser z* of W over the components ``keep`` (others held at 0)."""
        keep = np.arange(6) if keep is None else np.asarray(keep)
        q = np.zeros((self.m, 6))
        for idx, Q, zbar in self._terms:
            q[idx] += (Q @ zbar[:, :, None])[:, :, 0]
        z = np.zeros((self.m, 6))
        z[:, keep] = np.linalg.solve(self.Q[:, keep][:, :, keep], q[:, keep, None])[..., 0]
        return z
