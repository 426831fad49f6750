"""Exact distances between pairs of triangles in space, vectorised over the pairs (mm).

Used by the contact skip test (shellfem.contact) on the few triangle pairs whose bounding
spheres come within reach: the exact distance proves most of them apart, so the collision
build and the continuous collision detection of the whole sheet are not needed.

The distance of two triangles is 0 where an edge of one crosses the other; otherwise it is
attained between a vertex of one and the other triangle, or between two edges, so it is the
smallest of those 6 + 9 distances.
"""
from __future__ import annotations

import numpy as np


def _dot(u, v):
    return np.einsum("...k,...k->...", u, v)


def points_to_triangles(p, tri):
    """Distances (...,) from points p (..., 3) to triangles tri (..., 3, 3) (mm): the plane's
    distance where the foot point lies inside the triangle (no edge is closer then), else the
    nearest edge's."""
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    e1, e2, r = b - a, c - a, p - a
    g11, g12, g22 = _dot(e1, e1), _dot(e1, e2), _dot(e2, e2)
    r1, r2 = _dot(r, e1), _dot(r, e2)
    det = g11 * g22 - g12 * g12
    ok = det > 1e-14 * g11 * g22
    det = np.where(ok, det, 1.0)
    u, v = (g22 * r1 - g12 * r2) / det, (g11 * r2 - g12 * r1) / det
    inside = ok & (u >= 0) & (v >= 0) & (u + v <= 1)
    foot = a + u[..., None] * e1 + v[..., None] * e2
    d_in = np.linalg.norm(p - foot, axis=-1)
    d_edge = np.minimum(np.minimum(points_to_segments(p, a, b), points_to_segments(p, b, c)),
                        points_to_segments(p, c, a))
    return np.where(inside, d_in, d_edge)


def points_to_segments(p, s0, s1):
    """Distances (...,) from points p to segments s0 s1 (each (..., 3), mm)."""
    e = s1 - s0
    ee = _dot(e, e)
    t = np.clip(_dot(p - s0, e) / np.where(ee > 0, ee, 1.0), 0.0, 1.0)
    return np.linalg.norm(p - s0 - t[..., None] * e, axis=-1)


def segments_to_segments(p0, p1, q0, q1):
    """Distances (...,) between segments p0 p1 and q0 q1 (each (..., 3), mm): the closest points
    of the two lines clamped to the segments (Ericson, Real-Time Collision Detection, 5.1.9),
    with parallel and degenerate segments handled by the clamps."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e, b = _dot(d1, d1), _dot(d2, d2), _dot(d1, d2)
    c, f = _dot(d1, r), _dot(d2, r)
    den = a * e - b * b
    safe_a, safe_e = np.where(a > 0, a, 1.0), np.where(e > 0, e, 1.0)
    s = np.where(den > 1e-14 * a * e, np.clip((b * f - c * e) / np.where(den > 0, den, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + f) / safe_e
    s = np.where(t < 0.0, np.clip(-c / safe_a, 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / safe_a, 0.0, 1.0), s))
    t = np.clip((b * s + f) / safe_e, 0.0, 1.0)
    return np.linalg.norm(p0 + s[..., None] * d1 - q0 - t[..., None] * d2, axis=-1)


def segments_cross_triangles(p0, p1, tri):
    """True (...,) where segment p0 p1 meets triangle tri (..., 3, 3) (Moller-Trumbore)."""
    a = tri[..., 0, :]
    e1, e2, d = tri[..., 1, :] - a, tri[..., 2, :] - a, p1 - p0
    h = np.cross(d, e2)
    det = _dot(e1, h)
    ok = np.abs(det) > 1e-14 * np.linalg.norm(e1, axis=-1) * np.linalg.norm(h, axis=-1)
    inv = 1.0 / np.where(ok, det, 1.0)
    s = p0 - a
    u = inv * _dot(s, h)
    q = np.cross(s, e1)
    v = inv * _dot(d, q)
    t = inv * _dot(e2, q)
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def triangle_pair_distances(A, B):
    """Exact distances (k,) between triangles A[i] and B[i] ((k, 3, 3) corner positions, mm)."""
    A, B = np.asarray(A, float), np.asarray(B, float)
    nxt = [1, 2, 0]
    d = np.minimum(points_to_triangles(A, B[:, None]).min(1), points_to_triangles(B, A[:, None]).min(1))
    ea0, ea1 = A[:, :, None, :], A[:, nxt][:, :, None, :]          # (k, 3, 1, 3): edges of A
    eb0, eb1 = B[:, None, :, :], B[:, nxt][:, None, :, :]          # (k, 1, 3, 3): edges of B
    d = np.minimum(d, segments_to_segments(ea0, ea1, eb0, eb1).reshape(len(A), 9).min(1))
    cross = (segments_cross_triangles(A, A[:, nxt], B[:, None]).any(1)
             | segments_cross_triangles(B, B[:, nxt], A[:, None]).any(1))
    return np.where(cross, 0.0, d)
