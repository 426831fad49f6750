"""Energy densities per triangle, with exact gradients and Hessians (N, mm, MPa).

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
block, D = k_B:  1/2 k_B [nu tr(B)^2 + (1 - nu) tr(B^2)].

Fabric membrane (bare fabric), functions of a only:
- neo-Hookean (seed Eq. 3.2):  h A_rest / 2 [mu (I1 - 2 - 2 ln J) + lambda (ln J)^2],
  I1 = tr(abar^-1 a), J^2 = det a / det abar, lambda = E nu / (1 - nu^2), mu = E / (2 (1 + nu)).
- orthotropic log-barrier (seed Eq. 4.2-4.3):  h A_rest Psi(eps), eps = (e11, e22, 2 e12) the
  Green strain in the course frame,
  Psi = 1/2 eps^T C eps / (1 - nu^2) + f1(e11) + f2(e22),
  C = [[a1, sqrt(a1 a2) nu, 0], [sqrt(a1 a2) nu, a2, 0], [0, 0, a3 (1 - nu^2)]],
  f_i(e) = -phi_i(e) = b_i ((g_i - |e|) ln(1 - |e| / g_i) + |e|),  so dPsi/deps is the seed's
  Eq. 4.5 (its Eq. 4.2 omits the 1/2 that Eq. 4.5 implies).
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from shellfem.kinematics import C_OUTER, sandwich_into

_BASIS = np.array([[[1.0, 0.0], [0.0, 0.0]], [[0.0, 1.0], [1.0, 0.0]], [[0.0, 0.0], [0.0, 1.0]]])


def sym_to_mat(s: np.ndarray) -> np.ndarray:
    """(…, 3) components (11, 12, 22) -> (…, 2, 2) symmetric matrices."""
    return np.stack([np.stack([s[..., 0], s[..., 1]], -1), np.stack([s[..., 1], s[..., 2]], -1)], -2)


def rest_area(abar: np.ndarray) -> np.ndarray:
    """Area (mm^2) of a triangle whose edge-basis metric is abar (m, 3)."""
    return 0.5 * np.sqrt(abar[:, 0] * abar[:, 2] - abar[:, 1] ** 2)


def elastic_norm_matrix(abar: np.ndarray, nu) -> np.ndarray:
    """K (m, 3, 3) with ||abar^-1 S||^2 = s^T K s for S with components s = (11, 12, 22)."""
    ainv = np.linalg.inv(sym_to_mat(abar))
    M = np.einsum("mij,kjl->mkil", ainv, _BASIS)          # abar^-1 B_k
    t = np.einsum("mkii->mk", M)
    P = np.einsum("mjab,mkba->mjk", M, M)
    nu = np.broadcast_to(np.asarray(nu, float), (len(abar),))
    return (nu / (1 - nu ** 2))[:, None, None] * t[:, :, None] * t[:, None, :] + P / (1 + nu)[:, None, None]


def layer_quadratic(abar, bbar, E, nu, z0, z1, area=None):
    """Q (m,6,6), rest state zbar (m,6) of one layer: W = 1/2 (z - zbar)^T Q (z - zbar)."""
    m = len(abar)
    E, z0, z1 = (np.broadcast_to(np.asarray(v, float), (m,)) for v in (E, z0, z1))
    K = elastic_norm_matrix(abar, nu)
    A = rest_area(abar) if area is None else area
    m0, m1, m2 = z1 - z0, (z1 ** 2 - z0 ** 2) / 2, (z1 ** 3 - z0 ** 3) / 3
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


# --- fabric membrane models ----------------------------------------------------
_DET_HESS = np.array([[0.0, 0.0, 1.0], [0.0, -2.0, 0.0], [1.0, 0.0, 0.0]])


def neo_hookean(a, abar, E, nu, h, area=None):
    """Seed Eq. 3.2 per triangle; returns W (m,), dW/da (m,3), d2W/da2 (m,3,3).
    W = +inf where the triangle is inverted or degenerate (det a <= 0)."""
    A = rest_area(abar) if area is None else area
    lam, mu = E * nu / (1 - nu ** 2), E / (2 * (1 + nu))
    D = a[:, 0] * a[:, 2] - a[:, 1] ** 2
    Dbar = abar[:, 0] * abar[:, 2] - abar[:, 1] ** 2
    t = np.stack([abar[:, 2], -2 * abar[:, 1], abar[:, 0]], 1) / Dbar[:, None]    # tr(abar^-1 a) = t . a
    bad = D <= 0
    Ds = np.where(bad, 1.0, D)
    lnD = np.log(Ds) - np.log(Dbar)
    I1 = np.einsum("mi,mi->m", t, a)
    c = h * A / 2
    W = c * (mu * (I1 - 2 - lnD) + lam / 4 * lnD ** 2)
    gD = np.stack([a[:, 2], -2 * a[:, 1], a[:, 0]], 1)
    glnD = gD / Ds[:, None]
    HlnD = _DET_HESS[None] / Ds[:, None, None] - glnD[:, :, None] * glnD[:, None, :]
    g = c[:, None] * (mu * (t - glnD) + lam / 2 * lnD[:, None] * glnD)
    H = c[:, None, None] * (-mu * HlnD + lam / 2 * glnD[:, :, None] * glnD[:, None, :]
                            + lam / 2 * lnD[:, None, None] * HlnD)
    W = np.where(bad, np.inf, W)
    return W, g, H


def strain_map(rest_edges: np.ndarray):
    """Affine map a -> Voigt Green strain (e11, e22, 2 e12): eps = T a + (-1/2, -1/2, 0).

    rest_edges: (m, 2, 2) columns = rest edge vectors E1, E2 in the material frame (mm)."""
    Rinv = np.linalg.inv(rest_edges)
    G = np.einsum("mji,kjl,mln->mkin", Rinv, _BASIS, Rinv)   # R^-T B_k R^-1
    T = np.stack([0.5 * G[:, :, 0, 0], 0.5 * G[:, :, 1, 1], G[:, :, 0, 1]], 1)
    return T


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


def orthotropic(a, T, params, nu, h, area):
    """Seed Eq. 4.2-4.3 per triangle; returns W, dW/da, d2W/da2 (W = inf outside the barrier)."""
    a1, a2, a3 = params["a1"], params["a2"], params["a3"]
    eps = np.einsum("mik,mk->mi", T, a) - np.array([0.5, 0.5, 0.0])
    C = np.array([[a1, np.sqrt(a1 * a2) * nu, 0.0], [np.sqrt(a1 * a2) * nu, a2, 0.0],
                  [0.0, 0.0, a3 * (1 - nu ** 2)]]) / (1 - nu ** 2)
    Ce = eps @ C
    f1, d1, dd1 = log_barrier(eps[:, 0], params["b1"], params["g1"])
    f2, d2, dd2 = log_barrier(eps[:, 1], params["b2"], params["g2"])
    c = h * area
    W = c * (0.5 * np.einsum("mi,mi->m", eps, Ce) + f1 + f2)
    ge = Ce.copy()
    ge[:, 0] += d1
    ge[:, 1] += d2
    He = np.broadcast_to(C, (len(a), 3, 3)).copy()
    He[:, 0, 0] += np.where(np.isfinite(dd1), dd1, 0.0)
    He[:, 1, 1] += np.where(np.isfinite(dd2), dd2, 0.0)
    g = c[:, None] * np.einsum("mi,mik->mk", ge, T)
    H = c[:, None, None] * np.einsum("mik,mij,mjl->mkl", T, He, T)
    return W, g, H


# --- the face energy as a function of y = (a, h, psi) --------------------------------
#: Mid-edge tilt angles must stay below this (tan(psi) blows up at pi / 2); beyond it the
#: energy is +inf.
PSI_MAX = 0.49 * np.pi


def second_fundamental_form(h, psi):
    """b (m,3) = -2 sum_i tan(psi_i) h_i c_i c_i^T."""
    return -2 * np.einsum("mi,ik->mk", np.tan(psi) * h, C_OUTER)


def face_energy(a, h, psi, quad: QuadraticForm, membrane=None, order: int = 2):
    """Energy per face and its derivatives w.r.t. y = (a11, a12, a22, h0, h1, h2, psi0..2).

    membrane: optional callable a -> (W, g, H) added to the a-part (fabric models).
    Returns W (m,), W_y (m, 9) (order >= 1) and W_yy (m, 9, 9) (order 2), None where not asked;
    W = +inf where an angle leaves |psi| < PSI_MAX. The layered quadratic and the chain rule
    z = (a, b(h, psi)) -> y run in one compiled loop over the faces (the vectorised version's
    (m, 6, 9) products cost 20 of its 26 ms at 21k faces).
    """
    m = len(a)
    if membrane is not None:
        Wm, gm, Hm = membrane(a)
    else:
        Wm, gm, Hm = np.zeros(m), np.zeros((m, 3)), np.zeros((m, 3, 3))
    ptr, Qs, zbars = quad.packed()
    W = np.empty(m)
    Wy = np.empty((m if order >= 1 else 0, 9))
    Wyy = np.empty((m if order >= 2 else 0, 9, 9))
    _face_energy_kernel(np.ascontiguousarray(a, dtype=float), np.ascontiguousarray(h, dtype=float),
                        np.ascontiguousarray(psi, dtype=float), ptr, Qs, zbars, quad.Q, np.asarray(Wm, float),
                        np.ascontiguousarray(gm, dtype=float), np.ascontiguousarray(Hm, dtype=float), C_OUTER, order,
                        W, Wy, Wyy)
    W = np.where(np.abs(psi).max(1) >= PSI_MAX, np.inf, W)
    return W, (Wy if order >= 1 else None), (Wyy if order >= 2 else None)


@njit(cache=True, parallel=True)
def _face_energy_kernel(a, h, psi, ptr, Qs, zbars, Qtot, Wm, gm, Hm, C, order, W, Wy, Wyy):
    m = a.shape[0]
    for f in prange(m):
        z = np.empty(6)
        Wz = np.zeros(6)
        d = np.empty(6)
        tp = np.empty(3)
        sec2 = np.empty(3)
        for i in range(3):
            tp[i] = np.tan(psi[f, i])
            sec2[i] = 1.0 + tp[i] * tp[i]
        for k in range(3):
            z[k] = a[f, k]
            z[3 + k] = -2.0 * (tp[0] * h[f, 0] * C[0, k] + tp[1] * h[f, 1] * C[1, k] + tp[2] * h[f, 2] * C[2, k])
        w = 0.0
        for t in range(ptr[f], ptr[f + 1]):        # sum of squares, layer by layer (no cancellation)
            for k in range(6):
                d[k] = z[k] - zbars[t, k]
            for k in range(6):
                qd = 0.0
                for l in range(6):
                    qd += Qs[t, k, l] * d[l]
                w += 0.5 * d[k] * qd
                Wz[k] += qd
        W[f] = w + Wm[f]
        if order == 0:
            continue
        for k in range(3):
            Wz[k] += gm[f, k]
        # dz_b,k/dh_i = -2 tp_i C_ik,  dz_b,k/dpsi_i = -2 sec2_i h_i C_ik
        gi = np.empty(3)
        for i in range(3):
            gi[i] = Wz[3] * C[i, 0] + Wz[4] * C[i, 1] + Wz[5] * C[i, 2]
            Wy[f, i] = Wz[i]
            Wy[f, 3 + i] = -2.0 * tp[i] * gi[i]
            Wy[f, 6 + i] = -2.0 * sec2[i] * h[f, i] * gi[i]
        if order == 1:
            continue
        J = np.zeros((6, 9))
        for k in range(3):
            J[k, k] = 1.0
            for i in range(3):
                J[3 + k, 3 + i] = -2.0 * tp[i] * C[i, k]
                J[3 + k, 6 + i] = -2.0 * sec2[i] * h[f, i] * C[i, k]
        Z = np.empty((6, 6))
        for k in range(6):
            for l in range(6):
                Z[k, l] = Qtot[f, k, l]
        for k in range(3):
            for l in range(3):
                Z[k, l] += Hm[f, k, l]
        H = Wyy[f]
        sandwich_into(J, Z, np.empty((6, 9)), H)
        for i in range(3):
            cross = -2.0 * sec2[i] * gi[i]
            H[3 + i, 6 + i] += cross
            H[6 + i, 3 + i] += cross
            H[6 + i, 6 + i] += -4.0 * sec2[i] * tp[i] * h[f, i] * gi[i]
