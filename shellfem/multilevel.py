"""Nested iteration across meshes: a coarser mesh's equilibrium, interpolated, starts the finer one.

Form-finding from the flat state spends most of its Newton iterations finding the global
shape (which way the sheet rolls, how far), not resolving it; a mesh with ~2.5x fewer
vertices finds the same global shape for a fraction of the cost. The finer mesh then starts
from the coarser equilibrium interpolated at its vertices (both meshes cover the same
printed-state domain and conform to the same printed boundaries) and converges in a few
iterations. Measured on the 85 x 60 mm star benchmark (10,651 vertices; studies/bench_solver.py):
coarse levels of 1,770 and 4,331 vertices took the fine level from 89 to 16 Newton iterations,
to the same equilibrium (same energy to the last digit).

    from shellfem.multilevel import prolongate
    x_fine = prolongate(coarse_sheet.points, coarse_sheet.triangles, x_coarse, fine_sheet.points)
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

COARSENING = 2.0           # element-size factor between candidate levels
MAX_LEVEL_RATIO = 0.8      # a level must have at most this fraction of the next finer level's vertices
MIN_COARSE_VERTICES = 1500  # no level coarser than this (auto)
MAX_CANDIDATES = 8
MIN_FINE_VERTICES = 3000   # "auto": meshes smaller than this are solved alone


def locate_points(points: np.ndarray, triangles: np.ndarray, X: np.ndarray, k: int = 8):
    """(triangle index (p,), barycentric coordinates (p, 3)) of 2D points X (p, 2) in the
    triangle mesh (points (n, 2), triangles (m, 3)).

    Candidates are the triangles with the k nearest centroids, widened to 4k and then 16k for
    points none of them contains; a point outside the mesh (round-off on a curved or
    mismatched boundary) gets the triangle whose coordinates are least negative, clamped to
    the triangle."""
    points, X = np.asarray(points, float), np.asarray(X, float)
    centroids = points[triangles].mean(1)
    tree = cKDTree(centroids)
    m = len(triangles)
    tri = np.zeros(len(X), dtype=np.int64)
    bary = np.zeros((len(X), 3))
    todo = np.arange(len(X))
    for kk in (k, 4 * k, 16 * k):
        kk = min(kk, m)
        _, cand = tree.query(X[todo], k=kk)
        cand = cand.reshape(len(todo), kk)
        A, B, C = (points[triangles[cand, i]] for i in range(3))
        v0, v1, v2 = B - A, C - A, X[todo, None, :] - A
        det = v0[..., 0] * v1[..., 1] - v0[..., 1] * v1[..., 0]
        l1 = (v2[..., 0] * v1[..., 1] - v2[..., 1] * v1[..., 0]) / det
        l2 = (v0[..., 0] * v2[..., 1] - v0[..., 1] * v2[..., 0]) / det
        lam = np.stack([1.0 - l1 - l2, l1, l2], -1)
        score = lam.min(-1)
        best = score.argmax(1)
        rows = np.arange(len(todo))
        tri[todo] = cand[rows, best]
        bary[todo] = lam[rows, best]
        inside = score[rows, best] >= -1e-9
        todo = todo[~inside]
        if len(todo) == 0 or kk == m:
            break
    bary = np.clip(bary, 0.0, None)
    bary /= bary.sum(1, keepdims=True)
    return tri, bary


def prolongate(coarse_points: np.ndarray, coarse_triangles: np.ndarray, values: np.ndarray,
               fine_points: np.ndarray) -> np.ndarray:
    """Piecewise-linear interpolation of per-vertex ``values`` (n_coarse, d) of a coarse mesh
    (printed-state points (n_coarse, 2), mm) at the fine mesh's printed-state points (n_fine, 2)."""
    tri, bary = locate_points(coarse_points, coarse_triangles, fine_points)
    return np.einsum("pk,pkd->pd", bary, np.asarray(values, float)[coarse_triangles[tri]])
