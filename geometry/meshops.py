"""Triangle-mesh operations shared by curvature, fields, flattening, stripes, targets and meshing.

One function per geometric operation, arrays in and arrays out, no hidden state (the style
of libigl's Python API): V (n, 3) float vertex positions (mm), F (m, 3) int triangles,
half-edge 3f + c running from F[f, c] to F[f, (c + 1) % 3]. Where two callers need a
different variant of the same operation (vertex-normal weights, tangent-frame seeds,
eigen-solver start and stopping rule), it is a parameter, each caller's choice its default
or its argument.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.linalg import eigh
from scipy.sparse.csgraph import connected_components

from shellfem.errors import SelfshapeError

try:  # CHOLMOD (scikit-sparse) when installed; loaded with this module so that a caller's BLAS
    # thread limit (threadpoolctl) also holds the BLAS it brings
    from sksparse.cholmod import CholmodNotPositiveDefiniteError, cholesky
except ImportError:  # pragma: no cover - optional dependency
    cholesky = None


class NotPositiveDefiniteError(SelfshapeError):
    """The sparse Cholesky factorisation met a non-positive pivot."""


# ----------------------------------------------------------------------------- vectors and frames
def unit(X: np.ndarray) -> np.ndarray:
    """Rows of X scaled to unit length; zero rows stay zero."""
    n = np.linalg.norm(X, axis=-1, keepdims=True)
    return X / np.where(n > 0, n, 1.0)


def face_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Unit face normals (m, 3), right-hand rule on the winding (zero for a degenerate face)."""
    return unit(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]))


def face_areas(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Triangle areas (m,), mm^2."""
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)


def signed_areas(uv: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Signed areas (m,) of planar triangles uv (n, 2), positive when counter-clockwise (mm^2)."""
    a, b = uv[F[:, 1]] - uv[F[:, 0]], uv[F[:, 2]] - uv[F[:, 0]]
    return 0.5 * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])


def vertex_normals(V: np.ndarray, F: np.ndarray, weighting: str = "max", unit_length: bool = True) -> np.ndarray:
    """Vertex normals (n, 3): the sum over the incident faces of the face normal weighted by

    - "max": Max's 1999 weights, corner cross product / (|a|^2 |b|^2) (exact on a sphere);
    - "area": the face area.

    unit_length=False returns the weighted sums themselves (their length tells where the
    faces around a vertex cancel).
    """
    if weighting == "max":
        w = []
        for c in range(3):
            a = V[F[:, (c + 1) % 3]] - V[F[:, c]]
            b = V[F[:, (c + 2) % 3]] - V[F[:, c]]
            w.append(np.cross(a, b) / (np.einsum("ij,ij->i", a, a) * np.einsum("ij,ij->i", b, b))[:, None])
    elif weighting == "area":
        w = [face_normals(V, F) * face_areas(V, F)[:, None]] * 3
    else:
        raise ValueError(f"unknown vertex-normal weighting {weighting!r} (use 'max' or 'area')")
    N = np.zeros_like(V, dtype=float)
    for c in range(3):
        np.add.at(N, F[:, c], w[c])
    return unit(N) if unit_length else N


def face_frames(V: np.ndarray, F: np.ndarray):
    """Orthonormal face frames (U, W, N), each (m, 3): U along edge F[:, 0] -> F[:, 1],
    N the face normal, W = N x U."""
    N = face_normals(V, F)
    U = unit(V[F[:, 1]] - V[F[:, 0]])
    return U, np.cross(N, U), N


def tangent_frames(N: np.ndarray, seed: str = "least_aligned"):
    """Deterministic orthonormal tangent frames (e1, e2 = N x e1) for unit normals N (k, 3).

    e1 is the seed axis projected into the tangent plane: "least_aligned" the coordinate axis
    least aligned with N; "x_or_y" the x axis, or y where |N_x| >= 0.9.
    """
    if seed == "least_aligned":
        axis = np.argmin(np.abs(N), axis=1)
        a = np.zeros_like(N)
        a[np.arange(len(N)), axis] = 1.0
        e1 = unit(a - np.einsum("ij,ij->i", a, N)[:, None] * N)
    elif seed == "x_or_y":
        a = np.zeros_like(N)
        use_x = np.abs(N[:, 0]) < 0.9
        a[use_x, 0] = 1.0
        a[~use_x, 1] = 1.0
        e1 = a - np.sum(a * N, axis=1)[:, None] * N
        e1 /= np.linalg.norm(e1, axis=1)[:, None]
    else:
        raise ValueError(f"unknown tangent-frame seed {seed!r} (use 'least_aligned' or 'x_or_y')")
    return e1, np.cross(N, e1)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimal rotations (k, 3, 3) taking unit vectors a to unit vectors b."""
    v = np.cross(a, b)
    c = np.einsum("ij,ij->i", a, b)
    K = np.zeros((len(a), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    scale = 1.0 / np.maximum(1.0 + c, 1e-12)
    return np.eye(3)[None] + K + np.einsum("kij,kjl->kil", K, K) * scale[:, None, None]


# ----------------------------------------------------------------------------- angles and weights
def triangle_angles(points, triangles) -> np.ndarray:
    """(m, 3) interior angles in degrees (at vertex 0, 1, 2); points (n, 2) or (n, 3)."""
    p = np.asarray(points, float)[np.asarray(triangles)]
    a = np.linalg.norm(p[:, 2] - p[:, 1], axis=1)    # opposite vertex 0
    b = np.linalg.norm(p[:, 0] - p[:, 2], axis=1)
    c = np.linalg.norm(p[:, 1] - p[:, 0], axis=1)

    def ang(opp, s1, s2):
        return np.degrees(np.arccos(np.clip((s1 * s1 + s2 * s2 - opp * opp) / (2 * s1 * s2), -1.0, 1.0)))
    return np.column_stack([ang(a, b, c), ang(b, c, a), ang(c, a, b)])


def corner_cotangents(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """cot of the angle at corner c (m, 3); it weighs the opposite edge (c + 1 -> c + 2)."""
    cots = np.empty(F.shape)
    for c in range(3):
        p = V[F[:, c]]
        e1 = V[F[:, (c + 1) % 3]] - p
        e2 = V[F[:, (c + 2) % 3]] - p
        cots[:, c] = np.einsum("ij,ij->i", e1, e2) / np.linalg.norm(np.cross(e1, e2), axis=1)
    return cots


def cotan_weights(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """cot(opposite angle) / 2 for each half-edge (3m,); summed per edge (np.bincount over
    the half-edge -> edge map) they are the cotangent Laplacian's edge weights."""
    return (0.5 * np.roll(corner_cotangents(V, F), 1, axis=1)).reshape(-1)


def lumped_mass(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Barycentric vertex areas (n,) in mm^2: a third of each incident face."""
    return np.bincount(F.ravel(), weights=np.repeat(face_areas(V, F) / 3.0, 3), minlength=len(V))


# ----------------------------------------------------------------------------- topology
def halfedges(F: np.ndarray) -> np.ndarray:
    """Directed half-edges (3m, 2): row 3f + c is F[f, c] -> F[f, (c+1) % 3]."""
    return np.stack([F, np.roll(F, -1, axis=1)], axis=2).reshape(-1, 2)


def unique_edges(F: np.ndarray, n: int | None = None):
    """Undirected edges of a triangle mesh with n vertices (default max index + 1).

    Returns E (k, 2) vertex pairs a < b in lexicographic order, he2e (3m,) edge of each
    half-edge and the number of faces at each edge (k,).
    """
    H = halfedges(np.asarray(F, dtype=np.int64))
    n = int(F.max()) + 1 if n is None else int(n)
    key = np.minimum(H[:, 0], H[:, 1]) * n + np.maximum(H[:, 0], H[:, 1])
    ukey, he2e, counts = np.unique(key, return_inverse=True, return_counts=True)
    return np.column_stack([ukey // n, ukey % n]), he2e.reshape(-1), counts


def mesh_edges(F: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undirected edges. Returns E (k, 2) with a < b, face_edge (m, 3) id of the edge from corner
    c to corner c + 1, and forward (m, 3) bool (corner c is the edge's first vertex a)."""
    F = np.asarray(F, dtype=np.int64)
    E, he2e, _ = unique_edges(F, n)
    return E, he2e.reshape(F.shape), F == np.minimum(F, np.roll(F, -1, axis=1))


def boundary_loop_count(F: np.ndarray, n: int) -> int:
    """Number of boundary loops (components of the boundary-edge graph)."""
    E, _, counts = unique_edges(F)
    B = E[counts == 1]
    if len(B) == 0:
        return 0
    verts = np.unique(B)
    A = sp.coo_matrix((np.ones(len(B)), (B[:, 0], B[:, 1])), shape=(n, n))
    _, labels = connected_components(A, directed=False)
    return len(np.unique(labels[verts]))


def boundary_loops(V: np.ndarray, F: np.ndarray) -> list[np.ndarray]:
    """The boundary loops of a manifold mesh as vertex index arrays (each in the order its faces
    run along it), the longest (by length in V's units) first: a disk with holes' outer edge,
    then its holes' rims."""
    import igl

    loops = [np.asarray(loop, np.int64) for loop in igl.boundary_loop_all(np.ascontiguousarray(F, dtype=np.int64))]
    length = [float(np.linalg.norm(V[np.roll(loop, -1)] - V[loop], axis=1).sum()) for loop in loops]
    return [loops[i] for i in np.argsort(length, kind="stable")[::-1]]


def remove_unreferenced(V: np.ndarray, F: np.ndarray):
    """Drop vertices no face uses; returns (V, F, old index of each kept vertex)."""
    used = np.unique(F)
    remap = np.full(len(V), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[F], used


# ----------------------------------------------------------------------------- sparse solves
def factorize(A: sp.spmatrix, ordering: str = "default", check_definite: bool = False):
    """Factor a sparse Hermitian positive definite matrix once; returns solve(b).

    CHOLMOD (scikit-sparse) with fill-reducing ``ordering`` ("default": CHOLMOD's choice,
    "amd", ...) when installed, else SuperLU. Raises NotPositiveDefiniteError when CHOLMOD
    finds the matrix is not positive definite. CHOLMOD stops at a non-positive pivot only in
    its supernodal LL^T; on small matrices it picks a simplicial LDL^T that factors indefinite
    matrices too. ``check_definite`` makes the answer the same at every size: it also refuses
    an LDL^T with a non-positive D (and, with SuperLU, factors with diagonal pivots only, so
    that the pivots are D, and refuses a non-positive or zero one).
    """
    A = sp.csc_matrix(A)
    if cholesky is None:  # pragma: no cover - optional dependency
        from scipy.sparse.linalg import splu

        if not check_definite:
            lu = splu(A, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
            return lu.solve
        try:
            lu = splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        except RuntimeError as err:                    # an exactly zero pivot
            raise NotPositiveDefiniteError("matrix is not positive definite") from err
        d = lu.U.diagonal().real
        if not (np.array_equal(lu.perm_r, lu.perm_c) and np.all(d > 0)):
            raise NotPositiveDefiniteError("matrix is not positive definite")
        return lu.solve
    try:
        factor = cholesky(A, ordering_method=ordering)
    except CholmodNotPositiveDefiniteError as err:
        raise NotPositiveDefiniteError("matrix is not positive definite") from err
    if check_definite and not np.all(factor.D().real > 0):   # NaN pivots fail too
        raise NotPositiveDefiniteError("matrix is not positive definite")
    return factor


def smallest_eigenvector(A: sp.spmatrix, mass: np.ndarray, start: np.ndarray, *, rtol: float,
                         max_iter: int, stop: str = "eigenvalue", ordering: str = "default",
                         sigma: float | None = None, solve=None):
    """Smallest eigenpair of A x = lambda M x, M = diag(mass), by inverse power iteration.

    A: sparse Hermitian (n, n), real or complex; mass (n,) > 0.
    sigma None: A is positive semi-definite; one sparse Cholesky factor of A + 1e-8 s M
    (s = mean |A_ii| / mean M_i keeps a singular A factorable without moving its spectrum
    visibly) serves every iteration, and the eigenvalue is reported >= 0. sigma a number
    (units of lambda): A may be indefinite, sigma lies strictly below its smallest
    eigenvalue (see `definite_factor`) and the factor is of A - sigma M (``solve``: that
    factor when the caller has it already, else factorised with a definiteness check).
    start: (n,) one start vector, or (n, k) a start block: with k > 1 each iteration ends
    with a Rayleigh-Ritz step on the block (subspace iteration), which converges at
    (lambda_1 - sigma) / (lambda_(k+1) - sigma) where single-vector iteration crawls at
    (lambda_1 - sigma) / (lambda_2 - sigma) ~ 1 for clustered low modes.
    stop: "eigenvalue" stops when the smallest Ritz value changes by less than
    rtol * |lambda| + 1e-12 s; "vector" when 1 - |<x_old, M x_new>| < rtol (the M-unit vector
    no longer changes up to a global phase).
    Returns (x (n,) M-normalised, lambda, iterations used).
    """
    ritz, X, it = smallest_ritz_pairs(A, mass, start, rtol=rtol, max_iter=max_iter, stop=stop,
                                      ordering=ordering, sigma=sigma, solve=solve)
    x = X[:, 0]
    if X.shape[1] > 1:                                 # the Ritz vector is M-unit up to round-off
        x = x / np.sqrt(np.vdot(x, mass * x).real)
    lam = float(ritz[0])
    return x, (max(lam, 0.0) if sigma is None else lam), it


def smallest_ritz_pairs(A: sp.spmatrix, mass: np.ndarray, start: np.ndarray, *, rtol: float,
                        max_iter: int, stop: str = "eigenvalue", ordering: str = "default",
                        sigma: float | None = None, solve=None, converged=None):
    """The iteration of `smallest_eigenvector` (same arguments), returning the whole block.

    converged: None, or an extra test converged(ritz, X) -> bool called after every
    iteration with that iteration's Ritz values and vectors; the iteration then stops when
    both ``stop``'s rule and this test hold (or at max_iter).

    Returns (ritz (k,) ascending Ritz values, units of lambda; X (n, k) the Ritz vectors,
    M-orthonormal up to round-off; iterations used), k = the start block's width (1 for a
    single start vector: then ritz[0] is the Rayleigh quotient of the M-unit X[:, 0]).
    The values are not clamped at 0 (round-off may make them slightly negative for a
    singular A). Callers that must choose within a cluster of (nearly) equal low eigenvalues
    read the block.
    """
    if stop not in ("eigenvalue", "vector"):
        raise ValueError(f"stop must be 'eigenvalue' or 'vector', got {stop!r}")
    scale = float(np.abs(A.diagonal()).mean()) / float(mass.mean())
    if sigma is None:
        solve = factorize(A + sp.diags(1e-8 * scale * mass), ordering)
        floor = 0.0
    else:
        if solve is None:
            solve = factorize(A + sp.diags(-sigma * mass), ordering, check_definite=True)
        floor = -np.inf
    X = np.asarray(start)
    X = X[:, None] if X.ndim == 1 else X
    if stop == "vector":                               # the first comparison needs an M-unit start
        X = X / np.sqrt(_m_norms2(X, mass))
    block = X.shape[1] > 1
    lam_prev = np.inf
    it = 0
    ritz = np.array([np.nan])
    for it in range(1, max_iter + 1):
        Y = solve(mass[:, None] * X)
        Y /= np.sqrt(_m_norms2(Y, mass))
        if block:
            YH = Y.conj().T if np.iscomplexobj(Y) else Y.T
            try:
                ritz, Q = eigh(YH @ (A @ Y), YH @ (mass[:, None] * Y))   # Rayleigh-Ritz
            except np.linalg.LinAlgError:              # nearly dependent block: re-orthonormalise
                Y = np.linalg.qr(np.sqrt(mass)[:, None] * Y)[0] / np.sqrt(mass)[:, None]
                YH = Y.conj().T if np.iscomplexobj(Y) else Y.T
                ritz, Q = np.linalg.eigh(YH @ (A @ Y))
            Y = Y @ Q
            ritz = np.asarray(ritz, dtype=float)
        else:
            ritz = np.array([float(np.vdot(Y[:, 0], A @ Y[:, 0]).real)])
        lam = max(float(ritz[0]), floor)
        if stop == "eigenvalue":
            done = abs(lam_prev - lam) <= rtol * abs(lam) + 1e-12 * scale
        else:
            done = 1.0 - abs(np.vdot(X[:, 0], mass * Y[:, 0])) < rtol
        if converged is not None:
            done = bool(converged(ritz, Y)) and done
        X = Y
        if done:
            break
        lam_prev = lam
    return ritz, X, it


def definite_factor(A: sp.spmatrix, mass: np.ndarray, sigma: float, margin: float, ordering: str = "default"):
    """A positive definite factor of A - s M (M = diag(mass)) with s as close to ``sigma`` as
    the spectrum allows; returns (solve, s).

    s = sigma when A - sigma M is positive definite (lambda_min(A, M) > sigma), else
    s = lambda_min - ``margin`` (margin > 0, units of lambda): strictly below the smallest
    eigenvalue, so that the smallest eigenvector dominates the solution of (A - s M) x = b
    instead of making the factorisation fail. lambda_min comes from block inverse iteration
    with a factor below the spectrum, found by stepping down from sigma by margin x 10^k
    (at most to the Gershgorin bound min_i (A_ii - sum_j |A_ij|) / M_i, below which A - s M
    is diagonally dominant). If the Rayleigh quotient is not yet accurate to the margin, the
    margin grows x 10 per refused factor. SelfshapeError if A - s M cannot be factored even
    below the Gershgorin bound (non-finite entries).
    """
    A = sp.csc_matrix(A)
    if not (np.all(np.isfinite(A.data)) and np.all(np.isfinite(mass)) and np.all(mass > 0)):
        raise SelfshapeError("sparse solve: the matrix or the mass has non-finite or non-positive entries "
                             "(degenerate faces?)")

    def attempt(s):
        try:
            return factorize(A + sp.diags(-s * mass), ordering, check_definite=True)
        except NotPositiveDefiniteError:
            return None

    solve = attempt(sigma)
    if solve is not None:
        return solve, float(sigma)
    off = np.asarray(abs(A).sum(axis=1)).ravel() - np.abs(A.diagonal())    # sum_j!=i |A_ij|
    gersh = float(np.min((A.diagonal().real - off) / mass))
    step = margin
    while True:                                        # a shift strictly below the spectrum
        lo = sigma - step
        if lo <= gersh:
            lo = gersh - margin - abs(gersh) * 1e-8
        solve_lo = attempt(lo)
        if solve_lo is not None:
            break
        if lo < gersh:
            raise SelfshapeError("sparse solve: no shift makes the matrix positive definite")
        step *= 10.0
    n = A.shape[0]
    ramp = np.arange(n) / max(n - 1, 1)
    start = np.exp(1j * np.pi * np.outer(ramp, np.arange(min(4, n))))   # deterministic start block
    _, lam_min, _ = smallest_eigenvector(A, mass, start, rtol=1e-12, max_iter=100, stop="eigenvalue",
                                         ordering=ordering, sigma=lo, solve=solve_lo)
    m = margin
    while lam_min - m > lo:
        s = min(sigma, lam_min - m)
        solve = attempt(s)
        if solve is not None:
            return solve, float(s)
        m *= 10.0
    return solve_lo, float(lo)


def _m_norms2(X: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """Squared M-norms of the columns of X (k,)."""
    if X.shape[1] == 1:
        return np.array([np.vdot(X[:, 0], mass * X[:, 0]).real])
    if np.iscomplexobj(X):
        return np.einsum("ij,i,ij->j", X.conj(), mass, X).real
    return np.einsum("ij,i,ij->j", X, mass, X)
