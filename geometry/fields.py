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

Definiteness (every target of the class). The system is positive definite only for
lambda < lambda_min(A, M). On a doubly curved target lambda_min > 0 (the holonomy forbids a
parallel field) and the seed's lambda = 0 is solved as it is, as lambda - 1e-10 s
(s = mean A_ii / mean M, 1/mm^2). On a developable target (cylinder, cone, and targets that
are so in part) a parallel line field exists and lambda_min = 0; a mesh whose boundary
triangles are obtuse has negative cotangent weights there, which with the holonomy of the
discrete transport make A indefinite (lambda_min < 0, measured -1e-4 to -1e-8 1/mm^2 on
cylinder vaults), so lambda = 0 lies above the spectrum: the factorisation failed (large
meshes, CHOLMOD's LL^T) or the LDL^T of small meshes solved the indefinite system and turned
the field by 90 degrees. Then (and only then: a positive definite system is solved as before)
the negative weights are set to 0, which makes A positive semi-definite by construction
(``LineField.clamped``), and lambda is lowered to just below lambda_min where it is not below
it already (`geometry.meshops.definite_factor`; ``LineField.sigma`` is the value solved
with): the limit lambda -> lambda_min of the method, the smoothest field with its phase set
by the guidance, on a cylinder the circumferential direction everywhere.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from geometry.curvature import Curvature, principal_curvature
from geometry.meshops import (NotPositiveDefiniteError, cotan_weights, definite_factor, face_areas, face_frames,
                              face_normals, factorize, lumped_mass, rotation_between, smallest_eigenvector,
                              tangent_frames, unique_edges, vertex_normals)
from shellfem.errors import SelfshapeError


# ----------------------------------------------------------------------------- operators
def transport_angles(E: np.ndarray, VN: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """Angle rho_ij (k,) by which a tangent vector at E[:,0] turns, in the frames, when carried
    to E[:,1] by the minimal rotation between the two tangent planes."""
    i, j = E[:, 0], E[:, 1]
    t = np.einsum("kab,kb->ka", rotation_between(VN[i], VN[j]), e1[i])
    return np.arctan2(np.einsum("ij,ij->i", t, e2[j]), np.einsum("ij,ij->i", t, e1[j]))


def connection_laplacian(V: np.ndarray, F: np.ndarray, n_sym: int = 2, VN=None, frames=None,
                         clamp_negative: bool = False):
    """Hermitian connection Laplacian A (n, n) for n_sym-direction fields (cotangent weights).

    clamp_negative: set negative edge weights (obtuse opposite angles) to 0, which makes A
    positive semi-definite whatever the transport (a sum of w_ij |psi_j - r_ij psi_i|^2 >= 0)."""
    if VN is None:
        VN = vertex_normals(V, F)
    e1, e2 = tangent_frames(VN) if frames is None else frames
    E, he2e, _ = unique_edges(F)
    w = np.bincount(he2e, weights=cotan_weights(V, F), minlength=len(E))
    if clamp_negative:
        w = np.maximum(w, 0.0)
    r = np.exp(1j * n_sym * transport_angles(E, VN, e1, e2))
    i, j = E[:, 0], E[:, 1]
    nv = len(V)
    diag = np.bincount(i, weights=w, minlength=nv) + np.bincount(j, weights=w, minlength=nv)
    rows = np.concatenate([np.arange(nv), j, i])
    cols = np.concatenate([np.arange(nv), i, j])
    vals = np.concatenate([diag.astype(complex), -w * r, -w * np.conj(r)])
    return sp.csc_matrix((vals, (rows, cols)), shape=(nv, nv))


def _field_mesh(V, F):
    """V (n, 3) float and F (m, 3) int64 arrays for the field solves; SelfshapeError (one line)
    where the operators would be undefined: non-finite coordinates, indices outside 0..n-1,
    zero-area faces (infinite cotangent weights), vertices in no face (zero mass)."""
    V = np.ascontiguousarray(V, dtype=float)
    F = np.ascontiguousarray(F, dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise SelfshapeError(f"field: need vertices (n, 3) and triangles (m, 3), got {V.shape} and {F.shape}")
    if not np.isfinite(V).all():
        raise SelfshapeError(f"field: vertex {int(np.flatnonzero(~np.isfinite(V).all(axis=1))[0])} "
                             f"has a non-finite coordinate")
    if F.min() < 0 or F.max() >= len(V):
        raise SelfshapeError(f"field: a face references a vertex index outside 0..{len(V) - 1}")
    area = face_areas(V, F)
    if not (area > 0).all():
        raise SelfshapeError(f"field: face {int(np.flatnonzero(~(area > 0))[0])} has zero area, "
                             f"{int(np.sum(~(area > 0)))} such faces")
    used = np.zeros(len(V), dtype=bool)
    used[F.ravel()] = True
    if not used.all():
        raise SelfshapeError(f"field: vertex {int(np.flatnonzero(~used)[0])} belongs to no face")
    return V, F


# ----------------------------------------------------------------------------- fields
@dataclass
class LineField:
    """A line field: per-face unit tangent vectors (m, 3) and the vertex solution."""
    face_dirs: np.ndarray      # (m, 3) unit, sign arbitrary (a line field)
    vertex_psi: np.ndarray     # (n,) complex, psi = |psi| exp(2 i phi) in the vertex frames
    t: float                   # the paper's alignment parameter t = 1/(1+||psi||_M) (nan if smoothest)
    smoothest: bool            # True when the guidance was zero and the smoothest field was used
    sigma: float = float("nan")  # 1/mm^2, the factor's A - sigma M: lam - 1e-10 s (smoothest: -1e-8 s),
    #                              or just below lambda_min(A, M) when that is lower (module doc)
    clamped: bool = False      # True when A - sigma M was indefinite and A's negative weights were set to 0


def curvature_guidance(curv: Curvature, frames, n_sym: int = 2) -> np.ndarray:
    """q_v = (|k1| - |k2|) exp(i n phi1) at vertices, phi1 the angle of d1 in the vertex frame."""
    e1, e2 = frames
    phi = np.arctan2(np.einsum("ij,ij->i", curv.vertex_d1, e2), np.einsum("ij,ij->i", curv.vertex_d1, e1))
    mag = np.abs(curv.vertex_k1) - np.abs(curv.vertex_k2)
    return mag * np.exp(1j * n_sym * phi)


def _definite_system(V, F, n_sym, VN, frames, A, M, sigma, margin):
    """A positive definite factor of A - s M for the alignment and smoothest-field solves.

    A as built and s = sigma when A - sigma M is positive definite; otherwise A with its
    negative weights set to 0 and s = min(sigma, lambda_min - margin) (see the module doc).
    Returns (solve, s, the A factorised, clamped)."""
    try:
        return factorize(A + sp.diags(-sigma * M), check_definite=True), float(sigma), A, False
    except NotPositiveDefiniteError:
        pass
    A_clamped = connection_laplacian(V, F, n_sym, VN, frames, clamp_negative=True)
    solve, s = definite_factor(A_clamped, M, sigma, margin)
    return solve, s, A_clamped, bool((A_clamped != A).nnz)


def _smoothest_field(V, F, n_sym, VN, frames, A, M) -> LineField:
    """The smoothest field: smallest generalised eigenvector of (A, diag(M)) by single-vector
    inverse iteration (a factor of A + 1e-8 s M, s = mean A_ii / mean M, or the fallback of
    `_definite_system`) from the deterministic all-ones start, up to 200 iterations, until
    the vector changes by less than 1e-10 up to a global phase."""
    scale = float(np.abs(A.diagonal()).mean()) / float(M.mean())
    solve, sigma, A, clamped = _definite_system(V, F, n_sym, VN, frames, A, M, -(1e-8 * scale), 1e-8 * scale)
    psi = smallest_eigenvector(A, M, np.ones(A.shape[0], dtype=complex), rtol=1e-10, max_iter=200,
                               stop="vector", sigma=sigma, solve=solve)[0]
    return LineField(vertex_to_face(V, F, psi, VN, frames, n_sym), psi, float("nan"), True, sigma, clamped)


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
    try:
        ok = bool(np.isfinite(float(lam)) and float(lam) <= 0)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise SelfshapeError(f"field lambda: must be <= 0 (0 = default smoothing, < 0 = less), got {lam!r}")
    lam = float(lam)
    V, F = _field_mesh(V, F)
    curv = principal_curvature(V, F) if curvature is None else curvature
    VN = curv.vertex_normals
    frames = tangent_frames(VN)
    A = connection_laplacian(V, F, n_sym, VN, frames)
    M = lumped_mass(V, F)
    q = curvature_guidance(curv, frames, n_sym)
    qnorm = np.sqrt(np.vdot(q, M * q).real)
    kscale = float(np.sqrt(np.sum(M * (curv.vertex_k1 ** 2 + curv.vertex_k2 ** 2)) / M.sum()))
    if not qnorm > 1e-9 * max(kscale, 1e-300) * np.sqrt(M.sum()):
        return _smoothest_field(V, F, n_sym, VN, frames, A, M)
    qhat = q / qnorm
    shift = 1e-10 * float(np.abs(A.diagonal()).mean()) / float(M.mean())  # keeps A PD on flat disks
    solve, sigma, _, clamped = _definite_system(V, F, n_sym, VN, frames, A, M, lam - shift, shift)
    psi = solve(M * qhat)
    t = 1.0 / (1.0 + np.sqrt(np.vdot(psi, M * psi).real))
    return LineField(vertex_to_face(V, F, psi, VN, frames, n_sym), psi, float(t), False, sigma, clamped)


def smoothest_line_field(V: np.ndarray, F: np.ndarray, n_sym: int = 2) -> LineField:
    """The smoothest unit line field (smallest eigenvector of the connection Laplacian)."""
    V, F = _field_mesh(V, F)
    VN = vertex_normals(V, F)
    frames = tangent_frames(VN)
    return _smoothest_field(V, F, n_sym, VN, frames, connection_laplacian(V, F, n_sym, VN, frames), lumped_mass(V, F))


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
