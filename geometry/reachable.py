"""The surface nearest a target that the fabric's stretch bounds allow (mm).

A target whose bounded flattening (geometry.flattening) leaves the stretch bounds on part of its
area cannot be deployed exactly: the fabric cannot contract to the target's metric there, whatever
the plastic does. How near can it get? This finds a surface S on the target's mesh, near the target
T, with a flat (printed) mesh U such that on every face the stretch from S to U along the ribbon
direction and across it lies inside the bounds, by alternating two steps:

- U step: the bounded flattening of S, warm-started from the last U (the design's own solver);
- S step: S deformed towards the flat faces unstretched by bounded stretches (a local/global
  solve: per face the nearest rotation and admissible stretches, then one sparse linear system
  over S with the cotangent Laplacian of U), pulled towards T by an area-weighted data term
  ``|S - T|^2 / length^2``.

The pull is weakened (``length`` grows) until the faces out of bounds are fewer than a tolerance;
the distances between that S and T, both ways, say how near the bounds allow the sheet to come.
A design that deploys about that far is limited by its stretch bounds; one that deploys much
farther is limited by something else (the curvature law, the state it releases to). The S found
is a local optimum: a nearer admissible surface may exist, so the figure is how near the bounds
let the sheet come at least, along these ribbon directions.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from geometry.flattening import (_check_bounds, flatten, jacobians, local_triangles, principal_stretches,
                                 project_stretches)
from geometry.meshops import face_areas, face_normals, factorize, lumped_mass
from shellfem.errors import SelfshapeError


#: the U step's stop (mean change of the stretches per iteration): the design's 1e-6 stops a warm
#: start after a few iterations, and the alternation then crawls (a hemisphere at s 1.2: 15 % of the
#: faces still out of bounds after 30 rounds, against 1 % after 12 at 1e-8)
FLATTEN_TOL = 1e-8


@dataclass
class ReachableResult:
    """S (n, 3) mm: the surface found; uv (n, 2) mm: its bounded flattening; length_mm: the pull's
    length at the end (the data term's weight is 1 / length^2); excess (m,): per face the larger
    distance of its two stretches from the bounds (0 inside); out_of_bounds_pct: % of the faces
    whose excess is above the tolerance; distance_mm: (mean, max) of S -> T and (mean, max) of
    T -> S closest-point distances; history: per pull length a dict (length_mm, iterations,
    out_of_bounds_pct, distance_mm)."""
    S: np.ndarray
    uv: np.ndarray
    length_mm: float
    excess: np.ndarray
    out_of_bounds_pct: float
    distance_mm: tuple
    history: list = field(default_factory=list)


def stretch_excess(S, F, uv, dir1, bounds) -> np.ndarray:
    """Per face (m,) the larger of |sigma1 - nearest admissible sigma1| and the same for sigma2,
    for the map from the surface S (n, 3) to the flat mesh uv (n, 2), with sigma1 along the
    tangent direction dir1 (m, 3) (projected into each face of S); 0 inside the bounds."""
    S = np.asarray(S, float)
    F = np.asarray(F, np.int64)
    Uf, Wf, Dinv, _ = local_triangles(S, F)
    d = _tangent(S, F, dir1)
    k1 = np.column_stack([np.einsum("ij,ij->i", d, Uf), np.einsum("ij,ij->i", d, Wf)])
    k1 /= np.linalg.norm(k1, axis=1)[:, None]
    s1, s2, _ = principal_stretches(jacobians(uv, F, Dinv), k1)
    p1, p2 = project_stretches(s1, s2, _check_bounds(bounds))
    return np.maximum(np.abs(s1 - p1), np.abs(s2 - p2))


def _tangent(S, F, dir1):
    """dir1 (m, 3) projected into the faces of S and normalised (a face turned so far that
    nothing is left keeps its own first edge)."""
    n = face_normals(S, F)
    d = np.asarray(dir1, float)
    d = d - np.einsum("ij,ij->i", d, n)[:, None] * n
    norm = np.linalg.norm(d, axis=1)
    bad = ~(norm > 1e-9)
    if bad.any():
        e = S[F[bad, 1]] - S[F[bad, 0]]
        d[bad], norm[bad] = e, np.linalg.norm(e, axis=1)
    return d / norm[:, None]


def _gradient_operators(uv, F):
    """Sparse (m, n) operators Gx, Gy: the gradient of a piecewise linear function on the flat
    mesh uv, per face, in the flat x and y directions; and the flat face areas (m,)."""
    m, n = len(F), len(uv)
    e1, e2 = uv[F[:, 1]] - uv[F[:, 0]], uv[F[:, 2]] - uv[F[:, 0]]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    if not (np.abs(det) > 0).all():
        raise SelfshapeError(f"reachable surface: flat face {int(np.flatnonzero(~(np.abs(det) > 0))[0])} has no area")
    # grad f = D^-T (f1 - f0, f2 - f0), D = [e1 e2]
    inv = np.stack([np.stack([e2[:, 1], -e1[:, 1]], 1), np.stack([-e2[:, 0], e1[:, 0]], 1)], 1) / det[:, None, None]
    rows = np.repeat(np.arange(m), 3)
    ops = []
    for r in range(2):
        a, b = inv[:, r, 0], inv[:, r, 1]
        ops.append(sp.csr_matrix((np.column_stack([-a - b, a, b]).ravel(), (rows, F.ravel())), shape=(m, n)))
    return ops[0], ops[1], 0.5 * np.abs(det)


def _polar(M):
    """The 3 x 2 matrices with orthonormal columns nearest M (m, 3, 2)."""
    U, _, Vt = np.linalg.svd(M, full_matrices=False)
    return U @ Vt


def _s_step(S, T, F, uv, dflat, bounds, mass, length, iterations, basis):
    """``iterations`` local/global steps of the S step (module doc) on the fixed flat mesh uv with
    the flat ribbon directions dflat (m, 2, unit), S - T in the span of ``basis`` (n, k)."""
    Gx, Gy, area = _gradient_operators(uv, F)
    c, s = dflat[:, 0], dflat[:, 1]
    Gd = sp.diags(c) @ Gx + sp.diags(s) @ Gy           # derivative along the ribbons
    Gp = sp.diags(-s) @ Gx + sp.diags(c) @ Gy          # and across them
    w = 1.0 / length ** 2
    K = (Gd.T @ sp.diags(area) @ Gd + Gp.T @ sp.diags(area) @ Gp + sp.diags(w * mass)).tocsr()
    Kr = basis.T @ (K @ basis)
    KT = K @ T
    for _ in range(iterations):
        a, b = Gd @ S, Gp @ S                          # (m, 3) each: dS along and across
        t1, t2 = 1.0 / np.maximum(np.linalg.norm(a, axis=1), 1e-12), 1.0 / np.maximum(np.linalg.norm(b, axis=1), 1e-12)
        # the admissible stretches (flat length / surface length) nearest the current ones
        sig1, sig2 = project_stretches(t1, t2, bounds)
        c1, c2 = 1.0 / sig1, 1.0 / sig2
        Q = _polar(np.stack([c1[:, None] * a, c2[:, None] * b], axis=2))
        rhs = Gd.T @ (area[:, None] * (c1[:, None] * Q[:, :, 0])) + Gp.T @ (area[:, None] * (c2[:, None] * Q[:, :, 1])) \
            + (w * mass)[:, None] * T
        S = T + basis @ np.linalg.solve(Kr, basis.T @ (rhs - KT))
    return S


def smooth_basis(V, F, smooth_mm: float, max_modes: int = 400):
    """(n, k) the Laplacian eigenfunctions of the mesh (V, F) (free boundary, mass-orthonormal)
    whose wavelength 2 pi / sqrt(eigenvalue) is at least ``smooth_mm`` (mm), at most
    ``max_modes`` of them: the smooth displacements. ARPACK starts from a vector seeded by the
    mesh size, not from its own generator, whose state carries over between calls: two calls in
    one process returned bases equal only to round-off, which a multistable sheet designed for
    the proxy turns into another deployed state."""
    import igl
    from scipy.sparse.linalg import eigsh

    L = -igl.cotmatrix(V, np.asarray(F, np.int64))
    M = sp.diags(lumped_mass(V, F))
    k = int(min(max_modes, len(V) - 2))
    v0 = np.random.default_rng(len(V)).standard_normal(len(V))
    vals, vecs = eigsh(L.tocsc(), k=k, M=M.tocsc(), sigma=-1e-8, which="LM", v0=v0)
    order = np.argsort(vals)
    vals, vecs = vals[order], vecs[:, order]
    keep = vals <= (2.0 * np.pi / smooth_mm) ** 2
    return vecs[:, keep]


def _distances(S, T, F):
    """(mean, max) of S -> T and of T -> S closest-point distances (mm), each vertex to the other mesh."""
    import igl

    F = np.ascontiguousarray(F, dtype=np.int64)
    there = np.sqrt(igl.point_mesh_squared_distance(S, T, F)[0])
    back = np.sqrt(igl.point_mesh_squared_distance(T, S, F)[0])
    return (float(there.mean()), float(there.max()), float(back.mean()), float(back.max()))


def reachable_surface(V, F, dir1, bounds, uv0=None, *, tolerance: float = 0.01, out_of_bounds_pct: float = 1.0,
                      lengths=None, rounds: int = 12, s_iterations: int = 30, flatten_iterations: int = 300,
                      rtol: float = 1e-4, smooth_mm: float = 30.0) -> ReachableResult:
    """A surface near the target (V (n, 3) mm, F (m, 3)) whose faces the fabric can reach with
    stretches inside ``bounds`` (box (s1min, s1max, s2min, s2max) or a polygon of (sigma1, sigma2)
    pairs, as geometry.flattening.flatten) along the ribbon directions ``dir1`` (m, 3, tangent to
    the target's faces): see the module doc. ``uv0``: the target's bounded flattening to start from
    (default: flattened here). The pull towards the target is weakened through ``lengths`` (mm;
    default 0.1, 0.3, 1, 3 and 10 times the target's bounding-box diagonal) until at most
    ``out_of_bounds_pct`` % of the faces leave the bounds by more than ``tolerance`` (a stretch of
    1 % by default); at each length up to ``rounds`` U and S steps, until S moves less than ``rtol``
    of the diagonal. A target inside its bounds is returned as it is (S = T).

    ``smooth_mm``: S - T is a combination of the target's Laplacian eigenfunctions of wavelength
    at least this (mm; default twice the ribbons' length; smooth_basis). Why: free, the surface
    meets the bounds by crumpling at the mesh's scale (a 45 degree cap at stretches <= 1.03:
    dihedral angles up to 61 degrees against the cap's 3.6), nearer the target than a printed
    sheet, whose 15 mm ribbons do not wrinkle that short; at 15 mm the cap still wrinkles
    (dihedral angles to 27 degrees), at 30 mm it comes within rms 2.75 mm against 2.83 mm for
    the admissible flatter cap of its geodesic radius; at 60 mm the basis cannot meet the bounds
    (8 % of the faces out). A thin-plate penalty on S - T instead resisted the smooth change of
    curvature that the bounds ask (the cap stayed 61 % out)."""
    V = np.ascontiguousarray(V, float)
    F = np.ascontiguousarray(F, np.int64)
    bounds = _check_bounds(bounds)
    dir1 = np.asarray(dir1, float)
    if dir1.shape != F.shape:
        raise SelfshapeError(f"reachable surface: dir1 must have shape {F.shape}, got {dir1.shape}")
    diag = float(np.linalg.norm(V.max(0) - V.min(0)))
    if not diag > 0:
        raise SelfshapeError("reachable surface: the target has no extent")
    lengths = [diag * f for f in (0.1, 0.3, 1.0, 3.0, 10.0)] if lengths is None else list(lengths)
    if uv0 is None:
        uv = flatten(V, F, dir1, bounds, max_iter=flatten_iterations * 4).uv
    else:
        uv = np.array(uv0, float)
        if uv.shape != (len(V), 2):
            raise SelfshapeError(f"reachable surface: uv0 must have shape {(len(V), 2)}, got {uv.shape}")
    mass = lumped_mass(V, F)
    basis = smooth_basis(V, F, smooth_mm)
    S = V.copy()
    excess = stretch_excess(S, F, uv, dir1, bounds)
    history = []
    length = 0.0
    for length in lengths:
        if 100.0 * np.mean(excess > tolerance) <= out_of_bounds_pct:
            break
        it = 0
        for it in range(1, rounds + 1):
            fr = flatten(S, F, _tangent(S, F, dir1), bounds, uv_init=uv, isometric_iterations=0,
                         max_iter=flatten_iterations, tol=FLATTEN_TOL)
            uv = fr.uv
            S_new = _s_step(S, V, F, uv, fr.dir1, bounds, mass, length, s_iterations, basis)
            moved = float(np.abs(S_new - S).max())
            S = S_new
            if moved < rtol * diag:
                break
        # the flat mesh of the final S, for the excess measured on it
        uv = flatten(S, F, _tangent(S, F, dir1), bounds, uv_init=uv, isometric_iterations=0,
                     max_iter=flatten_iterations, tol=FLATTEN_TOL).uv
        excess = stretch_excess(S, F, uv, dir1, bounds)
        history.append({"length_mm": length, "iterations": it,
                        "out_of_bounds_pct": float(100.0 * np.mean(excess > tolerance)),
                        "distance_mm": _distances(S, V, F)})
    if not np.isfinite(S).all():
        raise SelfshapeError("reachable surface: the iteration diverged (non-finite positions)")
    return ReachableResult(S=S, uv=uv, length_mm=float(length), excess=excess,
                           out_of_bounds_pct=float(100.0 * np.mean(excess > tolerance)),
                           distance_mm=history[-1]["distance_mm"] if history else (0.0, 0.0, 0.0, 0.0),
                           history=history)
