"""Stripe patterns on triangle meshes (Knoppel, Crane, Pinkall, Schroder 2015, "Stripe Patterns
on Surfaces"), for line (sign-free) direction fields.

A stripe pattern is an S^1-valued function psi = exp(i alpha) per vertex whose phase alpha
advances at 2 pi / spacing per mm across a given direction field, so that the level sets of
alpha (the stripes) run *along* the direction and are ``spacing`` mm apart. psi is the
eigenvector of the smallest eigenvalue of a connection-Laplacian-like energy

    E(psi) = sum_edges w_ab |psi~_b - exp(i omega_ab) psi_a|^2,

(w = cotan weights, omega_ab the target phase increment along edge ab, psi~_b = psi_b or its
conjugate when the line field flips sheet across the edge) against the lumped mass matrix. The
energy is real-linear only (conjugation), so it is assembled as a real 2n x 2n matrix of 2x2
blocks and solved by inverse power iteration with a sparse Cholesky factor.

Per-face "texture coordinates" alpha at the three corners (unwrapped inside the face, exact
mod 2 pi at the vertices) make isoline extraction robust; faces where the unwrapping does not
close (the pattern has a zero inside) or where the line field has a half-integer singularity
are marked singular and no isoline is extracted there.

Lengths in mm, phases in radians. Planar meshes (n, 2) are handled as z = 0.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

from geometry.meshops import (NotPositiveDefiniteError, cotan_weights, face_areas, face_normals, lumped_mass,
                              mesh_edges, smallest_ritz_pairs, tangent_frames, vertex_normals)
from shellfem.errors import SelfshapeError

TWO_PI = 2.0 * np.pi


class MeshTooCoarse(SelfshapeError):
    """The mesh's edges are too long for the stripe spacing (an edge spans more than half a
    period): refine and retry."""


@dataclass
class StripeField:
    """Result of :func:`stripe_field` on a mesh with n vertices and m faces.

    psi: (n,) unit complex stripe function (phase = alpha mod 2 pi, in each vertex's own sheet).
    amplitude: (n,) |psi| of the M-normalised eigenvector before normalising (small near zeros).
    alpha: (m, 3) per-corner phase (rad), continuous inside each face.
    sheet: (m, 3) +-1, sign of each corner's vertex field in the face's sheet (alpha in the face
        = sheet * vertex phase mod 2 pi).
    branch: (m,) bool, the line field has a half-integer singularity in the face.
    index: (m,) int, winding number of psi around the face (nonzero: stripe singularity).
    singular: (m,) bool, branch | (index != 0): no isolines there.
    direction: (n, 3) unit isoline direction per vertex (tangent, sign arbitrary).
    frequency: (n,) phase rate 2 pi / spacing (rad/mm).
    eigenvalue: smallest eigenvalue of the energy (1/mm^2); 0 for an exactly realisable field.
    iterations: inverse power iterations used.
    """
    psi: np.ndarray
    amplitude: np.ndarray
    alpha: np.ndarray
    sheet: np.ndarray
    branch: np.ndarray
    index: np.ndarray
    singular: np.ndarray
    direction: np.ndarray
    frequency: np.ndarray
    eigenvalue: float
    iterations: int


@dataclass
class IsolineSet:
    """Isolines as concatenated arrays (p polylines, N points).

    points: (N, dim) positions. offsets: (p + 1,) polyline j is points[offsets[j]:offsets[j+1]].
    closed: (p,) bool, closed loops (last point connects to the first, not repeated).
    edge: (N, 2) mesh vertices (a < b) of the edge each point lies on, t: (N,) position
    along it (point = (1 - t) V[a] + t V[b]). seg_face: (N,) face containing the segment from
    point j to j + 1 (for a closed loop's last point: the closing segment; -1 at open ends).
    """
    points: np.ndarray
    offsets: np.ndarray
    closed: np.ndarray
    edge: np.ndarray
    t: np.ndarray
    seg_face: np.ndarray

    def polylines(self) -> list[np.ndarray]:
        """List of (k, dim) arrays; closed loops repeat their first point at the end."""
        out = []
        for j in range(len(self.closed)):
            p = self.points[self.offsets[j]:self.offsets[j + 1]]
            out.append(np.vstack([p, p[:1]]) if self.closed[j] else p)
        return out


# ----------------------------------------------------------------------------- mesh helpers

def _mesh(V, F) -> tuple[np.ndarray, np.ndarray, int]:
    V = np.asarray(V, dtype=float)
    F = np.asarray(F)
    if V.ndim != 2 or V.shape[1] not in (2, 3) or len(V) < 3:
        raise SelfshapeError(f"stripes: vertices must be an (n, 2) or (n, 3) array, got shape {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0 or not np.issubdtype(F.dtype, np.integer):
        raise SelfshapeError(f"stripes: faces must be an (m, 3) integer array, got shape {F.shape}")
    if not np.isfinite(V).all():
        raise SelfshapeError(f"stripes: vertex {int(np.argwhere(~np.isfinite(V))[0, 0])} is not finite")
    if F.min() < 0 or F.max() >= len(V):
        bad = int(np.argwhere((F < 0) | (F >= len(V)))[0, 0])
        raise SelfshapeError(f"stripes: face {bad} refers to a vertex outside 0..{len(V) - 1}")
    used = np.bincount(F.ravel(), minlength=len(V)) > 0
    if not used.all():
        raise SelfshapeError(f"stripes: vertex {int(np.argmin(used))} is not used by any face")
    dim = V.shape[1]
    if dim == 2:
        V = np.column_stack([V, np.zeros(len(V))])
    return V, F.astype(np.int64), dim


def _face_normals_areas(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals and areas; raises on a zero-area face."""
    areas = face_areas(V, F)
    scale = np.max(np.ptp(V, axis=0)) ** 2
    bad = 2.0 * areas <= 1e-14 * scale
    if bad.any():
        raise SelfshapeError(f"stripes: face {int(np.argmax(bad))} is degenerate (zero area)")
    return face_normals(V, F), areas


def _vertex_normals(V, F, areas) -> np.ndarray:
    """Area-weighted unit vertex normals; raises where the faces around a vertex cancel."""
    n = len(V)
    acc = vertex_normals(V, F, weighting="area", unit_length=False)
    nrm = np.linalg.norm(acc, axis=1)
    scale = np.bincount(F.ravel(), weights=np.repeat(areas, 3), minlength=n)
    bad = nrm <= 1e-9 * scale
    if bad.any():
        raise SelfshapeError(f"stripes: faces around vertex {int(np.argmax(bad))} are inconsistently "
                             "oriented (vertex normal vanishes)")
    return acc / nrm[:, None]


# ----------------------------------------------------------------------------- direction field

def _vertex_line_field(V, F, N, t1, t2, areas, direction, on: str):
    """Per-vertex unit isoline direction X (n, 3) and a per-face sign reference (m, 3) for the
    phase-gradient direction (used only to orient each face's sheet)."""
    n, m = len(V), len(F)
    d = np.asarray(direction, dtype=float)
    if d.ndim != 2 or d.shape[1] not in (2, 3):
        raise SelfshapeError(f"stripes: direction must be an (m, 2|3) or (n, 2|3) array, got {d.shape}")
    if on == "auto":
        if len(d) == m:
            on = "face"
        elif len(d) == n:
            on = "vertex"
        else:
            raise SelfshapeError(f"stripes: direction has {len(d)} rows; expected {m} (faces) or {n} (vertices)")
    if len(d) != (m if on == "face" else n):
        raise SelfshapeError(f"stripes: direction has {len(d)} rows, expected one per {on}")
    if d.shape[1] == 2:
        d = np.column_stack([d, np.zeros(len(d))])
    if not np.isfinite(d).all():
        raise SelfshapeError(f"stripes: direction[{int(np.argwhere(~np.isfinite(d))[0, 0])}] is not finite")
    if on == "face":
        fn, _ = _face_normals_areas(V, F)
        dt = d - np.sum(d * fn, axis=1)[:, None] * fn
        ln = np.linalg.norm(dt, axis=1)
        bad = ln <= 1e-12 * max(1.0, float(np.abs(d).max()))
        if bad.any():
            raise SelfshapeError(f"stripes: direction[{int(np.argmax(bad))}] is zero or normal to its face")
        dt /= ln[:, None]
        z = np.zeros(n, dtype=complex)
        for c in range(3):
            v = F[:, c]
            phi = np.arctan2(np.sum(dt * t2[v], axis=1), np.sum(dt * t1[v], axis=1))
            z += np.bincount(v, weights=areas * np.cos(2 * phi), minlength=n)
            z += 1j * np.bincount(v, weights=areas * np.sin(2 * phi), minlength=n)
        half = 0.5 * np.angle(z)
        X = np.cos(half)[:, None] * t1 + np.sin(half)[:, None] * t2
        ref = np.cross(fn, dt)
    else:
        dt = d - np.sum(d * N, axis=1)[:, None] * N
        ln = np.linalg.norm(dt, axis=1)
        bad = ln <= 1e-12 * max(1.0, float(np.abs(d).max()))
        if bad.any():
            raise SelfshapeError(f"stripes: direction[{int(np.argmax(bad))}] is zero or normal to the surface")
        X = dt / ln[:, None]
        ref = np.cross(N, X)[F].sum(axis=1)
    return X, ref


# ----------------------------------------------------------------------------- energy and solve

def _edge_transport(V, E, G, nu):
    """Sheet sign s (k,) and target phase increment omega (k,) along each edge a -> b, in a's sheet."""
    a, b = E[:, 0], E[:, 1]
    s = np.where(np.sum(G[a] * G[b], axis=1) < 0.0, -1.0, 1.0)
    e = V[b] - V[a]
    omega = 0.5 * (nu[a] * np.sum(G[a] * e, axis=1) + s * nu[b] * np.sum(G[b] * e, axis=1))
    return s, omega


def _energy_matrix(n, E, w, s, omega) -> sp.csr_matrix:
    """Real 2n x 2n matrix of sum_e w |C_s x_b - R(omega) x_a|^2 (2x2 blocks per vertex pair)."""
    a, b = E[:, 0], E[:, 1]
    c, sn = np.cos(omega), np.sin(omega)
    # block B = -w C_s R(omega) at (b, a), its transpose at (a, b)
    blk = -w[:, None, None] * np.stack([np.stack([c, -sn], 1), np.stack([s * sn, s * c], 1)], 1)
    rows = (2 * b)[:, None, None] + np.arange(2)[None, :, None]
    cols = (2 * a)[:, None, None] + np.arange(2)[None, None, :]
    rows = np.broadcast_to(rows, blk.shape)
    cols = np.broadcast_to(cols, blk.shape)
    diag = np.bincount(a, weights=w, minlength=n) + np.bincount(b, weights=w, minlength=n)
    r = np.concatenate([rows.ravel(), cols.ravel(), np.arange(2 * n)])
    q = np.concatenate([cols.ravel(), rows.ravel(), np.arange(2 * n)])
    val = np.concatenate([blk.ravel(), blk.ravel(), np.repeat(diag, 2)])
    return sp.csr_matrix((val, (r, q)), shape=(2 * n, 2 * n))


def _gauge_references(V: np.ndarray, mass: np.ndarray) -> list[np.ndarray]:
    """Fixed reference vectors (2n,) in the x[0::2] + 1j x[1::2] layout of the energy, in the
    order `_gauge_fixed` tries them; they depend only on the vertex positions V (n, 3) mm and
    the mass (2n,).

    Both are real (zero imaginary part): Re psi_a does not change when vertex a's sheet is
    conjugated, so the gauge they fix does not depend on which of the two line-field signs a
    vertex got (that choice flips with round-off where the field is at +-90 degrees to the
    vertex frame). r1 = 1 + sum_j (V_j - c_j) / L (c the M-weighted centroid, L the bounding
    box diagonal): the constant alone projects to ~0 when a domain holds a whole number of
    periods, the centred ramps have the opposite parity and do not. r2 = |V - c|^2 / L^2 (even,
    quadratic): the fallback.
    """
    m = mass[0::2]
    c = (m[:, None] * V).sum(axis=0) / m.sum()
    L = float(np.linalg.norm(np.ptp(V, axis=0)))
    d = (V - c) / L
    out = []
    for r in (1.0 + d.sum(axis=1), np.sum(d * d, axis=1)):
        x = np.zeros(2 * len(V))
        x[0::2] = r
        out.append(x)
    return out


def _gauge_fixed(Q: np.ndarray, mass: np.ndarray, references, rho_min: float = 1e-3) -> np.ndarray:
    """The M-normalised M-orthogonal projection of a fixed reference onto span(Q) (2n,).

    Q (2n, k): a basis of the (nearly) degenerate lowest eigenspace; mass (2n,).
    ``references`` are tried in order; the first whose projection keeps at least ``rho_min``
    of its M-norm is used (a smaller projection makes the phase sensitive to the basis'
    convergence error e: it turns by ~e / rho), else the one that keeps most. For k = 1 this
    is +-Q[:, 0] / |Q[:, 0]|_M. The sign is fixed by <r, M x> > 0, which holds by
    construction (<r, M P r> = |P r|_M^2).
    """
    R = np.linalg.cholesky(Q.T @ (mass[:, None] * Q))       # M-orthonormalise the basis
    Q = np.linalg.solve(R, Q.T).T
    best = None
    for r in references:
        c = Q.T @ (mass * r)
        rho = float(np.linalg.norm(c)) / float(np.sqrt(r @ (mass * r)))
        if best is None or rho > best[0]:
            best = (rho, c)
        if rho >= rho_min:
            break
    x = Q @ best[1]
    return x / np.sqrt(x @ (mass * x))


# A pair's gauge-fixed vector is iterated until it changes by less than this (M-norm of the
# change of the M-unit vector): the eigenvalue test alone leaves it ~1e-7 from its limit on a
# frustrated rectangle (spacing growing along the isolines, contraction 0.16 per iteration),
# enough to turn psi by ~1e-5 rad between start seeds; the round-off floor is ~2e-15.
_PHASE_TOL = 1e-10


def _cluster_size(ritz: np.ndarray, rtol: float, scale: float) -> int:
    """How many of the ascending Ritz values count as the lowest eigenvalue (see
    `_smallest_stripe_mode`); scale: mean A_ii / mean M_i (1/mm^2)."""
    window = 100.0 * (rtol * abs(float(ritz[0])) + 1e-12 * scale)
    return int(np.sum(ritz - ritz[0] <= window))


def _smallest_stripe_mode(A, mass, V, seed, rtol, max_iter, block=6):
    """Smallest eigenpair of A x = lambda M x (M = diag(mass)), x M-normalised, with a
    deterministic global phase. V (n, 3): vertex positions (mm), for the phase's reference.

    Block inverse power iteration (subspace iteration with a Rayleigh-Ritz step) on ``block``
    vectors from a seeded normal random start, one sparse Cholesky factor (AMD ordering).
    Frustrated fields have clustered low modes (e.g. an almost free global phase), where
    single-vector inverse iteration crawls at rate lambda_1 / lambda_2 ~ 1; the block
    converges at lambda_1 / lambda_(block + 1). Stops when the smallest Ritz value changes by
    less than rtol * lambda + atol.

    The energy is invariant under a global phase rotation when the line field is orientable:
    its lowest eigenvalue is then a pair, and the lowest Ritz vector an arbitrary member of
    the pair's span, decided by the start block and round-off (BLAS kernels). The Ritz
    vectors within ``100 (rtol lambda_1 + 1e-12 s)`` of lambda_1 (s = mean A_ii / mean M_i,
    1/mm^2; 1e-12 s is the iteration's absolute stopping tolerance) are taken as one
    eigenspace, and the returned x is the projection of a fixed reference onto it
    (`_gauge_fixed`, `_gauge_references`), iterated until it changes by < _PHASE_TOL. The
    window lies at least 100x above the splitting of exact pairs at rtol = 1e-9 and 100x below
    the closest genuinely distinct eigenvalue met (docs/notes.md, session 19). An isolated
    lambda_1 gives the lowest Ritz vector, its sign fixed.
    """
    start = np.random.default_rng(seed).standard_normal((A.shape[0], min(block, A.shape[0])))
    scale = float(np.abs(A.diagonal()).mean()) / float(mass.mean())
    refs = _gauge_references(V, mass)
    last = {}

    def phase_converged(ritz, X):
        k = _cluster_size(ritz, rtol, scale)
        if k == 1:
            last.clear()
            return True
        x = _gauge_fixed(X[:, :k], mass, refs)
        prev = last.get(k)
        last.clear()
        last[k] = x
        return prev is not None and float(np.sqrt((x - prev) @ (mass * (x - prev)))) <= _PHASE_TOL

    try:
        ritz, X, it = smallest_ritz_pairs(A, mass, start, rtol=rtol, max_iter=max_iter, stop="eigenvalue",
                                          ordering="amd", converged=phase_converged)
    except NotPositiveDefiniteError as err:
        raise SelfshapeError("stripes: energy matrix is not positive definite (mesh with "
                             "degenerate or flipped faces?)") from err
    x = _gauge_fixed(X[:, :_cluster_size(ritz, rtol, scale)], mass, refs)
    return x, max(float(ritz[0]), 0.0), it


# ----------------------------------------------------------------------------- texture coordinates

def _texture_coordinates(V, F, psi, G, nu, s_edge, face_edge, ref):
    """Per-corner unwrapped phase alpha (m, 3), sheet signs (m, 3), branch and index per face."""
    sF = s_edge[face_edge]                       # sign across face edges 0->1, 1->2, 2->0
    branch = sF.prod(axis=1) < 0
    s0 = np.where(np.sum(G[F[:, 0]] * ref, axis=1) < 0.0, -1.0, 1.0)
    sheet = np.column_stack([s0, s0 * sF[:, 0], s0 * sF[:, 2]])
    Y = sheet[:, :, None] * G[F]                 # (m, 3, 3) gradient directions in the face sheet
    P = V[F]
    ps = psi[F]
    ps = np.where(sheet > 0, ps, np.conj(ps))
    alpha = np.empty(F.shape)
    alpha[:, 0] = np.angle(ps[:, 0])
    cur = alpha[:, 0]
    for c in range(3):
        d = (c + 1) % 3
        e = P[:, d] - P[:, c]
        om = 0.5 * (nu[F[:, c]] * np.sum(Y[:, c] * e, axis=1) + nu[F[:, d]] * np.sum(Y[:, d] * e, axis=1))
        nxt = cur + om + np.angle(ps[:, d] * np.conj(ps[:, c]) * np.exp(-1j * om))
        if d:
            alpha[:, d] = nxt
        cur = nxt
    index = np.rint((cur - alpha[:, 0]) / TWO_PI).astype(np.int64)
    return alpha, sheet.astype(np.int8), branch, index


# ----------------------------------------------------------------------------- public API

def stripe_field(V, F, direction, spacing, seed: int = 0, direction_on: str = "auto",
                 rtol: float = 1e-9, max_iter: int = 200) -> StripeField:
    """Stripe pattern whose isolines run along ``direction`` with ``spacing`` mm between them.

    V: (n, 2|3) vertices (mm), F: (m, 3) faces. direction: per-face (m, 2|3) or per-vertex
    (n, 2|3) line field (sign ignored) giving the isoline direction; ``direction_on`` = "face"
    or "vertex" resolves m == n. spacing: scalar or (n,) per-vertex stripe spacing (mm).
    seed: start block of the inverse power iteration; the result does not depend on it beyond
    the iteration's convergence (the global phase is fixed by a reference, see
    `_smallest_stripe_mode`). Iteration stops when the eigenvalue estimate changes by less
    than rtol (relative) in one iteration.
    """
    V3, F, _ = _mesh(V, F)
    n = len(V3)
    if direction_on not in ("auto", "face", "vertex"):
        raise SelfshapeError(f"stripes: direction_on = {direction_on!r}, expected auto, face or vertex")
    spacing = np.broadcast_to(np.asarray(spacing, dtype=float), (n,)) if np.ndim(spacing) == 0 \
        else np.asarray(spacing, dtype=float)
    if spacing.shape != (n,):
        raise SelfshapeError(f"stripes: spacing must be a scalar or one value per vertex ({n}), got {spacing.shape}")
    bad = ~np.isfinite(spacing) | (spacing <= 0.0)
    if bad.any():
        raise SelfshapeError(f"stripes: spacing[{int(np.argmax(bad))}] = {spacing[bad][0]} mm must be finite and > 0")

    fn, areas = _face_normals_areas(V3, F)
    N = _vertex_normals(V3, F, areas)
    t1, t2 = tangent_frames(N, seed="x_or_y")
    X, ref = _vertex_line_field(V3, F, N, t1, t2, areas, direction, direction_on)
    G = np.cross(N, X)                            # phase-gradient direction (across the stripes)
    nu = TWO_PI / spacing

    E, face_edge, _ = mesh_edges(F, n)
    s_edge, omega = _edge_transport(V3, E, G, nu)
    worst = int(np.argmax(np.abs(omega)))
    if abs(omega[worst]) > np.pi:
        a, b = E[worst]
        raise MeshTooCoarse(
            f"stripes: mesh too coarse for the spacing: edge ({a}, {b}) spans {abs(omega[worst]) / TWO_PI:.2f} "
            f"stripe periods (spacing {spacing[a]:.3g} mm); refine to edges below half the spacing")

    branch = s_edge[face_edge].prod(axis=1) < 0
    # cotangent weights, none across the faces where the line field branches
    he_w = np.where(np.repeat(branch, 3), 0.0, cotan_weights(V3, F))
    w = np.maximum(np.bincount(face_edge.ravel(), weights=he_w, minlength=len(E)), 0.0)
    A = _energy_matrix(n, E, w, s_edge, omega)
    x, lam, iters = _smallest_stripe_mode(A, np.repeat(lumped_mass(V3, F), 2), V3, seed, rtol, max_iter)

    z = x[0::2] + 1j * x[1::2]
    amp = np.abs(z)
    psi = np.where(amp > 0, z / np.where(amp > 0, amp, 1.0), 1.0 + 0j)
    alpha, sheet, branch, index = _texture_coordinates(V3, F, psi, G, nu, s_edge, face_edge, ref)
    return StripeField(psi=psi, amplitude=amp, alpha=alpha, sheet=sheet, branch=branch, index=index,
                       singular=branch | (index != 0), direction=X, frequency=nu,
                       eigenvalue=lam, iterations=iters)


def _crossing_key(C: np.ndarray, value: float) -> np.ndarray:
    """Integer label of an edge crossing from its value C in the edge's first-vertex sheet:
    C is value + 2 pi k (even label) or -value + 2 pi k (odd label)."""
    r1 = (C - value) / TWO_PI
    k1 = np.rint(r1)
    k2 = np.rint((C + value) / TWO_PI)
    return np.where(np.abs(r1 - k1) < 1e-6, 2 * k1, 2 * k2 + 1).astype(np.int64)


def isoline_set(V, F, field: StripeField, value: float = 0.0) -> IsolineSet:
    """Isolines alpha = value (mod 2 pi) of a stripe field, chained across faces, skipping
    singular faces. value in [0, 2 pi); 0 and pi are well defined for any line field, other
    values follow each face's sheet (consistent where the input direction is a vector field)."""
    V3, F, dim = _mesh(V, F)
    n, m = len(V3), len(F)
    value = float(value)
    if not np.isfinite(value):
        raise SelfshapeError("isolines: value must be finite")
    value = value % TWO_PI
    al = field.alpha
    if al.shape != F.shape:
        raise SelfshapeError(f"isolines: the stripe field has {len(al)} faces, the mesh {m}")
    lo, hi = al.min(axis=1), al.max(axis=1)
    k_lo = np.floor((lo - value) / TWO_PI).astype(np.int64) + 1
    k_hi = np.floor((hi - value) / TWO_PI).astype(np.int64)
    cnt = np.where(field.singular, 0, np.maximum(k_hi - k_lo + 1, 0))
    face = np.repeat(np.arange(m), cnt)
    empty = IsolineSet(np.zeros((0, dim)), np.zeros(1, np.int64), np.zeros(0, bool),
                       np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0, np.int64))
    if len(face) == 0:
        return empty
    first = np.cumsum(cnt) - cnt
    k = k_lo[face] + np.arange(len(face)) - first[face]
    L = value + TWO_PI * k
    a = al[face]
    above = a >= L[:, None]
    cross = above != np.roll(above, -1, axis=1)        # face edge c: corner c -> c + 1
    rows, slot = np.nonzero(cross)                     # exactly two per row, sorted by row
    slot = slot.reshape(-1, 2)
    seg_face = face
    # crossing points
    fr = np.repeat(face, 2)
    sl = slot.ravel()
    c0, c1 = sl, (sl + 1) % 3
    a0 = al[fr, c0]
    a1 = al[fr, c1]
    Lr = np.repeat(L, 2)
    t = (Lr - a0) / (a1 - a0)
    v0, v1 = F[fr, c0], F[fr, c1]
    fwd = v0 < v1
    ea = np.where(fwd, v0, v1)
    eb = np.where(fwd, v1, v0)
    tc = np.where(fwd, t, 1.0 - t)
    # canonical crossing value in the first edge vertex's own sheet
    ca = np.where(fwd, c0, c1)
    sa = field.sheet[fr, ca].astype(float)
    C = np.angle(field.psi[ea]) + sa * (Lr - al[fr, ca])
    key = _crossing_key(C, value)
    E, face_edge, _ = mesh_edges(F, n)
    eid = face_edge[fr, sl]
    if np.abs(key).max() >= 2 ** 20:
        raise SelfshapeError("isolines: stripe phase out of range (corrupt field?)")
    node_key = eid * (2 ** 21) + (key + 2 ** 20)
    uniq, first_idx, node = np.unique(node_key, return_index=True, return_inverse=True)
    nn = len(uniq)
    pts = (1.0 - tc[first_idx, None]) * V3[ea[first_idx]] + tc[first_idx, None] * V3[eb[first_idx]]
    node_edge = np.column_stack([ea[first_idx], eb[first_idx]])
    node_t = tc[first_idx]
    seg = node.reshape(-1, 2)
    return _chain(seg, seg_face, nn, pts[:, :dim], node_edge, node_t)


def _chain(seg, seg_face, nn, pts, node_edge, node_t) -> IsolineSet:
    """Order the nodes of a graph of max degree 2 into paths and loops."""
    u, w = seg[:, 0], seg[:, 1]
    deg = np.bincount(seg.ravel(), minlength=nn)
    if deg.max() > 2:
        raise SelfshapeError("isolines: an isoline branches (inconsistent stripe field)")
    adj = sp.coo_matrix((np.ones(len(seg)), (u, w)), shape=(nn, nn)).tocsr()
    ncomp, comp = csgraph.connected_components(adj, directed=False)
    # start node per component: its smallest degree-1 node, else (a loop) its smallest node
    big = np.iinfo(np.int64).max
    ids = np.arange(nn)
    start_open = np.full(ncomp, big)
    np.minimum.at(start_open, comp[deg == 1], ids[deg == 1])
    closed = start_open == big
    start_any = np.full(ncomp, big)
    np.minimum.at(start_any, comp, ids)
    start = np.where(closed, start_any, start_open)
    # loops: drop one segment at the start node so the walk is a path
    is_start_closed = np.zeros(nn, bool)
    is_start_closed[start[closed]] = True
    touches = np.where(is_start_closed[u], u, np.where(is_start_closed[w], w, -1))
    cand = np.nonzero(touches >= 0)[0]
    _, pick = np.unique(touches[cand], return_index=True)
    drop = np.zeros(len(seg), bool)
    drop[cand[pick]] = True
    keep = ~drop
    root = nn
    r = np.concatenate([u[keep], np.full(ncomp, root)])
    c = np.concatenate([w[keep], start])
    G = sp.coo_matrix((np.ones(len(r)), (r, c)), shape=(nn + 1, nn + 1)).tocsr()
    order = csgraph.depth_first_order(G, root, directed=False, return_predecessors=False)[1:]
    lab = comp[order]
    brk = np.nonzero(np.diff(lab))[0] + 1
    offsets = np.concatenate([[0], brk, [len(order)]]).astype(np.int64)
    pcomp = lab[offsets[:-1]]
    # face of each consecutive segment (including the closing one of loops)
    nxt = np.roll(order, -1)
    last = offsets[1:] - 1
    nxt[last] = order[offsets[:-1]]
    sk = np.minimum(u, w) * nn + np.maximum(u, w)
    srt = np.argsort(sk)
    qk = np.minimum(order, nxt) * nn + np.maximum(order, nxt)
    pos = np.clip(np.searchsorted(sk[srt], qk), 0, len(sk) - 1)
    found = sk[srt][pos] == qk
    sface = np.where(found, seg_face[srt][pos], -1)
    sface[last[~closed[pcomp]]] = -1
    return IsolineSet(points=pts[order], offsets=offsets, closed=closed[pcomp],
                      edge=node_edge[order], t=node_t[order], seg_face=sface.astype(np.int64))


def isolines(V, F, field: StripeField, value: float = 0.0) -> list[np.ndarray]:
    """Isolines alpha = value of ``field`` as a list of (k, dim) polylines (mm), chained across
    faces and stopping at singular faces and the boundary; loops repeat their first point."""
    return isoline_set(V, F, field, value).polylines()
