"""Measures of deployed sheets and of mesh convergence, shared by the studies and the tests (mm).

- centre_quadric: curvatures of a quadric fitted to the deployed centre of a sheet.
- gallery_measure: the number that asserts each gallery case's shape (studies/gallery.py),
  also the along/across ribbon curvature of the orthotropic sweep (studies/ortho_sweep.py).
- observed_order, rigid_align, rms_to_reference: convergence order and the distance between
  two deployed solutions on different meshes (studies/convergence.py).
"""
from __future__ import annotations

import numpy as np

from inverse.registration import kabsch
from shellfem.sheet import Sheet

# --------------------------------------------------------------------------- deployed shapes


def centre_quadric(sheet, x, frac=0.3) -> dict:
    """Fit z = quadric to the deployed vertices whose printed distance to the centroid is below
    frac x the largest, in the principal frame of those vertices; curvatures (1/mm) at the centre."""
    P = sheet.points
    r = np.linalg.norm(P - P.mean(0), axis=1)
    sel = r < frac * r.max()
    X = x[sel] - x[sel].mean(0)
    F = X @ np.linalg.svd(X, full_matrices=False)[2].T
    u, v, w = F.T
    A = np.column_stack([u * u, u * v, v * v, u, v, np.ones_like(u)])
    co = np.linalg.lstsq(A, w, rcond=None)[0]
    fxx, fxy, fyy, gx, gy = 2 * co[0], co[1], 2 * co[2], co[3], co[4]
    n2 = 1 + gx * gx + gy * gy
    K = (fxx * fyy - fxy ** 2) / n2 ** 2
    H = ((1 + gy * gy) * fxx - 2 * gx * gy * fxy + (1 + gx * gx) * fyy) / (2 * n2 ** 1.5)
    return dict(gauss_centre_fit=float(K), mean_curv_centre_fit=float(abs(H)),
                principal_centre_fit=[float(k) for k in np.linalg.eigvalsh([[fxx, fxy], [fxy, fyy]])],
                fit_rms_mm=float(np.sqrt(np.mean((A @ co - w) ** 2))),
                height_span_mm=float(np.ptp(x[:, 2])))


def _centre_rim(sheet, values, frac=0.25):
    c = sheet.points[sheet.triangles].mean(1)
    r = np.linalg.norm(c - c.mean(0), axis=1)
    R = r.max()
    return float(np.median(values[r < frac * R])), float(np.median(values[r > (1 - frac) * R]))


def _edge_length(x, idx):
    return float(np.sum(np.linalg.norm(np.diff(x[idx], axis=0), axis=1)))


def gallery_measure(name, sim) -> dict:
    """The shape measures of gallery case ``name`` (a key of validation.cases.GALLERY_CASES) on
    a forward.simulate result: curvatures in 1/mm, length ratios deployed / printed."""
    sheet, model, q = sim.sheet, sim.model, sim.result.q
    k, H, K = model.curvatures(q)
    a, b = model.cartesian_forms(q)
    S = np.linalg.solve(a, b)
    out = {}
    if name == "tube":
        kab = np.sort(np.abs(k), axis=1)
        out["median_kmax_over_kmin"] = float(np.median(kab[:, 1] / np.maximum(kab[:, 0], 1e-12)))
        out["median_abs_k_mm"] = [float(v) for v in np.median(kab, 0)]
    elif name in ("dome", "flat_centre"):
        out.update(centre_quadric(sheet, model.split(q)[0]))
        kc, kr = _centre_rim(sheet, K)
        out.update(gauss_centre_median_triangle=kc, gauss_rim_median_triangle=kr)
    elif name in ("ribbons", "ortho_0", "ortho_90"):
        c = sheet.points[sheet.triangles].mean(1)
        lo, hi = c.min(0), c.max(0)
        inner = np.all((c > lo + 0.2 * (hi - lo)) & (c < hi - 0.2 * (hi - lo)), axis=1)
        Sm = np.median(S[inner], axis=0)
        out.update(curvature_along_ribbons=float(Sm[0, 0]), curvature_across_ribbons=float(Sm[1, 1]),
                   twist=float(Sm[0, 1]),
                   along_over_across=float(abs(Sm[0, 0]) / max(abs(Sm[1, 1]), 1e-12)))
    elif name == "half_annulus":
        x = model.split(q)[0]
        P = sheet.points
        ctr = np.array([P[:, 0].max() / 2 + P[:, 0].min() / 2, 0.0])
        rr = np.linalg.norm(P - ctr, axis=1)
        ang = np.arctan2(P[:, 1] - ctr[1], P[:, 0] - ctr[0])
        tol = 0.3
        res = {}
        for edge, sel in (("inner", rr < rr.min() + tol), ("outer", rr > rr.max() - tol)):
            idx = np.flatnonzero(sel)
            idx = idx[np.argsort(ang[idx])]
            res[edge] = _edge_length(x, idx) / _edge_length(np.column_stack([P, np.zeros(len(P))]), idx)
        out.update(inner_length_ratio=res["inner"], outer_length_ratio=res["outer"],
                   inner_contracts_more=bool(res["inner"] < res["outer"]))
    return out


# --------------------------------------------------------------------------- mesh convergence


def observed_order(h, err) -> float:
    """Least-squares slope of log(err) against log(h)."""
    return float(np.polyfit(np.log(np.asarray(h, float)), np.log(np.asarray(err, float)), 1)[0])


def rigid_align(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """X moved by the rotation + translation that best fits it to Y (Kabsch, least squares)."""
    R, t = kabsch(X, Y)
    return X @ R.T + t


def rms_to_reference(sheet: Sheet, x: np.ndarray, ref_sheet: Sheet, ref_x: np.ndarray) -> float:
    """RMS distance (mm) between deployed positions x and the reference solution linearly
    interpolated at the same printed points, after the best rigid alignment."""
    from matplotlib.tri import LinearTriInterpolator, Triangulation
    tri = Triangulation(ref_sheet.points[:, 0], ref_sheet.points[:, 1], ref_sheet.triangles)
    p = sheet.points
    y = np.column_stack([np.asarray(LinearTriInterpolator(tri, ref_x[:, k])(p[:, 0], p[:, 1]).filled(np.nan))
                         for k in range(3)])
    ok = np.isfinite(y).all(1)
    return float(np.sqrt(np.mean(np.sum((rigid_align(x[ok], y[ok]) - y[ok]) ** 2, axis=1))))
