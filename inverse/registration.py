"""Rigid registration of a deployed surface to its target (scale fixed, mm): Kabsch on known
correspondences, point-to-plane ICP against the closest surface points, and the map from
printed-state points to target positions through the flat mesh."""
from __future__ import annotations

import numpy as np

from geometry.meshops import face_normals


def kabsch(X: np.ndarray, Y: np.ndarray, w=None):
    """Rotation R and translation t minimising sum w |R x + t - y|^2 (proper rotation, scale fixed)."""
    w = np.ones(len(X)) if w is None else np.asarray(w, float)
    w = w / w.sum()
    cx, cy = w @ X, w @ Y
    H = (X - cx).T @ ((Y - cy) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cy - R @ cx


def register(X: np.ndarray, V: np.ndarray, F: np.ndarray, Y0: np.ndarray | None = None, iterations: int = 100,
             tol: float = 1e-9):
    """Rigid registration (scale fixed) of points X (k, 3) to the surface (V, F): Kabsch on the
    correspondences Y0 (if given), then point-to-plane ICP against the closest surface points
    (linearised rotation per step, mapped back to a rotation by Rodrigues). Point-to-plane steps
    can overshoot when the shapes differ a lot, so the pose with the smallest RMS distance seen
    (the Kabsch start included) is returned. Returns (registered X, closest-point distances
    (k,), ICP iterations)."""
    import igl

    F = np.ascontiguousarray(F, dtype=np.int64)
    if Y0 is not None:
        R, t = kabsch(X, Y0)
        X = X @ R.T + t
    N = face_normals(V, F)
    prev = None
    best = (np.inf, X, None)
    it = 0
    for it in range(1, iterations + 1):
        d2, I, C = igl.point_mesh_squared_distance(X, V, F)
        rms = float(np.sqrt(d2.mean()))
        if rms < best[0]:
            best = (rms, X, d2)
        if prev is not None and prev - rms <= tol * prev:
            break
        prev = rms
        n = N[I]
        c = X.mean(axis=0)
        A = np.column_stack([np.cross(X - c, n), n])
        b = -np.einsum("ij,ij->i", X - C, n)
        w, t = np.split(np.linalg.lstsq(A, b, rcond=None)[0], 2)
        ang = float(np.linalg.norm(w))
        K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / max(ang, 1e-300)
        R = np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K
        X = (X - c) @ R.T + c + t
    d2, _, _ = igl.point_mesh_squared_distance(X, V, F)
    if float(np.sqrt(d2.mean())) > best[0]:
        _, X, d2 = best
    return X, np.sqrt(d2), it


def flat_to_target(points2d: np.ndarray, uv: np.ndarray, F: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Target positions (k, 3) of printed-state points (k, 2) through the flat mesh (closest
    flat triangle, barycentric coordinates)."""
    import igl

    P = np.column_stack([points2d, np.zeros(len(points2d))])
    U = np.column_stack([uv, np.zeros(len(uv))])
    F = np.ascontiguousarray(F, dtype=np.int64)
    _, I, C = igl.point_mesh_squared_distance(P, U, F)
    a, b, c = (U[F[I, k]] for k in range(3))
    B = igl.barycentric_coordinates(np.ascontiguousarray(C), np.ascontiguousarray(a), np.ascontiguousarray(b),
                                    np.ascontiguousarray(c))
    return np.einsum("kc,kcd->kd", B, V[F[I]])
