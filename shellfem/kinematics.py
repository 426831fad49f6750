"""Discrete shell kinematics: first and second fundamental forms per triangle.

Unknowns: deformed vertex positions x (n, 3) and one angle theta per edge.

First fundamental form (edge basis E1 = x1 - x0, E2 = x2 - x0):
    a = [[E1.E1, E1.E2], [E1.E2, E2.E2]]     stored as (a11, a12, a22)

Second fundamental form: mid-edge normals with one extra degree of freedom per edge
(Grinspun et al. 2006; Chen et al. 2018, libshell's "MidedgeAngleTan" family). In
triangle f the normal at the midpoint of edge i (opposite vertex i) is tilted from the
face normal, towards the edge's outward in-plane normal, by the angle

    psi_i = phi_e / 2 + sigma_fe * theta_e        (interior edge e)
    psi_i = theta_e                               (boundary edge)

where phi_e is the signed dihedral angle of edge e (positive where the sheet bends away
from its normal, as on a sphere with outward normals) and sigma_fe = +1 in the edge's
first face, -1 in its second. Linear (Crouzeix-Raviart) interpolation of the mid-edge
normals n_i = n_f + tan(psi_i) t_i gives, exactly,

    b = -2 * sum_i tan(psi_i) * h_i * c_i c_i^T,   h_i = 2 A / |e_i|,
    c_0 = (-1, -1), c_1 = (1, 0), c_2 = (0, 1),

with the convention b_ab = -dn(E_a) . E_b: b = a / R > 0 when the centre of curvature lies
on the +normal side (a sheet with normal +z bending into a valley). With this b the metric at
height z along the normal is a(z) = a - 2 z b + O(z^2). The seed's Eq. 4.1 stencil
"(n_j - n_i).(v_j - v_i)" is b/2 in this convention (see shellfem.layers for how the
seed's bilayer coefficients map onto it).

The per-element derivatives run in compiled (numba) loops over triangles/hinges and are
exact (checked against finite differences in tests/test_kinematics.py and, for the whole
energy, tests/test_energies.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

# c_i c_i^T as (11, 12, 22) components
C_OUTER = np.array([[1.0, 1.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])

_EPS3 = np.zeros((3, 3, 3))
_EPS3[0, 1, 2] = _EPS3[1, 2, 0] = _EPS3[2, 0, 1] = 1.0
_EPS3[0, 2, 1] = _EPS3[2, 1, 0] = _EPS3[1, 0, 2] = -1.0


def _selector(n_pts: int, plus: int, minus: int) -> np.ndarray:
    """(3, 3 n_pts) matrix S with S x = x[plus] - x[minus] for stacked points x."""
    S = np.zeros((3, 3 * n_pts))
    S[:, 3 * plus:3 * plus + 3] += np.eye(3)
    S[:, 3 * minus:3 * minus + 3] -= np.eye(3)
    return S


def _cross_hessian(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Constant Hessian (3, d, d) of N = (P x) x (Q x)."""
    return np.einsum("kmn,ma,nb->kab", _EPS3, P, Q) + np.einsum("kmn,mb,na->kab", _EPS3, P, Q)


# --- constant tensors -------------------------------------------------------
_S1 = _selector(3, 1, 0)   # E1 = x1 - x0
_S2 = _selector(3, 2, 0)   # E2 = x2 - x0
#: Hessians of (a11, a12, a22) w.r.t. the 9 face coordinates (constant).
A_HESS = np.stack([2 * _S1.T @ _S1, _S1.T @ _S2 + _S2.T @ _S1, 2 * _S2.T @ _S2])
N_HESS_FACE = _cross_hessian(_S1, _S2)             # N = E1 x E2
#: edge vectors e_i opposite vertex i: x2 - x1, x0 - x2, x1 - x0

# hinge: points (e0, e1, oA, oB); e = e1 - e0, N_A = (e1 - e0) x (oA - e0),
# N_B = (e0 - e1) x (oB - e1)
_HA1, _HA2 = _selector(4, 1, 0), _selector(4, 2, 0)
_HB1, _HB2 = _selector(4, 0, 1), _selector(4, 3, 1)
#: constant Hessian (9, 12, 12) of u = (e, N_A, N_B) w.r.t. the 12 hinge coordinates
U_HESS_HINGE = np.concatenate([np.zeros((3, 12, 12)), _cross_hessian(_HA1, _HA2), _cross_hessian(_HB1, _HB2)])


# --- topology ----------------------------------------------------------------
@dataclass
class Topology:
    """Edges and their faces for a triangle mesh (edge i of a face is opposite vertex i)."""
    triangles: np.ndarray    # (m, 3)
    edges: np.ndarray        # (ne, 2) vertex pair as traversed in the edge's first face
    face_edges: np.ndarray   # (m, 3) edge id of local edge i
    edge_faces: np.ndarray   # (ne, 2) first face, second face (-1 on the boundary)
    face_sign: np.ndarray    # (m, 3) +1 if the face is the edge's first face, else -1
    flaps: np.ndarray        # (m, 3) vertex across local edge i (-1 on the boundary)
    hinge: np.ndarray        # (ni, 4) (e0, e1, oA, oB) for interior edges
    hinge_edges: np.ndarray  # (ni,) edge ids of the interior edges
    interior: np.ndarray     # (ne,) bool

    @property
    def n_edges(self) -> int:
        return len(self.edges)


def build_topology(triangles: np.ndarray) -> Topology:
    t = np.asarray(triangles, dtype=np.int64)
    m = len(t)
    a = t[:, [1, 2, 0]].ravel()      # local edge i: (t[i+1], t[i+2])
    b = t[:, [2, 0, 1]].ravel()
    key = np.minimum(a, b) * (t.max() + 1) + np.maximum(a, b)
    uniq, first_idx, inv, counts = np.unique(key, return_index=True, return_inverse=True, return_counts=True)
    if counts.max() > 2:
        bad = int(np.argmax(counts > 2))
        raise ValueError(f"non-manifold edge {divmod(int(uniq[bad]), t.max() + 1)} shared by {counts[bad]} triangles")
    ne = len(uniq)
    face_edges = inv.reshape(m, 3)
    half = np.arange(3 * m)
    is_first = np.zeros(3 * m, bool)
    is_first[first_idx] = True
    edge_faces = -np.ones((ne, 2), dtype=np.int64)
    edge_local = -np.ones((ne, 2), dtype=np.int64)
    edge_faces[inv[is_first], 0] = half[is_first] // 3
    edge_local[inv[is_first], 0] = half[is_first] % 3
    edge_faces[inv[~is_first], 1] = half[~is_first] // 3
    edge_local[inv[~is_first], 1] = half[~is_first] % 3
    edges = np.column_stack([a[first_idx], b[first_idx]])
    # consistent orientation: the second face must traverse the edge backwards
    sec = ~is_first
    if np.any(a[sec] != edges[inv[sec], 1]):
        raise ValueError("triangles are not consistently oriented")
    face_sign = np.where(is_first, 1, -1).reshape(m, 3)
    interior = edge_faces[:, 1] >= 0
    flaps = -np.ones((m, 3), dtype=np.int64)
    fA, lA = edge_faces[interior, 0], edge_local[interior, 0]
    fB, lB = edge_faces[interior, 1], edge_local[interior, 1]
    oA, oB = t[fA, lA], t[fB, lB]
    flaps[fA, lA] = oB
    flaps[fB, lB] = oA
    hinge = np.column_stack([edges[interior, 0], edges[interior, 1], oA, oB])
    return Topology(t, edges, face_edges, edge_faces, face_sign, flaps, hinge, np.flatnonzero(interior), interior)


#: vertex pairs (plus, minus) of the edge vectors e_i opposite vertex i: x2 - x1, x0 - x2, x1 - x0
_EDGE_PAIRS = np.array([[2, 1], [0, 2], [1, 0]])


# --- compiled per-element kernels -------------------------------------------------------
# numba, one element per loop iteration (parallel over elements, each element's sums in a
# fixed order: results are bitwise the same for any thread count). Measured on the
# 85 x 60 benchmark sheet (21k faces, 31k hinges), 2 threads: the face chain rule 0.04 s
# against 0.30 s for the vectorised numpy version (whose (m, 9, 21) temporaries dominated),
# the hinge Hessians 0.02 s against 0.11 s.
_CHUNK = 512   # elements per parallel task: scratch arrays are allocated once per chunk


@njit(cache=True, inline="always")
def _add_skew(M, r0, c0, v, s):
    """M[r0:r0+3, c0:c0+3] += s [v]x."""
    M[r0, c0 + 1] -= s * v[2]
    M[r0, c0 + 2] += s * v[1]
    M[r0 + 1, c0] += s * v[2]
    M[r0 + 1, c0 + 2] -= s * v[0]
    M[r0 + 2, c0] -= s * v[1]
    M[r0 + 2, c0 + 1] += s * v[0]


@njit(cache=True, inline="always")
def _cross_into(out, a, b):
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@njit(cache=True, inline="always")
def _diff_into(out, a, b):
    for c in range(3):
        out[c] = a[c] - b[c]


@njit(cache=True, inline="always")
def _dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True, inline="always")
def sandwich_into(J, M, K, out):
    """out = J^T M J (symmetric, both triangles) for one element; K (rows of M, cols of J) is
    scratch. Zero entries of M are skipped (M is block-sparse)."""
    K[:] = 0.0
    for r in range(M.shape[0]):
        for t in range(M.shape[1]):
            mv = M[r, t]
            if mv != 0.0:
                for b in range(J.shape[1]):
                    K[r, b] += mv * J[t, b]
    n = J.shape[1]
    for a in range(n):
        for b in range(a, n):
            s = 0.0
            for r in range(J.shape[0]):
                s += J[r, a] * K[r, b]
            out[a, b] = s
            out[b, a] = s


@njit(cache=True, parallel=True)
def _face_chain_kernel(xf, face_sign, face_hinge, hinge_cols, gphi, Wy, Wyy, nh, ah, pairs, hessian, g, H):
    m = xf.shape[0]
    for chunk in prange((m + _CHUNK - 1) // _CHUNK):
        V = np.empty((4, 3))                      # E1, E2, N, uN
        J = np.empty((9, 21))                     # dy/dq, y = (a, h, psi)
        JN = np.empty((3, 9))
        gN = np.empty(9)
        ls = np.empty(3)
        us = np.empty((3, 3))
        K = np.empty((9, 21))
        PJ = np.empty((3, 9))
        S = np.empty((9, 9))
        G = np.empty(9)
        for f in range(chunk * _CHUNK, min(m, (chunk + 1) * _CHUNK)):
            E1, E2, N, uN = V[0], V[1], V[2], V[3]
            _diff_into(E1, xf[f, 1], xf[f, 0])
            _diff_into(E2, xf[f, 2], xf[f, 0])
            J[:] = 0.0
            for c in range(3):
                J[0, 3 + c] = 2 * E1[c]
                J[0, c] = -2 * E1[c]
                J[1, 3 + c] = E2[c]
                J[1, 6 + c] = E1[c]
                J[1, c] = -(E1[c] + E2[c])
                J[2, 6 + c] = 2 * E2[c]
                J[2, c] = -2 * E2[c]
            _cross_into(N, E1, E2)
            n = np.sqrt(_dot3(N, N))
            for c in range(3):
                uN[c] = N[c] / n
            JN[:] = 0.0                           # d(E1 x E2) = -[E2]x dE1 + [E1]x dE2
            _add_skew(JN, 0, 3, E2, -1.0)
            _add_skew(JN, 0, 6, E1, 1.0)
            _add_skew(JN, 0, 0, E2, 1.0)
            _add_skew(JN, 0, 0, E1, -1.0)
            for d in range(9):
                gN[d] = uN[0] * JN[0, d] + uN[1] * JN[1, d] + uN[2] * JN[2, d]
            for i in range(3):                    # h_i = |N| / l_i
                p, q = pairs[i, 0], pairs[i, 1]
                _diff_into(us[i], xf[f, p], xf[f, q])
                l = np.sqrt(_dot3(us[i], us[i]))
                ls[i] = l
                for c in range(3):
                    us[i, c] /= l
                for d in range(9):
                    J[3 + i, d] = gN[d] / l
                for c in range(3):
                    J[3 + i, 3 * p + c] -= n / (l * l) * us[i, c]
                    J[3 + i, 3 * q + c] += n / (l * l) * us[i, c]
            for i in range(3):                    # psi_i = sigma theta + phi / 2
                J[6 + i, 18 + i] = face_sign[f, i]
                k = face_hinge[f, i]
                if k >= 0:
                    for j in range(12):
                        J[6 + i, hinge_cols[f, i, j]] += 0.5 * gphi[k, j]
            w = Wy[f]
            for j in range(21):
                s = 0.0
                for r in range(9):
                    s += w[r] * J[r, j]
                g[f, j] = s
            if not hessian:
                continue
            Hf = H[f]
            sandwich_into(J, Wyy[f], K, Hf)
            # second derivatives of y on the own 9 coordinates: sum_k W_a,k A_k + sum_i W_h,i d2h_i,
            # d2h_i = H_N / l_i - (gN gl_i^T + gl_i gN^T) / l_i^2 + 2 |N| gl_i gl_i^T / l_i^3
            # - |N| H_li / l_i^2, H_N = JN^T (I - uN uN^T) JN / |N| + sum_c uN_c N_HESS_FACE[c]
            for d in range(9):
                t_ = uN[0] * JN[0, d] + uN[1] * JN[1, d] + uN[2] * JN[2, d]
                for c in range(3):
                    PJ[c, d] = (JN[c, d] - uN[c] * t_) / n
            s_wl = w[3] / ls[0] + w[4] / ls[1] + w[5] / ls[2]
            for a in range(9):
                for b in range(9):
                    v = s_wl * (JN[0, a] * PJ[0, b] + JN[1, a] * PJ[1, b] + JN[2, a] * PJ[2, b])
                    for c in range(3):
                        v += w[c] * ah[c, a, b] + s_wl * uN[c] * nh[c, a, b]
                    S[a, b] = v
            G[:] = 0.0
            for i in range(3):
                p, q = pairs[i, 0], pairs[i, 1]
                l = ls[i]
                cw = w[3 + i] / (l * l)
                cb = n * w[3 + i] / (l * l * l)
                for c in range(3):
                    G[3 * p + c] += cw * us[i, c]
                    G[3 * q + c] -= cw * us[i, c]
                for a in range(3):       # 2|N| w gl gl^T / l^3 - |N| w H_l / l^2 on the pair (p, q)
                    for b in range(3):
                        B = cb * (3 * us[i, a] * us[i, b] - (1.0 if a == b else 0.0))
                        S[3 * p + a, 3 * p + b] += B
                        S[3 * q + a, 3 * q + b] += B
                        S[3 * p + a, 3 * q + b] -= B
                        S[3 * q + a, 3 * p + b] -= B
            for a in range(9):
                for b in range(a, 9):
                    Hf[a, b] += S[a, b] - gN[a] * G[b] - G[a] * gN[b]
                for b in range(a):
                    Hf[a, b] = Hf[b, a]


def face_chain(xf, face_sign, face_hinge, hinge_cols, gphi, Wy, Wyy=None, out=None):
    """Chain rule from a face energy's derivatives in y = (a, h, psi) to the face's 21 DOFs
    (own 3 vertices, 3 flap vertices, 3 edge angles):

        W_q = J^T W_y,   W_qq = J^T W_yy J + sum_k W_y,k d2y_k/dq2   (a and h parts)

    xf (m, 3, 3) face points (mm); face_sign (m, 3) the edge angles' signs; face_hinge (m, 3)
    hinge of each local edge (-1 on the boundary); hinge_cols (m, 3, 12) the hinge's 12
    coordinates among the face's first 18 DOFs; gphi (k, 12) dihedral-angle gradients; W_y
    (m, 9), W_yy (m, 9, 9). The dihedral angles' own second derivatives are hinge terms
    (assembled per hinge by the caller). Returns W_q (m, 21) and W_qq (m, 21, 21) (None
    without W_yy), the latter written into ``out`` if given (a reused buffer saves the page
    faults of a fresh 74 MB array on the benchmark sheet: 24 -> 7 ms)."""
    m = len(xf)
    hessian = Wyy is not None
    g = np.empty((m, 21))
    H = (_buffer(out, (m, 21, 21)) if hessian else np.empty((0, 21, 21)))
    _face_chain_kernel(np.ascontiguousarray(xf, dtype=float), np.asarray(face_sign, float), face_hinge, hinge_cols,
                       gphi, Wy, Wyy if hessian else np.zeros((0, 9, 9)), _N_HESS_C, _A_HESS_C, _EDGE_PAIRS,
                       hessian, g, H)
    return g, (H if hessian else None)


def _buffer(out, shape):
    if out is None:
        return np.empty(shape)
    if out.shape != shape or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise ValueError(f"output buffer {out.shape} {out.dtype} is not a C-contiguous float64 {shape}")
    return out


@njit(cache=True, parallel=True)
def _face_metrics_kernel(xf, pairs):
    m = xf.shape[0]
    a = np.empty((m, 3))
    h = np.empty((m, 3))
    for f in prange(m):
        e1x, e1y, e1z = xf[f, 1, 0] - xf[f, 0, 0], xf[f, 1, 1] - xf[f, 0, 1], xf[f, 1, 2] - xf[f, 0, 2]
        e2x, e2y, e2z = xf[f, 2, 0] - xf[f, 0, 0], xf[f, 2, 1] - xf[f, 0, 1], xf[f, 2, 2] - xf[f, 0, 2]
        a[f, 0] = e1x * e1x + e1y * e1y + e1z * e1z
        a[f, 1] = e1x * e2x + e1y * e2y + e1z * e2z
        a[f, 2] = e2x * e2x + e2y * e2y + e2z * e2z
        nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
        n = np.sqrt(nx * nx + ny * ny + nz * nz)
        for i in range(3):
            p, q = pairs[i, 0], pairs[i, 1]
            dx, dy, dz = xf[f, p, 0] - xf[f, q, 0], xf[f, p, 1] - xf[f, q, 1], xf[f, p, 2] - xf[f, q, 2]
            h[f, i] = n / np.sqrt(dx * dx + dy * dy + dz * dz)
    return a, h


def face_metrics(xf: np.ndarray):
    """First fundamental form a = (E1.E1, E1.E2, E2.E2) (m, 3) (mm^2) and heights
    h_i = 2 A / |e_i| (m, 3) (mm) of faces with points xf (m, 3, 3). Their derivatives live
    in face_chain."""
    return _face_metrics_kernel(np.ascontiguousarray(xf, dtype=float), _EDGE_PAIRS)


@njit(cache=True, parallel=True)
def _hinge_kernel(xh, weights, uh, order, phi, grad, H):
    k = xh.shape[0]
    for chunk in prange((k + _CHUNK - 1) // _CHUNK):
        V = np.empty((8, 3))                      # e, E2, F1, F2, NA, NB, NA x NB, e / |e|
        Ju = np.empty((9, 12))
        gY = np.empty(9)
        gX = np.empty(9)
        gu = np.empty(9)
        Hu = np.empty((9, 9))
        K = np.empty((9, 12))
        for t in range(chunk * _CHUNK, min(k, (chunk + 1) * _CHUNK)):
            e, E2, F1, F2, NA, NB, NAxNB, eh = V[0], V[1], V[2], V[3], V[4], V[5], V[6], V[7]
            _diff_into(e, xh[t, 1], xh[t, 0])
            _diff_into(E2, xh[t, 2], xh[t, 0])
            _diff_into(F1, xh[t, 0], xh[t, 1])
            _diff_into(F2, xh[t, 3], xh[t, 1])
            _cross_into(NA, e, E2)
            _cross_into(NB, F1, F2)
            _cross_into(NAxNB, NA, NB)
            l = np.sqrt(_dot3(e, e))
            Y = _dot3(e, NAxNB)
            dot = _dot3(NA, NB)
            Xv = l * dot
            phi[t] = np.arctan2(Y, Xv)
            if order == 0:
                continue
            for c in range(3):
                eh[c] = e[c] / l
            Ju[:] = 0.0                           # d(e, NA, NB) / d(12 coordinates)
            for c in range(3):
                Ju[c, c] = -1.0
                Ju[c, 3 + c] = 1.0
            _add_skew(Ju, 3, 3, E2, -1.0)         # NA = e x E2
            _add_skew(Ju, 3, 6, e, 1.0)
            _add_skew(Ju, 3, 0, E2, 1.0)
            _add_skew(Ju, 3, 0, e, -1.0)
            _add_skew(Ju, 6, 0, F2, -1.0)         # NB = F1 x F2
            _add_skew(Ju, 6, 9, F1, 1.0)
            _add_skew(Ju, 6, 3, F2, 1.0)
            _add_skew(Ju, 6, 3, F1, -1.0)
            _cross_into(gY[3:6], NB, e)
            _cross_into(gY[6:9], e, NA)
            for c in range(3):
                gY[c] = NAxNB[c]
                gX[c] = dot * eh[c]
                gX[3 + c] = l * NB[c]
                gX[6 + c] = l * NA[c]
            r2 = Y * Y + Xv * Xv
            pY, pX = Xv / r2, -Y / r2
            for r in range(9):
                gu[r] = pY * gY[r] + pX * gX[r]
            for j in range(12):
                s = 0.0
                for r in range(9):
                    s += gu[r] * Ju[r, j]
                grad[t, j] = s
            if order == 1:
                continue
            # Hu = pYY (gY gY^T - gX gX^T) + pXY (gY gX^T + gX gY^T) + pY HY + pX HX (pXX = -pYY)
            r4 = r2 * r2
            pYY, pXY = -2 * Xv * Y / r4, (Y * Y - Xv * Xv) / r4
            for a in range(9):
                for b in range(9):
                    Hu[a, b] = pYY * (gY[a] * gY[b] - gX[a] * gX[b]) + pXY * (gY[a] * gX[b] + gX[a] * gY[b])
            c1 = pX * dot / l
            for a in range(3):
                Hu[a, a] += c1
                for b in range(3):
                    Hu[a, b] -= c1 * eh[a] * eh[b]
                    Hu[a, 3 + b] += pX * eh[a] * NB[b]
                    Hu[3 + b, a] += pX * eh[a] * NB[b]
                    Hu[a, 6 + b] += pX * eh[a] * NA[b]
                    Hu[6 + b, a] += pX * eh[a] * NA[b]
                Hu[6 + a, 3 + a] += pX * l
                Hu[3 + a, 6 + a] += pX * l
            _add_skew(Hu, 0, 3, NB, -pY)
            _add_skew(Hu, 3, 0, NB, pY)
            _add_skew(Hu, 0, 6, NA, pY)
            _add_skew(Hu, 6, 0, NA, -pY)
            _add_skew(Hu, 6, 3, e, pY)
            _add_skew(Hu, 3, 6, e, -pY)
            Ht = H[t]
            sandwich_into(Ju, Hu, K, Ht)
            for a in range(12):
                for b in range(a, 12):
                    s = Ht[a, b]
                    for r in range(6):
                        s += gu[3 + r] * uh[r, a, b]
                    Ht[a, b] = weights[t] * s
                    Ht[b, a] = weights[t] * s


# --- dihedral angles ------------------------------------------------------------
def hinge_angles(xh: np.ndarray, with_hessian: bool = True, weights=None, out=None):
    """Signed dihedral angles of hinges xh (k, 4, 3) = (e0, e1, oA, oB), with gradient
    (k, 12) and Hessian (k, 12, 12) (None without; written into ``out`` if given). Positive
    when the sheet bends away from the normal of face A = (e0, e1, oA) (convex side up). With
    ``weights`` (k,) the Hessians come multiplied by them (w_k d2phi_k, the chain rule's term,
    without a separate pass over the (k, 12, 12) array).

    phi = atan2(Y, X) with Y = e . (N_A x N_B), X = |e| N_A . N_B, through the 9 intermediate
    values u = (e, N_A, N_B), which are bilinear in the coordinates (constant Hessian)."""
    k = len(xh)
    w = np.ones(k) if weights is None else np.ascontiguousarray(weights, dtype=float)
    phi, g = np.empty(k), np.empty((k, 12))
    H = _buffer(out, (k, 12, 12)) if with_hessian else np.empty((0, 12, 12))
    _hinge_kernel(np.ascontiguousarray(xh, dtype=float), w, _U_HESS_C, 2 if with_hessian else 1, phi, g, H)
    return phi, g, (H if with_hessian else None)


def hinge_angle_values(xh: np.ndarray) -> np.ndarray:
    """Signed dihedral angles only (k,) of hinges xh (k, 4, 3), as hinge_angles."""
    phi = np.empty(len(xh))
    _hinge_kernel(np.ascontiguousarray(xh, dtype=float), np.ones(0), _U_HESS_C, 0, phi, np.empty((0, 12)),
                  np.empty((0, 12, 12)))
    return phi


_N_HESS_C = np.ascontiguousarray(N_HESS_FACE)
_A_HESS_C = np.ascontiguousarray(A_HESS)
_U_HESS_C = np.ascontiguousarray(U_HESS_HINGE[3:9])
