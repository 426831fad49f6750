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
"(n_j - n_i).(v_j - v_i)" is b/2 in this convention (see shellfem.energies for how the
seed's bilayer coefficients map onto it).

Everything here is vectorised over triangles/edges and returns exact first and second
derivatives (checked against finite differences in tests/test_kinematics.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# c_i c_i^T as (11, 12, 22) components
C_OUTER = np.array([[1.0, 1.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])

_EPS3 = np.zeros((3, 3, 3))
_EPS3[0, 1, 2] = _EPS3[1, 2, 0] = _EPS3[2, 0, 1] = 1.0
_EPS3[0, 2, 1] = _EPS3[2, 1, 0] = _EPS3[1, 0, 2] = -1.0


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x with [v]x w = v x w, batched over leading axes."""
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


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
_SE = [_selector(3, 2, 1), _selector(3, 0, 2), _selector(3, 1, 0)]

# hinge: points (e0, e1, oA, oB); e = e1 - e0, N_A = (e1 - e0) x (oA - e0),
# N_B = (e0 - e1) x (oB - e1)
_HE = _selector(4, 1, 0)
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


def sandwich(J: np.ndarray, H: np.ndarray) -> np.ndarray:
    """J^T H J per element for J (m, r, d), H (m, r, r). matmul on a swapped (strided) view
    takes numpy's slow path; a contiguous transpose is ~4x faster for these small blocks."""
    return np.matmul(np.ascontiguousarray(np.swapaxes(J, 1, 2)), np.matmul(H, J))


# --- first fundamental form ---------------------------------------------------
def first_fundamental_form(xf: np.ndarray):
    """a = (a11, a12, a22) and its Jacobian (m, 3, 9) for face points xf (m, 3, 3)."""
    E1, E2 = xf[:, 1] - xf[:, 0], xf[:, 2] - xf[:, 0]
    a = np.stack([np.einsum("ij,ij->i", E1, E1), np.einsum("ij,ij->i", E1, E2), np.einsum("ij,ij->i", E2, E2)], 1)
    m = len(xf)
    J = np.zeros((m, 3, 3, 3))
    J[:, 0, 1], J[:, 0, 0] = 2 * E1, -2 * E1
    J[:, 1, 1], J[:, 1, 2], J[:, 1, 0] = E2, E1, -(E1 + E2)
    J[:, 2, 2], J[:, 2, 0] = 2 * E2, -2 * E2
    return a, J.reshape(m, 3, 9)


# --- heights h_i = |N| / |e_i| -----------------------------------------------------
def _norm_derivs(v, Jv, Hv_const=None, hessian=True):
    """|v| with gradient and (if ``hessian``) Hessian, given v's Jacobian Jv (m,3,d) and
    its constant (3,d,d) Hessian Hv_const (None for linear v)."""
    n = np.linalg.norm(v, axis=1)
    u = v / n[:, None]
    g = np.einsum("mk,mkd->md", u, Jv)
    if not hessian:
        return n, g, None
    P = (np.eye(3)[None] - u[:, :, None] * u[:, None, :]) / n[:, None, None]
    H = sandwich(np.ascontiguousarray(Jv), P)
    if Hv_const is not None:
        H += (u @ Hv_const.reshape(3, -1)).reshape(H.shape)
    return n, g, H


def face_heights(xf: np.ndarray, with_hessian: bool = True):
    """h_i = 2 A / |e_i| (m, 3), gradients (m, 3, 9) and Hessians (m, 3, 9, 9)."""
    m = len(xf)
    X = xf.reshape(m, 9)
    E1, E2 = xf[:, 1] - xf[:, 0], xf[:, 2] - xf[:, 0]
    N = np.cross(E1, E2)
    JN = (X @ N_HESS_FACE.reshape(27, 9).T).reshape(m, 3, 9)  # N_c = 1/2 x^T H_c x, so dN_c/dx = H_c x
    nN, gN, HN = _norm_derivs(N, JN, N_HESS_FACE, hessian=with_hessian)
    h = np.empty((m, 3))
    g = np.empty((m, 3, 9))
    H = np.empty((m, 3, 9, 9)) if with_hessian else None
    for i in range(3):  # three local edges, not a loop over elements
        S = _SE[i]
        e = np.einsum("ad,md->ma", S, X)
        Je = np.broadcast_to(S, (m, 3, 9))
        l, gl, Hl = _norm_derivs(e, Je, hessian=with_hessian)
        h[:, i] = nN / l
        g[:, i] = gN / l[:, None] - (nN / l ** 2)[:, None] * gl
        if with_hessian:
            H[:, i] = (HN / l[:, None, None]
                       - (gN[:, :, None] * gl[:, None, :] + gl[:, :, None] * gN[:, None, :]) / (l ** 2)[:, None, None]
                       + (2 * nN / l ** 3)[:, None, None] * gl[:, :, None] * gl[:, None, :]
                       - (nN / l ** 2)[:, None, None] * Hl)
    return h, g, H


#: vertex pairs (plus, minus) of the edge vectors e_i in _SE
_EDGE_PAIRS = ((2, 1), (0, 2), (1, 0))


def face_heights_hessian(xf: np.ndarray, w: np.ndarray) -> np.ndarray:
    """sum_i w_i d2h_i/dx2 (m, 9, 9) for weights w (m, 3): the contraction the energy's
    Hessian needs, without forming the three (9, 9) Hessians of face_heights (3x fewer
    operations: the edge-length terms live on one vertex pair each). With
    h_i = |N| / l_i: d2h_i = H_N / l_i - (g_N gl_i^T + gl_i g_N^T) / l_i^2
    + 2 |N| gl_i gl_i^T / l_i^3 - |N| H_li / l_i^2."""
    m = len(xf)
    X = xf.reshape(m, 9)
    N = np.cross(xf[:, 1] - xf[:, 0], xf[:, 2] - xf[:, 0])
    JN = (X @ N_HESS_FACE.reshape(27, 9).T).reshape(m, 3, 9)
    nN, gN, HN = _norm_derivs(N, JN, N_HESS_FACE)
    H = HN * (w / _edge_lengths(xf)).sum(1)[:, None, None]
    G = np.zeros((m, 9))
    for i, (p, q) in enumerate(_EDGE_PAIRS):
        e = xf[:, p] - xf[:, q]
        l = np.linalg.norm(e, axis=1)
        u = e / l[:, None]
        a = w[:, i] / l ** 2
        G[:, 3 * p:3 * p + 3] += a[:, None] * u        # gl_i = (+u at p, -u at q)
        G[:, 3 * q:3 * q + 3] -= a[:, None] * u
        uu = u[:, :, None] * u[:, None, :]
        # 2|N| w gl gl^T / l^3 - |N| w H_l / l^2 with H_l = (I - u u^T) / l on the pair (p, q)
        B = (nN * w[:, i] / l ** 3)[:, None, None] * (3 * uu - np.eye(3)[None])
        for r, sr in ((p, 1.0), (q, -1.0)):
            for c, sc in ((p, 1.0), (q, -1.0)):
                H[:, 3 * r:3 * r + 3, 3 * c:3 * c + 3] += (sr * sc) * B
    H -= gN[:, :, None] * G[:, None, :] + G[:, :, None] * gN[:, None, :]
    return H


def _edge_lengths(xf):
    return np.stack([np.linalg.norm(xf[:, p] - xf[:, q], axis=1) for p, q in _EDGE_PAIRS], 1)


# --- dihedral angles ------------------------------------------------------------
def hinge_angles(xh: np.ndarray, with_hessian: bool = True):
    """Signed dihedral angles of hinges xh (k, 4, 3) = (e0, e1, oA, oB), with gradient
    (k, 12) and Hessian (k, 12, 12). Positive when the sheet bends away from the normal
    of face A = (e0, e1, oA) (convex side up)."""
    k = len(xh)
    X = xh.reshape(k, 12)
    e = xh[:, 1] - xh[:, 0]
    NA = np.cross(xh[:, 1] - xh[:, 0], xh[:, 2] - xh[:, 0])
    NB = np.cross(xh[:, 0] - xh[:, 1], xh[:, 3] - xh[:, 1])
    l = np.linalg.norm(e, axis=1)
    ehat = e / l[:, None]
    NAxNB = np.cross(NA, NB)
    Y = np.einsum("ij,ij->i", e, NAxNB)
    dot = np.einsum("ij,ij->i", NA, NB)
    Xv = l * dot
    phi = np.arctan2(Y, Xv)
    # Jacobian of u = (e, NA, NB) w.r.t. the 12 coordinates: exact for the bilinear parts
    Ju = np.empty((k, 9, 12))
    Ju[:, 0:3] = _HE
    Ju[:, 3:9] = (X @ U_HESS_HINGE[3:9].reshape(72, 12).T).reshape(k, 6, 12)
    gY = np.concatenate([NAxNB, np.cross(NB, e), np.cross(e, NA)], 1)
    gX = np.concatenate([dot[:, None] * ehat, l[:, None] * NB, l[:, None] * NA], 1)
    r2 = Y * Y + Xv * Xv
    pY, pX = Xv / r2, -Y / r2
    gu = pY[:, None] * gY + pX[:, None] * gX
    grad = (gu[:, None, :] @ Ju)[:, 0]
    if not with_hessian:
        return phi, grad, None
    # Hu = pY HY + pX HX + pYY (gY gY^T - gX gX^T) + pXY (gY gX^T + gX gY^T)   (pXX = -pYY);
    # the last two as one rank-2 product, HY / HX (block-sparse) added block by block
    r4 = r2 * r2
    pYY, pXY = -2 * Xv * Y / r4, (Y * Y - Xv * Xv) / r4
    A = np.stack([gY, gX], 2)                                            # (k, 9, 2)
    M = np.stack([np.stack([pYY, pXY], 1), np.stack([pXY, -pYY], 1)], 1)  # (k, 2, 2)
    Hu = np.matmul(np.matmul(A, M), np.ascontiguousarray(np.swapaxes(A, 1, 2)))
    SA, SB, Se = skew(NA), skew(NB), skew(e)
    c = pY[:, None, None]
    eNB = pX[:, None, None] * ehat[:, :, None] * NB[:, None, :]
    eNA = pX[:, None, None] * ehat[:, :, None] * NA[:, None, :]
    lI = (pX * l)[:, None, None] * np.eye(3)[None]
    Hu[:, 0:3, 0:3] += (pX * dot / l)[:, None, None] * (np.eye(3)[None] - ehat[:, :, None] * ehat[:, None, :])
    Hu[:, 0:3, 3:6] += eNB - c * SB
    Hu[:, 3:6, 0:3] += np.swapaxes(eNB, 1, 2) + c * SB
    Hu[:, 0:3, 6:9] += eNA + c * SA
    Hu[:, 6:9, 0:3] += np.swapaxes(eNA, 1, 2) - c * SA
    Hu[:, 6:9, 3:6] += lI + c * Se
    Hu[:, 3:6, 6:9] += lI - c * Se
    H = sandwich(Ju, Hu) + (gu @ U_HESS_HINGE.reshape(9, 144)).reshape(k, 12, 12)
    return phi, grad, H
