"""Benchmark: stripe fields + ribbon layout on a ~100k-face planar disk with varying spacing,
direction and curvature sign. Prints one JSON line (times in s, lengths in mm): the time of one
stripe field (theta, the ribbon rows) and of its isolines, the whole layout (two stripe fields,
dashes, clipping, trimming, sides), ribbon counts, and the measured spacing between the
centre-line rows (theta = 0 and pi isolines) over the target mu2 of Eq. 5.15.

    python studies/bench_layout.py [--radius 100] [--faces 100000]
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import shapely
from scipy.spatial import Delaunay

from geometry.stripes import isoline_set, stripe_field
from inverse.layout import ribbon_layout
from inverse.spacing import ribbon_spacing


def disk_mesh(radius: float, n_faces: int):
    """Delaunay disk: hexagonal lattice inside, a ring of points on the circle (mm)."""
    h = np.sqrt(2.0 * np.pi * radius ** 2 / (n_faces * np.sqrt(3) / 2))
    ys = np.arange(-radius, radius + h, h * np.sqrt(3) / 2)
    xs = np.arange(-radius, radius + h, h)
    X = xs[None, :] + 0.5 * h * (np.arange(len(ys)) % 2)[:, None]
    P = np.column_stack([X.ravel(), np.repeat(ys, len(xs))])
    P = P[np.hypot(*P.T) < radius - 0.5 * h]
    a = np.linspace(0, 2 * np.pi, int(np.ceil(2 * np.pi * radius / h)), endpoint=False)
    P = np.vstack([P, radius * np.column_stack([np.cos(a), np.sin(a)])])
    return P, Delaunay(P).simplices, h


def fields(c, radius):
    """Smooth per-face ribbon direction, stretches and signed curvature."""
    x, y = c[:, 0] / radius, c[:, 1] / radius
    ang = 0.35 * np.sin(2.0 * x) + 0.25 * y
    dir1 = np.column_stack([np.cos(ang), np.sin(ang)])
    sigma1 = 1.0 + 0.15 * (1 + x) / 2
    sigma2 = 1.3 + 0.2 * (1 + y) / 2
    kappa1 = 0.02 * np.cos(2.5 * x + 1.0)
    return dir1, sigma1, sigma2, kappa1


def row_spacing(sets, spacing_v, stride=10):
    """Centre-line rows (isoline sets of theta at 0 and pi): at every ``stride``-th point, the
    mean distance to the nearest other row on either side along the row normal, relative to the
    local target mu2 = spacing_v / 2 (1 = exact). Points with a row on both sides only."""
    polys, samples = [], []
    for S in sets:
        for j in range(len(S.closed)):
            sl = slice(S.offsets[j], S.offsets[j + 1])
            polys.append(shapely.LineString(S.points[sl]))
            a, b = S.edge[sl, 0], S.edge[sl, 1]
            mu2 = 0.5 * ((1 - S.t[sl]) * spacing_v[a] + S.t[sl] * spacing_v[b])
            samples.append((len(polys) - 1, S.points[sl], mu2))
    tree = shapely.STRtree(polys)
    rel = []
    for i, p, mu2 in samples:
        for k in range(1, len(p) - 1, stride):
            t = p[k + 1] - p[k - 1]
            t /= np.linalg.norm(t)
            nrm = np.array([-t[1], t[0]])
            sides = []
            for sgn in (1.0, -1.0):
                probe = shapely.LineString([p[k] + 1e-6 * sgn * nrm, p[k] + 2.0 * mu2[k] * sgn * nrm])
                hits = [shapely.distance(shapely.Point(p[k]), shapely.intersection(probe, polys[j]))
                        for j in tree.query(probe, predicate="intersects") if j != i]
                sides.append(min(hits, default=np.inf))
            if np.isfinite(sides).all():
                rel.append(0.5 * (sides[0] + sides[1]) / mu2[k])
    return np.array(rel)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--radius", type=float, default=100.0)
    ap.add_argument("--faces", type=int, default=100_000)
    a = ap.parse_args(argv)
    s = 1.6
    V, F, h = disk_mesh(a.radius, a.faces)
    c = V[F].mean(axis=1)
    dir1, sigma1, sigma2, kappa1 = fields(c, a.radius)

    _, mu2 = ribbon_spacing(sigma1, sigma2, s)
    t0 = time.perf_counter()
    e1, e2 = V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]
    area = np.repeat(0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]), 3)
    spacing_v = np.bincount(F.ravel(), area * np.repeat(2 * mu2, 3)) / np.bincount(F.ravel(), area)
    theta = stripe_field(V, F, dir1, spacing_v, direction_on="face")   # the layout's theta field
    t1 = time.perf_counter()
    lines = isoline_set(V, F, theta, 0.0)
    t2 = time.perf_counter()
    rel = row_spacing([lines, isoline_set(V, F, theta, np.pi)], spacing_v)
    c0 = time.process_time()
    ribbons = ribbon_layout(V, F, dir1, sigma1, sigma2, kappa1, s)
    t3 = time.perf_counter()
    cpu = time.process_time() - c0

    lengths = np.array([r.length_mm for r in ribbons])
    print(json.dumps({
        "bench": "stripes+layout", "n_vertices": int(len(V)), "n_faces": int(len(F)), "edge_mm": round(h, 3),
        "stripe_field_s": round(t1 - t0, 2), "stripe_iterations": theta.iterations,
        "stripe_singular_faces": int(theta.singular.sum()),
        "isolines_s": round(t2 - t1, 3), "n_isolines": int(len(lines.closed)),
        "ribbon_layout_s": round(t3 - t2, 2), "ribbon_layout_cpu_s": round(cpu, 2),
        "load_avg_1min": round(os.getloadavg()[0], 1), "n_ribbons": len(ribbons),
        "n_front": sum(r.side == "front" for r in ribbons), "n_back": sum(r.side == "back" for r in ribbons),
        "full_length_pct": round(100.0 * float(np.mean(np.abs(lengths - 15.0) < 1e-6)), 1),
        "row_spacing_over_mu2": {"median": round(float(np.median(rel)), 4),
                                   "p10": round(float(np.percentile(rel, 10)), 4),
                                   "p90": round(float(np.percentile(rel, 90)), 4)},
    }))


if __name__ == "__main__":
    main()
