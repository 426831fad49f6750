"""Rotation-corrected step paths for Newton on vertex positions.

A Newton step d moves every vertex along a straight line. When a region of the sheet
rotates by an angle beta, the straight line stretches it by ~beta^2 / 2 and, with a stiff
printed membrane, the line search has to cut the step long before the bending energy's
minimum: rolling sheets then take hundreds of short steps. This module bends the step
into a curve that is tangent to d at alpha = 0 but rotates each triangle rigidly:

1. per triangle, the infinitesimal rotation omega that best explains the edge increments
   of d (least squares over its three edges: omega x E ~ dE);
2. target edges for step length alpha: R(alpha omega) E + alpha (dE - omega x E), i.e. the
   rotation exact and the remaining (stretch) part linear;
3. vertex positions whose edges best match the targets: one Laplacian solve (factorised
   once per mesh, the global step of as-rigid-as-possible deformation), translated so
   the mean displacement is alpha times that of d.

For a rigid infinitesimal rotation d = omega x x the path is the exact finite rotation.
Positions in mm, rotations in radians.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


def rotate(E: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors E (m, k, 3) by the rotation vectors v (m, 3) (Rodrigues)."""
    th = np.linalg.norm(v, axis=1)
    k = v / np.maximum(th, 1e-300)[:, None]
    c, s = np.cos(th)[:, None, None], np.sin(th)[:, None, None]
    kk = k[:, None, :]
    cross = np.cross(np.broadcast_to(kk, E.shape), E)
    dot = np.einsum("mkj,mj->mk", E, k)[..., None]
    return E * c + cross * s + kk * dot * (1.0 - c)


class RotationPath:
    """Curved step paths x(alpha) for a triangle mesh (triangles (m, 3), n vertices)."""

    def __init__(self, triangles: np.ndarray, n_vertices: int):
        t = np.asarray(triangles, dtype=np.int64)
        self.n = int(n_vertices)
        # the three edges of each triangle, tail -> head
        self.tail = t[:, [0, 1, 2]]
        self.head = t[:, [1, 2, 0]]
        i, j = self.tail.ravel(), self.head.ravel()
        n = self.n
        w = np.ones(len(i))
        L = sp.coo_matrix((np.concatenate([w, w, -w, -w]), (np.concatenate([i, j, i, j]), np.concatenate([i, j, j, i]))),
                          shape=(n, n)).tocsc()
        # pin the translation with a weak anchor on vertex 0, then restore the mean
        L = L + sp.coo_matrix(([1.0], ([0], [0])), shape=(n, n)).tocsc()
        self._solve = spla.factorized(L)

    def step(self, x: np.ndarray, d: np.ndarray):
        """(omega, at): per-triangle rotation vectors (m, 3) that best explain the edge
        increments of d, and at(alpha) -> positions (n, 3) along the corrected path.
        Everything independent of alpha is computed here, once per step."""
        E = x[self.head] - x[self.tail]                     # (m, 3, 3): edge k, xyz
        dE = d[self.head] - d[self.tail]
        A = (np.einsum("mkj,mkj->m", E, E)[:, None, None] * np.eye(3) - np.einsum("mki,mkj->mij", E, E))
        omega = np.linalg.solve(A, np.cross(E, dE).sum(axis=1)[..., None])[..., 0]
        stretch = dE - np.cross(np.broadcast_to(omega[:, None, :], E.shape), E)
        tv, hv = self.tail.ravel(), self.head.ravel()
        mean = x.mean(axis=0), d.mean(axis=0)

        def at(alpha: float) -> np.ndarray:
            target = (rotate(E, alpha * omega) + alpha * stretch).reshape(-1, 3)
            # normal equations of sum |y_head - y_tail - target|^2 (+ anchor on vertex 0)
            y0 = x[0] + alpha * d[0]
            y = np.empty_like(x)
            for c in range(3):
                b = (np.bincount(hv, weights=target[:, c], minlength=self.n)
                     - np.bincount(tv, weights=target[:, c], minlength=self.n))
                b[0] += y0[c]
                y[:, c] = self._solve(b)
            y += (mean[0] + alpha * mean[1]) - y.mean(axis=0)
            return y
        return omega, at

    def path(self, x: np.ndarray, d: np.ndarray, alpha: float) -> np.ndarray:
        """Positions (n, 3) at step length alpha along the rotation-corrected path of d."""
        return self.step(x, d)[1](alpha)
