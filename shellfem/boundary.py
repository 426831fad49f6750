"""Supports, rigid-motion gauge and the seeded symmetry-breaking perturbation (mm)."""
from __future__ import annotations

import numpy as np

from shellfem.errors import SelfshapeError


def rigid_modes(x: np.ndarray) -> np.ndarray:
    """(3n, 6) translations and infinitesimal rotations about the centroid of points x (n, 3)."""
    n = len(x)
    c = x - x.mean(0)
    R = np.zeros((n, 3, 6))
    R[:, 0, 0] = R[:, 1, 1] = R[:, 2, 2] = 1.0
    for k, axis in enumerate(np.eye(3)):
        R[:, :, 3 + k] = np.cross(axis, c)
    return R.reshape(3 * n, 6)


def gauge_dofs(x: np.ndarray, fixed_position_dofs: np.ndarray) -> np.ndarray:
    """Position DOFs to hold so that no rigid motion is left free (none if the supports
    already block all six).

    Holding a DOF of an energy invariant under rigid motions is a pure gauge choice only
    if a rigid motion of the free equilibrium can meet the held values, at any deformed
    shape. So: p0 (nearest the centre) holds x, y, z; p1, offset from p0 mostly along x
    at a moderate distance, holds only the components ACROSS that offset (y, z); p2, offset
    mostly along y, holds z. Holding a component along an offset would prescribe a
    distance, which the contracting, rolling sheet does not keep (the constraint then
    carries load). ``gauge_reaction`` checks this after a solve."""
    R = rigid_modes(x)
    n = len(x)
    c = x.mean(0)
    p0 = int(np.argmin(np.linalg.norm(x - c, axis=1)))
    off = x[:, :2] - x[p0, :2]
    dist = np.linalg.norm(off, axis=1)
    size = max(float(dist.max()), 1e-300)
    band = (dist >= 0.05 * size) & (dist <= 0.25 * size)
    if not band.any():
        band = dist > 0
    cand = []
    for axis in (0, 1):
        score = np.where(band, np.abs(off[:, 1 - axis]) / np.maximum(np.abs(off[:, axis]), 1e-300), np.inf)
        cand.append(int(np.argmin(score)))
    p1, p2 = cand
    candidates = [3 * p0, 3 * p0 + 1, 3 * p0 + 2, 3 * p1 + 1, 3 * p1 + 2, 3 * p2 + 2, 3 * p2 + 0]
    chosen = list(np.asarray(fixed_position_dofs, dtype=np.int64))
    rank = np.linalg.matrix_rank(R[chosen]) if chosen else 0
    gauge = []
    for dof in candidates:
        if rank == 6:
            break
        if dof in chosen:
            continue
        r = np.linalg.matrix_rank(R[chosen + [dof]])
        if r > rank:
            chosen.append(dof)
            gauge.append(dof)
            rank = r
    if rank < 6:  # degenerate configuration: fall back to any DOFs that raise the rank
        for dof in range(3 * n):
            if rank == 6:
                break
            if dof not in chosen and np.linalg.matrix_rank(R[chosen + [dof]]) > rank:
                chosen.append(dof)
                gauge.append(dof)
                rank += 1
    return np.array(gauge, dtype=np.int64)


def gauge_reaction(model, q: np.ndarray, gauge: np.ndarray) -> float:
    """Energy (N mm) that releasing the gauge DOFs would still free, sum r_i^2 / (2 k_ii)
    over their reactions r and Hessian diagonal k: ~0 when the gauge is pure (the returned
    shape is the free equilibrium), > 0 when a held DOF carries load."""
    if len(gauge) == 0:
        return 0.0
    E, g, (Hf, Hh) = model.hessian_blocks(q)
    diag = np.zeros(model.n_dofs)
    for blocks, dofs in ((Hf, model.face_dofs), (Hh, model.hinge_dofs)):
        diag += np.bincount(dofs.ravel(), weights=np.diagonal(blocks, axis1=1, axis2=2).ravel(), minlength=model.n_dofs)
    r = g[gauge]
    return float(np.sum(r * r / (2 * np.maximum(np.abs(diag[gauge]), 1e-300))))


def nearest_vertices(points2d: np.ndarray, query: np.ndarray, tol: float, label: str = "support") -> np.ndarray:
    """Indices of the mesh vertices nearest to each query point (printed mm); error if a
    query point is farther than ``tol`` from every vertex (it misses the sheet)."""
    from scipy.spatial import cKDTree
    q = np.asarray(query, float).reshape(-1, 2)
    if not np.all(np.isfinite(q)):
        raise SelfshapeError(f"{label}: points must be finite numbers")
    dist, idx = cKDTree(points2d).query(q)
    if np.any(dist > tol):
        k = int(np.argmax(dist))
        raise SelfshapeError(f"{label}: point {k} at ({q[k, 0]:g}, {q[k, 1]:g}) is {dist[k]:.3g} mm from the "
                             f"nearest sheet vertex (more than {tol:.3g} mm): it does not hit the sheet")
    return idx


def smooth_perturbation(points2d: np.ndarray, seed: int, amplitude: float, n_modes: int = 6) -> np.ndarray:
    """A smooth random out-of-plane field z(x, y) (mm), reproducible from ``seed``, with
    wavelengths between 1/2 and 2 sheet sizes: breaks the symmetry of the flat state."""
    rng = np.random.default_rng(seed)
    lo, hi = points2d.min(0), points2d.max(0)
    L = max(float(np.max(hi - lo)), 1e-9)
    k = rng.normal(size=(n_modes, 2))
    k *= (2 * np.pi / L * rng.uniform(0.5, 2.0, n_modes) / np.linalg.norm(k, axis=1))[:, None]
    ph = rng.uniform(0, 2 * np.pi, n_modes)
    c = rng.normal(size=n_modes)
    z = np.sin((points2d - lo) @ k.T + ph) @ c
    z -= z.mean()
    return amplitude * z / max(float(np.abs(z).max()), 1e-300)


def lifted_perturbation(points2d: np.ndarray, triangles: np.ndarray, edges: np.ndarray, held: np.ndarray,
                        seed: int, amplitude: float, lift: float) -> np.ndarray:
    """The symmetry-breaking start of a sheet above a ground plane: a smooth field z (n,) (mm),
    0 at the ``held`` vertices (whose z a support holds on the plane) and > 0 at every other.

    Why not the plain perturbation lifted above the plane with the held vertices snapped down to
    it: that puts a step of the lift at every support, a kink the plastic pays for (the gallery
    dome held on its rim: 4.2e5 N mm at the start against 261 for the plain perturbation, and its
    solve stalled near 1e4 N mm, a folded state). Here a bubble w solves the graph-Laplacian
    problem L w = A (A the vertices' lumped printed areas, so that w follows the Poisson problem
    -Laplace w = const whatever the grading of the mesh) on the free vertices with w = 0 on the
    held ones: w > 0 on every free vertex of a component with a held vertex (L restricted to the
    free vertices is an M-matrix), smooth, rising from the supports at a finite slope. The
    result is ``amplitude`` w / max w times (1 + p / 2), p the seeded :func:`smooth_perturbation`
    scaled to [-1, 1]: a factor in [0.5, 1.5] that breaks the symmetry as the plain
    perturbation does. A component with no held vertex gets ``lift`` + its plain perturbation
    minus its minimum (a free sheet above the plane)."""
    import scipy.sparse.csgraph as csg
    import scipy.sparse.linalg as spla
    n = len(points2d)
    held = np.asarray(held, bool)
    p = smooth_perturbation(points2d, seed, 1.0)
    L = graph_laplacian(n, edges)
    P = np.column_stack([points2d, np.zeros(n)])[np.asarray(triangles)]
    area = 0.5 * np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1)
    A = np.bincount(np.asarray(triangles).ravel(), weights=np.repeat(area / 3.0, 3), minlength=n)
    _, label = csg.connected_components(L, directed=False)
    anchored = np.zeros(label.max() + 1, bool)
    anchored[label[held]] = True
    z = np.zeros(n)
    solve = ~held & anchored[label]
    if solve.any():
        w = spla.spsolve(L[solve][:, solve].tocsc(), A[solve] / A[solve].mean())
        z[solve] = amplitude * w / w.max() * (1.0 + 0.5 * p[solve])
    for c in np.unique(label[~anchored[label]]):
        m = label == c
        z[m] = lift + amplitude * (p[m] - p[m].min())
    return z


def graph_laplacian(n_vertices: int, edges: np.ndarray):
    """Uniform-weight graph Laplacian (n, n) CSR of the unique mesh edges (ne, 2)."""
    import scipy.sparse as sp
    e = np.asarray(edges)
    A = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                      shape=(n_vertices, n_vertices)).tocsr()
    return (sp.diags(np.asarray(A.sum(1)).ravel()) - A).tocsr()


def harmonic_extension(L, held: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Extend values (k, d) given at the vertices ``held`` to all vertices by the harmonic
    interpolant of the graph Laplacian L (:func:`graph_laplacian`); returns (n, d). Vertices in
    components with no held vertex get 0. Used to carry a support's motion into the sheet so
    that the first iterate has no inverted triangles (a fixed boundary moved to the relaxed
    fabric is a uniform scaling, which this reproduces exactly)."""
    import scipy.sparse.csgraph as csg
    import scipy.sparse.linalg as spla
    n = L.shape[0]
    values = np.asarray(values, float).reshape(len(held), -1)
    out = np.zeros((n, values.shape[1]))
    out[held] = values
    free = np.ones(n, bool)
    free[held] = False
    _, label = csg.connected_components(L, directed=False)
    anchored = np.zeros(label.max() + 1, bool)
    anchored[label[held]] = True
    solve = free & anchored[label]
    if solve.any():
        rows = L[solve]
        rhs = -(rows[:, ~free] @ out[~free])
        out[solve] = spla.spsolve(rows[:, solve].tocsc(), rhs).reshape(-1, values.shape[1])
    return out
