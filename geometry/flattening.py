"""Flattening with bounded directional stretch (seed Sec. 5.3.2-5.3.4, Eq. 5.3-5.15).

The flat mesh is the PRINTED (pre-stretched) state: it is the target surface stretched by
sigma1 along the maximum-curvature direction k1 and by sigma2 across it, with
sigma_i in [sigma_i_min, sigma_i_max] (>= 1). Per face e, with X^e the triangle in a local
2D frame (edge 0->1 on the u-axis) and R_theta^e the rotation taking k1 to the u-axis,
the energy is E = sum_e A_e ||J^e - R^e Sigma^e R_theta^e||_F^2 (Eq. 5.3). Local steps:
Sigma by clamping diag(R_theta J^T R) (Eq. 5.7), R by the signed Procrustes solution
(Eq. 5.12, closed form in 2D); global step: the cotangent-Laplacian system (Eq. 5.14),
factored once. All lengths mm.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from geometry.meshops import (boundary_loop_count, cotan_weights, face_areas, face_frames, factorize, halfedges,
                              signed_areas, unique_edges)
from shellfem.errors import SelfshapeError


# ----------------------------------------------------------------------------- bounds
def stretch_bounds(s: float = 1.6, ribbon_length: float = 15.0, ribbon_width: float = 1.5,
                   max_transverse_spacing: float | None = None):
    """Principal stretch bounds (s1min, s1max, s2min, s2max) for fabric pre-stretch ``s``
    and ribbons of length/width (mm) as in seed Sec. 5.3.4.

    s2max: Eq. 5.15 inverted at the largest transverse spacing mu2 (default the ribbon
    length, as the seed): sigma2 = s mu2 / (mu2 + w_r (s - 1)); 1.509 at s = 1.6.
    s1min = 1 (ribbons end to end, no contraction along k1). s1max = s2min = (1 + s) / 2:
    the seed's 1.3 at s = 1.6, i.e. half of the fabric's contraction; for sigma2 it means a
    transverse spacing of w_r (1 + s), a gap of w_r s between neighbouring ribbons.
    """
    for name, val in (("stretch", s), ("ribbon_length", ribbon_length), ("ribbon_width", ribbon_width)):
        if not np.isfinite(val):
            raise SelfshapeError(f"stretch bounds: {name} must be finite, got {val}")
    if s <= 1.0:
        raise SelfshapeError(f"stretch bounds: fabric stretch must be > 1, got {s}")
    if ribbon_length <= 0 or ribbon_width <= 0:
        raise SelfshapeError(f"stretch bounds: ribbon length and width must be > 0, got {ribbon_length}, {ribbon_width}")
    mu2 = ribbon_length if max_transverse_spacing is None else float(max_transverse_spacing)
    s1min, mid = 1.0, 0.5 * (1.0 + s)
    s2max = s * mu2 / (mu2 + ribbon_width * (s - 1.0))
    if not s2max >= mid:
        raise SelfshapeError(f"stretch bounds: max_transverse_spacing {mu2} mm gives sigma2_max {s2max:.4f} "
                             f"below sigma2_min {mid:.4f}; it must be >= {ribbon_width * (1 + s):.4g} mm")
    return s1min, mid, mid, float(s2max)


def polygon_area(P: np.ndarray) -> float:
    """Signed area of the polygon P (k, 2) (shoelace; > 0 counter-clockwise)."""
    e = np.roll(P, -1, axis=0)
    return 0.5 * float(np.sum(P[:, 0] * e[:, 1] - e[:, 0] * P[:, 1]))


def _check_bounds(bounds):
    """A box (s1min, s1max, s2min, s2max) as a tuple, or a simple polygon of (sigma1, sigma2)
    vertices as a (k, 2) array (inverse.contraction: what a pattern's spacings realise)."""
    a = np.asarray(bounds, dtype=float)
    if a.ndim == 2:
        if a.shape[1] != 2 or len(a) < 3 or not np.isfinite(a).all() or a.min() <= 0:
            raise SelfshapeError(f"flatten: polygon bounds must be (k >= 3, 2) positive stretches, got shape {a.shape}")
        if not abs(polygon_area(a)) > 0:
            raise SelfshapeError("flatten: polygon bounds enclose no area")
        return a
    b = tuple(float(x) for x in np.ravel(a))
    if len(b) != 4 or not all(np.isfinite(b)) or min(b) <= 0 or b[0] > b[1] or b[2] > b[3]:
        raise SelfshapeError(f"flatten: bounds must be 0 < s1min <= s1max, 0 < s2min <= s2max, got {bounds}")
    return b


def project_stretches(t1, t2, bounds):
    """Nearest (sigma1, sigma2) to (t1, t2) (arrays) inside the bounds: a box clips each
    stretch; a polygon ((k, 2), geometry.flattening._check_bounds; convex or not) keeps the
    pairs inside it and moves the others to the nearest point of its boundary: the local step's
    minimiser of (s1 - t1)^2 + (s2 - t2)^2 over the admissible set."""
    t1 = np.asarray(t1, dtype=float)
    t2 = np.asarray(t2, dtype=float)
    if not isinstance(bounds, np.ndarray):
        return np.clip(t1, bounds[0], bounds[1]), np.clip(t2, bounds[2], bounds[3])
    P = np.stack([t1, t2], -1).reshape(-1, 2)
    A = bounds
    B = np.roll(A, -1, axis=0)
    # crossing number: edges (A -> B) straddling each point's horizontal line, crossed to its right
    ya, yb = A[None, :, 1], B[None, :, 1]
    py = P[:, None, 1]
    straddle = (ya > py) != (yb > py)
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = A[None, :, 0] + (py - ya) * (B[None, :, 0] - A[None, :, 0]) / (yb - ya)
    inside = (np.count_nonzero(straddle & (xc > P[:, None, 0]), axis=1) % 2) == 1
    out = P.copy()
    outside = ~inside
    if outside.any():
        E = B - A
        r = P[outside][:, None, :] - A[None]
        u = np.clip((r * E[None]).sum(-1) / (E * E).sum(-1)[None], 0.0, 1.0)   # (n', k)
        Q = A[None] + u[..., None] * E[None]
        j = np.argmin(((P[outside][:, None, :] - Q) ** 2).sum(-1), axis=1)
        out[outside] = Q[np.arange(len(j)), j]
    return out[:, 0].reshape(t1.shape), out[:, 1].reshape(t2.shape)


def bounds_box(bounds) -> tuple:
    """The bounding box (s1min, s1max, s2min, s2max) of box or polygon bounds."""
    if isinstance(bounds, np.ndarray):
        return (float(bounds[:, 0].min()), float(bounds[:, 0].max()), float(bounds[:, 1].min()),
                float(bounds[:, 1].max()))
    return tuple(float(b) for b in bounds)


# ----------------------------------------------------------------------------- geometry
def local_triangles(V: np.ndarray, F: np.ndarray):
    """Per-face 2D frames: returns (U, W) (m, 3) in-plane axes (U along edge 0->1) and the
    inverse edge matrices Dinv (m, 2, 2) of [X2 - X1, X3 - X1], and X (m, 3, 2)."""
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    l1 = np.linalg.norm(e1, axis=1)
    U, W, _ = face_frames(V, F)
    a, b = np.einsum("ij,ij->i", e2, U), np.einsum("ij,ij->i", e2, W)
    X = np.zeros((len(F), 3, 2))
    X[:, 1, 0], X[:, 2, 0], X[:, 2, 1] = l1, a, b
    Dinv = np.zeros((len(F), 2, 2))
    Dinv[:, 0, 0], Dinv[:, 0, 1], Dinv[:, 1, 1] = 1.0 / l1, -a / (l1 * b), 1.0 / b
    return U, W, Dinv, X


def jacobians(uv: np.ndarray, F: np.ndarray, Dinv: np.ndarray) -> np.ndarray:
    """Per-face Jacobians (m, 2, 2) of the map from the local triangles to ``uv``."""
    E = np.stack([uv[F[:, 1]] - uv[F[:, 0]], uv[F[:, 2]] - uv[F[:, 0]]], axis=2)
    return E @ Dinv


def tutte_embedding(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Tutte embedding (uniform weights) with the outer boundary (the longest loop) on the unit
    circle, spaced by arc length; counter-clockwise with respect to the face orientation. (n, 2)

    A disk with holes: each hole is first closed by a fan of triangles to a vertex at its rim's
    centroid, the closed disk embedded, and the fans dropped again; the embedding of a disk is
    injective (Tutte), so the holes' rims come out as simple polygons inside the outer one."""
    import igl

    from geometry.meshops import boundary_loops

    F = np.ascontiguousarray(F, dtype=np.int64)
    loops = boundary_loops(V, F)
    n_input = len(V)
    if len(loops) > 1:
        V, F = _holes_closed(V, F, loops[1:])
    bnd = loops[0]
    bc = igl.map_vertices_to_circle(np.asfortranarray(V, dtype=float), bnd.astype(np.int32))
    n = len(V)
    E, _, _ = unique_edges(F)
    A = sp.coo_matrix((np.ones(2 * len(E)), (np.r_[E[:, 0], E[:, 1]], np.r_[E[:, 1], E[:, 0]])), shape=(n, n)).tocsr()
    L = sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A
    free = np.setdiff1d(np.arange(n), bnd)
    uv = np.zeros((n, 2))
    uv[bnd] = bc
    if len(free):
        solve = factorize(L[free][:, free])
        uv[free] = solve(-(L[free][:, bnd] @ bc))
    if signed_areas(uv, F).sum() < 0:
        uv[:, 0] *= -1.0
    return uv[:n_input]


def _holes_closed(V: np.ndarray, F: np.ndarray, holes) -> tuple[np.ndarray, np.ndarray]:
    """(V, F) with each hole rim (a vertex loop) closed by a fan to a new vertex at its centroid,
    the fan's faces oriented as their neighbours (each runs its rim edge the other way)."""
    H = halfedges(F)
    n = len(V)
    key = H[:, 0] * n + H[:, 1]
    boundary = H[~np.isin(key, H[:, 1] * n + H[:, 0])]          # halfedges without a twin
    owner = np.full(n, -1, np.int64)
    for k, loop in enumerate(holes):
        owner[loop] = k
    hole = owner[boundary[:, 0]]
    inner = hole >= 0
    centres = np.array([V[loop].mean(axis=0) for loop in holes])
    fans = np.column_stack([boundary[inner, 1], boundary[inner, 0], n + hole[inner]])
    return np.vstack([V, centres]), np.vstack([F, fans])


def slim_map(V: np.ndarray, F: np.ndarray, uv0: np.ndarray, iterations: int = 3) -> np.ndarray:
    """libigl SLIM (symmetric Dirichlet, no constraints) from an injective start; the start
    is first scaled to the surface area so the result is in the mesh units (mm)."""
    import igl

    area3 = face_areas(V, F).sum()
    area2 = abs(signed_areas(uv0, F).sum())
    uv0 = uv0 * np.sqrt(area3 / area2)
    if iterations <= 0:
        return uv0
    data = igl.slim_precompute(np.asfortranarray(V, dtype=float), np.asfortranarray(F, dtype=np.int32),
                               np.asfortranarray(uv0), igl.SYMMETRIC_DIRICHLET,
                               np.zeros(0, dtype=np.int32), np.zeros((0, 2), order="F"), 0.0)
    return np.ascontiguousarray(igl.slim_solve(data, int(iterations)))


# ----------------------------------------------------------------------------- result
@dataclass
class FlatResult:
    """Flattened (printed, stretched) mesh and its diagnostics (seed Table 5.1 columns).

    uv (n, 2) mm; sigma1/sigma2 (m,): principal stretches of the final Jacobians (sigma1 the
    one whose right singular vector is closest to k1); dir1 (m, 2): unit pushforward of k1;
    energy: Eq. 5.3 (mm^2); residual_energy: energy / target area (the Table 5.1 average);
    k1_deviation_deg: mean angle between the sigma1 right singular vector and k1;
    sigma_bound_violation: [max excess of sigma1, of sigma2] outside the bounds (for polygon
    bounds: the components of the distance to the nearest admissible pair);
    sigma_out_of_bounds_pct: [% faces with sigma1, sigma2 outside the bounds];
    flipped: faces with det J <= 0; times: seconds per stage.
    """
    uv: np.ndarray
    sigma1: np.ndarray
    sigma2: np.ndarray
    dir1: np.ndarray
    energy: float
    residual_energy: float
    iterations: int
    converged: bool
    k1_deviation_deg: float
    sigma_bound_violation: list
    sigma_out_of_bounds_pct: list
    flipped: int
    bounds: object            # box tuple or (k, 2) polygon
    times: dict = field(default_factory=dict)
    history: list = field(default_factory=list)   # (mean |d sigma1|, mean |d sigma2|) per iteration


# ----------------------------------------------------------------------------- solver
def principal_stretches(J: np.ndarray, k1: np.ndarray):
    """Singular values of J (m, 2, 2) assigned to k1 (m, 2 unit, local frame): returns
    sigma1, sigma2 and the angle (deg) between the sigma1 right singular vector and k1."""
    a = J[:, 0, 0] ** 2 + J[:, 1, 0] ** 2
    c = J[:, 0, 1] ** 2 + J[:, 1, 1] ** 2
    b = J[:, 0, 0] * J[:, 0, 1] + J[:, 1, 0] * J[:, 1, 1]
    mean, rad = 0.5 * (a + c), np.hypot(0.5 * (a - c), b)
    smax, smin = np.sqrt(mean + rad), np.sqrt(np.maximum(mean - rad, 0.0))
    alpha = 0.5 * np.arctan2(2 * b, a - c)              # right singular vector of smax
    d = np.abs(np.cos(alpha) * k1[:, 0] + np.sin(alpha) * k1[:, 1])
    first = d >= np.sqrt(0.5)
    sigma1, sigma2 = np.where(first, smax, smin), np.where(first, smin, smax)
    dev = np.degrees(np.arccos(np.clip(np.where(first, d, np.sqrt(np.maximum(1 - d * d, 0))), 0, 1)))
    return sigma1, sigma2, dev


def _local_step(P0, P1, s1, s2, bounds):
    """One local update: rotation R = [[c, -s], [s, c]] by the signed Procrustes solution
    (Eq. 5.12) for the current stretches, then clamped stretches (Eq. 5.7).
    P0 = J k1, P1 = J k2 (m, 2): the Jacobian in the curvature frame."""
    x = s1 * P0[:, 0] + s2 * P1[:, 1]
    y = s1 * P0[:, 1] - s2 * P1[:, 0]
    h = np.hypot(x, y)
    h[h == 0] = 1.0
    c, s = x / h, y / h
    c[h == 0] = 1.0
    s1, s2 = project_stretches(P0[:, 0] * c + P0[:, 1] * s, P1[:, 1] * c - P1[:, 0] * s, bounds)
    return c, s, s1, s2


class _Problem:
    """Precomputed sparse operators of Eq. 5.3 for one mesh and k1 field.

    B (2m, n): stacked maps uv -> J k1 and uv -> J k2 per face. A1, A2 (n, m): the global
    right-hand side of Eq. 5.14 is A1 @ (R Sigma)[:, :, 0] + A2 @ (R Sigma)[:, :, 1]."""

    def __init__(self, V, F, k1, Dinv, X, bounds, local_loops):
        self.bounds, self.local_loops = bounds, local_loops
        n, m = len(V), len(F)
        self.m = m
        self.area = face_areas(V, F)
        K = np.stack([k1, np.column_stack([-k1[:, 1], k1[:, 0]])], axis=2)   # columns k1, k2
        Q = Dinv @ K                        # J K = [e1 e2] Q, e1, e2 the flat edge vectors
        rows = np.repeat(np.arange(m), 3)
        cols = F.reshape(-1)
        blocks = []
        for j in range(2):                  # coefficient of uv[F0], uv[F1], uv[F2] in (J K)[:, j]
            coef = np.column_stack([-(Q[:, 0, j] + Q[:, 1, j]), Q[:, 0, j], Q[:, 1, j]]).reshape(-1)
            blocks.append(sp.csr_matrix((coef, (rows, cols)), shape=(m, n)))
        self.B = sp.vstack(blocks).tocsr()
        Dh = X[:, [0, 1, 2], :] - X[:, [1, 2, 0], :]                      # X_i - X_j per half-edge
        Y = np.einsum("fab,fha->fhb", K, Dh)                               # in the (k1, k2) frame
        w = cotan_weights(V, F)
        he_i, he_j = F.reshape(-1), np.roll(F, -1, axis=1).reshape(-1)
        he = np.arange(3 * m)
        G = sp.csr_matrix((np.r_[np.ones(3 * m), -np.ones(3 * m)], (np.r_[he, he], np.r_[he_i, he_j])),
                          shape=(3 * m, n))
        Kt = (G.T @ sp.diags(w)).tocsr()
        R = sp.csr_matrix((np.ones(3 * m), (he, he // 3)), shape=(3 * m, m))
        self.A1 = (Kt @ sp.diags(Y[..., 0].reshape(-1)) @ R).tocsr()
        self.A2 = (Kt @ sp.diags(Y[..., 1].reshape(-1)) @ R).tocsr()
        L = (Kt @ G).tocsc()
        # vertex n-1 is pinned (translation gauge): the free unknowns are a contiguous slice
        self.solve = factorize(L[: n - 1, : n - 1])
        self.L_fp = np.asarray(L[: n - 1, n - 1].todense()).ravel()

    def local(self, uv, s1, s2):
        P = self.B @ uv
        P0, P1 = P[: self.m], P[self.m:]
        for _ in range(self.local_loops):
            c, s, s1, s2 = _local_step(P0, P1, s1, s2, self.bounds)
        # ||J - R Sigma R_theta||_F = ||J K - R Sigma||_F (K orthogonal)
        r = ((P0[:, 0] - c * s1) ** 2 + (P0[:, 1] - s * s1) ** 2
             + (P1[:, 0] + s * s2) ** 2 + (P1[:, 1] - c * s2) ** 2)
        return (c, s, s1, s2), float(self.area @ r)

    def global_step(self, uv, st):
        c, s, s1, s2 = st
        b = self.A1 @ np.column_stack([c * s1, s * s1]) + self.A2 @ np.column_stack([-s * s2, c * s2])
        out = uv.copy()
        out[:-1] = self.solve(b[:-1] - np.outer(self.L_fp, uv[-1]))
        return out


def _anderson(xs, gs, window):
    """Anderson (type II) extrapolation from the last iterates x_k and G(x_k)."""
    f = [g - x for x, g in zip(xs, gs)]
    dF = np.stack([f[i + 1] - f[i] for i in range(len(f) - 1)], axis=1)
    dG = np.stack([gs[i + 1] - gs[i] for i in range(len(gs) - 1)], axis=1)
    gamma = np.linalg.lstsq(dF, f[-1], rcond=None)[0]
    return gs[-1] - dG @ gamma


def _iterate(prob, uv, st, E, max_iter, tol, anderson, change):
    """Local/global iterations from (uv, local state st, energy E) until
    change(old_state, new_state, old_E, new_E) -> (c1, c2) has both entries below tol."""
    history, xs, gs = [], [], []
    it = 0
    while it < max_iter:
        g = prob.global_step(uv, st)
        it += 1
        new_uv = g
        if anderson > 1:
            xs.append(uv[:-1].ravel())
            gs.append(g[:-1].ravel())
            del xs[:-anderson - 1], gs[:-anderson - 1]
            if len(xs) > 1:
                new_uv = g.copy()
                new_uv[:-1] = _anderson(xs, gs, anderson).reshape(-1, 2)
        new_st, new_E = prob.local(new_uv, st[2], st[3])
        if new_uv is not g and not new_E <= E:
            new_uv = g                                   # reject the extrapolation
            new_st, new_E = prob.local(g, st[2], st[3])
            xs, gs = [], []
        history.append(change(st, new_st, E, new_E))
        uv, st, E = new_uv, new_st, new_E
        if history[-1][0] < tol and history[-1][1] < tol:
            return uv, st, E, it, True, history
    return uv, st, E, it, False, history


def flatten(V: np.ndarray, F: np.ndarray, dir1: np.ndarray, bounds=None, *, max_iter: int = 2000,
            tol: float = 1e-6, slim_iterations: int = 2, isometric_iterations: int = 100,
            uv_init: np.ndarray | None = None, local_loops: int = 2, anderson: int = 5,
            stop: str = "norm") -> FlatResult:
    """Bounded-stretch flattening of a disk-topology target (V mm, F; holes allowed) with per-face k1
    directions ``dir1`` (m, 3). bounds = (s1min, s1max, s2min, s2max), default
    `stretch_bounds()`, or a polygon of admissible (sigma1, sigma2) pairs ((k, 2);
    inverse.contraction: what a pattern's spacings realise), onto which the local step projects.

    Init: Tutte (unit circle) + ``slim_iterations`` of SLIM (or ``uv_init``), then up to
    ``isometric_iterations`` of the same solver with all bounds 1 (ARAP: polishes the start to
    an isometry cheaply, reusing the factorisation). Each iteration: ``local_loops`` local
    updates, one global solve (Eq. 5.14, factored once). Stops when the average change of
    sigma1 and of sigma2 between iterations is below ``tol``; at ``max_iter`` iterations
    returns converged=False. "Average change": with stop="norm" (default) ||d sigma||_2 / m,
    the formula of the seed authors' published local/global solver (shrink-morph), the only
    one consistent with the seed's timings; stop="mean" uses mean |d sigma| (sqrt(m) times
    stricter). ``anderson`` > 1: Anderson acceleration (window ``anderson``) of the global
    iterates, each extrapolation kept only if it lowers Eq. 5.3, else the plain step is
    taken; 0 = the plain seed iteration."""
    times = {}
    V = np.ascontiguousarray(V, dtype=float)
    F = np.ascontiguousarray(F, dtype=np.int64)
    bounds = _check_bounds(stretch_bounds() if bounds is None else bounds)
    dir1 = np.asarray(dir1, dtype=float)
    if dir1.shape != F.shape:
        raise SelfshapeError(f"flatten: dir1 must have shape {F.shape}, got {dir1.shape}")
    if boundary_loop_count(F, len(V)) < 1:
        raise SelfshapeError("flatten: the mesh has no boundary (a disk, possibly with holes, is needed)")
    if stop not in ("norm", "mean"):
        raise SelfshapeError(f"flatten: stop must be 'norm' or 'mean', got {stop!r}")
    U, W, Dinv, X = local_triangles(V, F)
    k1 = np.column_stack([np.einsum("ij,ij->i", dir1, U), np.einsum("ij,ij->i", dir1, W)])
    kn = np.linalg.norm(k1, axis=1)
    if not (kn > 1e-9).all():
        raise SelfshapeError(f"flatten: dir1 of face {int(np.flatnonzero(~(kn > 1e-9))[0])} is not a tangent direction")
    k1 /= kn[:, None]
    m = len(F)

    def avg(d):
        return float(np.linalg.norm(d)) / m if stop == "norm" else float(np.abs(d).mean())

    def sigma_change(st0, st1, E0, E1):
        return avg(st1[2] - st0[2]), avg(st1[3] - st0[3])

    def energy_change(st0, st1, E0, E1):
        # with all bounds 1 sigma never changes: stop on the relative energy decrease
        rel = (E0 - E1) / max(E0, 1e-300)
        return (rel, rel) if E1 > 1e-14 * prob.area.sum() else (0.0, 0.0)

    t0 = time.perf_counter()
    if uv_init is None:
        uv = tutte_embedding(V, F)
        times["tutte"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        uv = slim_map(V, F, uv, slim_iterations)
        times["slim"] = time.perf_counter() - t0
    else:
        uv = np.array(uv_init, dtype=float)
        if uv.shape != (len(V), 2):
            raise SelfshapeError(f"flatten: uv_init must have shape {(len(V), 2)}, got {uv.shape}")
    t0 = time.perf_counter()
    prob = _Problem(V, F, k1, Dinv, X, (1.0, 1.0, 1.0, 1.0), local_loops)
    ones = np.ones(m)
    iso_it = 0
    if isometric_iterations > 0:
        st, E = prob.local(uv, ones, ones)
        uv, st, E, iso_it, _, _ = _iterate(prob, uv, st, E, isometric_iterations, tol, anderson, energy_change)
    times["isometric"] = time.perf_counter() - t0
    times["isometric_iterations"] = iso_it
    t0 = time.perf_counter()
    prob.bounds = bounds
    st, E = prob.local(uv, ones, ones)     # sigma = 1, R from Eq. 5.12
    uv, st, E, it, converged, history = _iterate(prob, uv, st, E, max_iter, tol, anderson, sigma_change)
    times["local_global"] = time.perf_counter() - t0

    c, s, s1, s2 = st
    J = jacobians(uv, F, Dinv)
    sigma1, sigma2, dev = principal_stretches(J, k1)
    d1 = np.einsum("kab,kb->ka", J, k1)
    d1 /= np.linalg.norm(d1, axis=1)[:, None]
    viol, pct = [], []
    for sig, proj in zip((sigma1, sigma2), project_stretches(sigma1, sigma2, bounds)):
        excess = np.abs(sig - proj)        # a box: the excess over the violated bound
        viol.append(float(excess.max()))
        pct.append(float(100.0 * np.mean(excess > 1e-6)))
    detJ = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    return FlatResult(uv=uv, sigma1=sigma1, sigma2=sigma2, dir1=d1, energy=E,
                      residual_energy=E / float(prob.area.sum()), iterations=it, converged=converged,
                      k1_deviation_deg=float(dev.mean()), sigma_bound_violation=viol,
                      sigma_out_of_bounds_pct=pct, flipped=int((detJ <= 0).sum()), bounds=bounds,
                      times=times, history=history)


def flatten_surface(V: np.ndarray, F: np.ndarray, lam: float = 0.0, bounds=None, **kwargs):
    """Curvature -> line field (lambda ``lam``, 1/mm^2) -> bounded flattening, timed.
    Returns (FlatResult, LineField, Curvature); FlatResult.times has every stage."""
    from geometry.curvature import principal_curvature
    from geometry.fields import curvature_line_field

    t0 = time.perf_counter()
    curv = principal_curvature(V, F)
    t1 = time.perf_counter()
    lf = curvature_line_field(V, F, lam, curv)
    t2 = time.perf_counter()
    res = flatten(V, F, lf.face_dirs, bounds, **kwargs)
    res.times = {"curvature": t1 - t0, "field": t2 - t1, **res.times}
    return res, lf, curv
