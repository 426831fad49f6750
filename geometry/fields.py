"""Smooth curvature-aligned line fields (n = 2 direction fields), Knoppel et al. 2013.

"Globally optimal direction fields" represents an n-direction field by one complex
number per vertex, psi = |psi| exp(i n phi) in a tangent frame, and measures smoothness
with the connection Laplacian A (psi^H A psi = sum_ij w_ij |psi_j - r_ij^n psi_i|^2, w the
cotangent weights, r_ij the discrete Levi-Civita transport). With a guidance field q (here
the maximum-|curvature| direction) the curvature-aligned field solves

    (A - lambda M) psi = M q_hat,      q_hat = q / ||q||_M            (paper Sec. 6)

and lambda in (-inf, lambda_min(A, M)) trades smoothness (lambda -> lambda_min: the
smoothest field) against alignment (lambda -> -inf: psi -> q). The paper's t in [0, 1) is
t = 1 / (1 + ||psi||_M) (reported as ``t``). The paper's other parameter, s in [-1, 1],
is not a trade-off: it blends the holomorphic (s = -1), Dirichlet (s = 0) and
anti-holomorphic (s = +1) energies. The seed (Sec. 5.3.4) uses geometry-central's
vertex connection Laplacian, i.e. the Dirichlet energy s = 0, and its "lambda" is the
lambda above: lambda = 0 default, lambda < 0 for less smoothing (Table 5.1: -0.01, -0.1).
Here s = 0 and lambda is in 1/mm^2 for meshes in mm: 1/sqrt(-lambda) is roughly the
length (mm) over which the field is smoothed (lambda = -0.1 -> ~3 mm, -0.01 -> ~10 mm;
lambda = 0 smooths over the whole surface).

Choices (documented deviations): transport r_ij is the minimal rotation between the vertex
tangent planes (an extrinsic discrete Levi-Civita connection); M is the lumped (barycentric)
mass matrix; the guidance has magnitude ||k1| - |k2|| (not |k1 - k2|) so it vanishes where
the maximum-|k| direction is ambiguous (umbilics and symmetric saddles). If the guidance is
zero everywhere (plane, exact sphere) the smoothest field (smallest eigenvector) is returned.
Deterministic: no random start vectors.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from geometry.curvature import Curvature, principal_curvature
from geometry.meshops import (cotan_weights, face_frames, face_normals, factorize, lumped_mass, rotation_between,
                              smallest_eigenvector, tangent_frames, unique_edges, vertex_normals)
from shellfem.errors import SelfshapeError


# ----------------------------------------------------------------------------- operators
def transport_angles(E: np.ndarray, VN: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """Angle rho_ij (k,) by which a tangent vector at E[:,0] turns, in the frames, when carried
    to E[:,1] by the minimal rotation between the two tangent planes."""
    i, j = E[:, 0], E[:, 1]
    t = np.einsum("kab,kb->ka", rotation_between(VN[i], VN[j]), e1[i])
    return np.arctan2(np.einsum("ij,ij->i", t, e2[j]), np.einsum("ij,ij->i", t, e1[j]))


def connection_laplacian(V: np.ndarray, F: np.ndarray, n_sym: int = 2, VN=None, frames=None):
    """Hermitian connection Laplacian A (n, n) for n_sym-direction fields (cotangent weights)."""
    if VN is None:
        VN = vertex_normals(V, F)
    e1, e2 = tangent_frames(VN) if frames is None else frames
    E, he2e, _ = unique_edges(F)
    w = np.bincount(he2e, weights=cotan_weights(V, F), minlength=len(E))
    r = np.exp(1j * n_sym * transport_angles(E, VN, e1, e2))
    i, j = E[:, 0], E[:, 1]
    nv = len(V)
    diag = np.bincount(i, weights=w, minlength=nv) + np.bincount(j, weights=w, minlength=nv)
    rows = np.concatenate([np.arange(nv), j, i])
    cols = np.concatenate([np.arange(nv), i, j])
    vals = np.concatenate([diag.astype(complex), -w * r, -w * np.conj(r)])
    return sp.csc_matrix((vals, (rows, cols)), shape=(nv, nv))


# ----------------------------------------------------------------------------- fields
@dataclass
class LineField:
    """A line field: per-face unit tangent vectors (m, 3) and the vertex solution."""
    face_dirs: np.ndarray      # (m, 3) unit, sign arbitrary (a line field)
    vertex_psi: np.ndarray     # (n,) complex, psi = |psi| exp(2 i phi) in the vertex frames
    t: float                   # the paper's alignment parameter t = 1/(1+||psi||_M) (nan if smoothest)
    smoothest: bool            # True when the guidance was zero and the smoothest field was used


def curvature_guidance(curv: Curvature, frames, n_sym: int = 2) -> np.ndarray:
    """q_v = (|k1| - |k2|) exp(i n phi1) at vertices, phi1 the angle of d1 in the vertex frame."""
    e1, e2 = frames
    phi = np.arctan2(np.einsum("ij,ij->i", curv.vertex_d1, e2), np.einsum("ij,ij->i", curv.vertex_d1, e1))
    mag = np.abs(curv.vertex_k1) - np.abs(curv.vertex_k2)
    return mag * np.exp(1j * n_sym * phi)


def _smoothest_psi(A, M):
    """The smoothest field: smallest generalised eigenvector of (A, diag(M)) by single-vector
    inverse iteration from the deterministic all-ones start, up to 200 iterations, until the
    vector changes by less than 1e-10 up to a global phase."""
    return smallest_eigenvector(A, M, np.ones(A.shape[0], dtype=complex), rtol=1e-10, max_iter=200,
                                stop="vector")[0]


def vertex_to_face(V, F, psi, VN, frames, n_sym: int = 2) -> np.ndarray:
    """Face directions (m, 3): average of the three vertex values carried into the face frame."""
    e1, _ = frames
    U, W, N = face_frames(V, F)
    z = np.zeros(len(F), dtype=complex)
    for c in range(3):
        v = F[:, c]
        t = np.einsum("kab,kb->ka", rotation_between(VN[v], N), e1[v])
        beta = np.arctan2(np.einsum("ij,ij->i", t, W), np.einsum("ij,ij->i", t, U))
        z += psi[v] * np.exp(1j * n_sym * beta)
    ang = np.angle(z) / n_sym
    return np.cos(ang)[:, None] * U + np.sin(ang)[:, None] * W


def curvature_line_field(V: np.ndarray, F: np.ndarray, lam: float = 0.0,
                         curvature: Curvature | None = None, n_sym: int = 2) -> LineField:
    """Smooth line field along the maximum-|curvature| direction (Knoppel et al. 2013).

    lam: the seed's lambda (1/mm^2 for meshes in mm), <= 0; 0 is the default smoothing,
    lam < 0 smooths less. Returns per-face unit tangent vectors (m, 3) in a LineField.
    """
    if not (np.isfinite(lam) and lam <= 0):
        raise SelfshapeError(f"field lambda: must be <= 0 (0 = default smoothing, < 0 = less), got {lam}")
    V = np.ascontiguousarray(V, dtype=float)
    F = np.ascontiguousarray(F, dtype=np.int64)
    curv = principal_curvature(V, F) if curvature is None else curvature
    VN = curv.vertex_normals
    frames = tangent_frames(VN)
    A = connection_laplacian(V, F, n_sym, VN, frames)
    M = lumped_mass(V, F)
    q = curvature_guidance(curv, frames, n_sym)
    qnorm = np.sqrt(np.vdot(q, M * q).real)
    kscale = float(np.sqrt(np.sum(M * (curv.vertex_k1 ** 2 + curv.vertex_k2 ** 2)) / M.sum()))
    if not qnorm > 1e-9 * max(kscale, 1e-300) * np.sqrt(M.sum()):
        psi = _smoothest_psi(A, M)
        return LineField(vertex_to_face(V, F, psi, VN, frames, n_sym), psi, float("nan"), True)
    qhat = q / qnorm
    shift = 1e-10 * float(np.abs(A.diagonal()).mean()) / float(M.mean())  # keeps A PD on flat disks
    psi = factorize(A + sp.diags((shift - lam) * M))(M * qhat)
    t = 1.0 / (1.0 + np.sqrt(np.vdot(psi, M * psi).real))
    return LineField(vertex_to_face(V, F, psi, VN, frames, n_sym), psi, float(t), False)


def smoothest_line_field(V: np.ndarray, F: np.ndarray, n_sym: int = 2) -> LineField:
    """The smoothest unit line field (smallest eigenvector of the connection Laplacian)."""
    V = np.ascontiguousarray(V, dtype=float)
    F = np.ascontiguousarray(F, dtype=np.int64)
    VN = vertex_normals(V, F)
    frames = tangent_frames(VN)
    psi = _smoothest_psi(connection_laplacian(V, F, n_sym, VN, frames), lumped_mass(V, F))
    return LineField(vertex_to_face(V, F, psi, VN, frames, n_sym), psi, float("nan"), True)


def line_field_roughness(V: np.ndarray, F: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Angle (deg, in [0, 90]) between the line directions of the two faces at each interior
    edge, after carrying one into the other's plane by the minimal rotation. (k_interior,)"""
    E, he2e, counts = unique_edges(F)
    # the two faces of each interior edge
    order = np.argsort(he2e, kind="stable")
    first = np.searchsorted(he2e[order], np.arange(len(E)))
    interior = np.flatnonzero(counts == 2)
    fa = order[first[interior]] // 3
    fb = order[first[interior] + 1] // 3
    N = face_normals(V, F)
    t = np.einsum("kab,kb->ka", rotation_between(N[fa], N[fb]), D[fa])
    c = np.abs(np.einsum("ij,ij->i", t, D[fb])) / (np.linalg.norm(t, axis=1) * np.linalg.norm(D[fb], axis=1))
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))
