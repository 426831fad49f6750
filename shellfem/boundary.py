"""Supports, rigid-motion gauge and the seeded symmetry-breaking perturbation (mm)."""
from __future__ import annotations

import numpy as np

from selfshape.errors import SelfshapeError


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
    already block all six). Holding a DOF of an energy invariant under rigid motions is
    a pure gauge choice: it does not change the equilibrium shape."""
    R = rigid_modes(x)
    n = len(x)
    c = x.mean(0)
    d = np.linalg.norm(x - c, axis=1)
    p0 = int(np.argmin(d))
    far = x - x[p0]
    dist = np.linalg.norm(far, axis=1)
    p1 = int(np.argmax(dist))                               # farthest from the centre
    u = far[p1] / max(dist[p1], 1e-300)
    off = np.linalg.norm(far - np.outer(far @ u, u), axis=1)  # distance from the axis p0-p1
    p2 = int(np.argmax(off - 1e-3 * np.abs(far @ u)))       # across that axis, near the centre
    k1 = int(np.argmin(np.abs(u)))                          # the component of p1 across the axis
    candidates = [3 * p0, 3 * p0 + 1, 3 * p0 + 2, 3 * p1 + k1, 3 * p1 + 2, 3 * p2 + 2,
                  3 * p1, 3 * p1 + 1, 3 * p2, 3 * p2 + 1]
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
