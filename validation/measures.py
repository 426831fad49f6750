"""Measures of deployed sheets and of mesh convergence, shared by the studies and the tests (mm).

- centre_quadric, quadric_curvatures, sampled_centre_quadric: curvatures of a quadric fitted to
  the deployed centre of a sheet (its vertices, or the surface sampled on a uniform flat grid).
- gallery_measure: the number that asserts each gallery case's shape (studies/gallery.py),
  also the along/across ribbon curvature of the orthotropic sweep (studies/ortho_sweep.py).
- deployed_at, normal_curvature, curve_curvatures, coarse_curvature_tensor, ribbon_curvatures,
  line_contractions, centreline_measures: measures on the printed geometry, the same for any mesh of it (the
  rods model's and the shell's, studies/rods_vs_shell.py): the deployed surface sampled at
  flat points (barycentric interpolation in the flat mesh) and the normal curvatures of the
  3D curves through those samples.
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
    return quadric_curvatures(x[r < frac * r.max()])


def quadric_curvatures(X) -> dict:
    """Curvatures of the quadric z = f(u, v) least-squares fitted to the 3D points X (n, 3) mm in
    their principal frame (w along the smallest singular direction), at the frame's origin:
    gauss_centre_fit K (1/mm^2), mean_curv_centre_fit |H| (1/mm), principal_centre_fit (the
    Hessian's eigenvalues, 1/mm), fit_rms_mm and height_span_mm (of X's z)."""
    X = np.asarray(X, float)
    Xc = X - X.mean(0)
    F = Xc @ np.linalg.svd(Xc, full_matrices=False)[2].T
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
                height_span_mm=float(np.ptp(X[:, 2])))


def sampled_centre_quadric(points, triangles, x, frac=0.3, spacing=0.5) -> dict:
    """centre_quadric on the deployed surface sampled at a square grid of flat points
    (``spacing`` mm) within frac x the largest vertex distance from the vertices' centroid:
    every flat area counts the same whatever the mesh (a mesh dense on the printed arms
    would weigh their bumps more). Curvatures 1/mm (K 1/mm^2)."""
    P = np.asarray(points, float)
    c = P.mean(0)
    R = frac * np.linalg.norm(P - c, axis=1).max()
    g = np.arange(-R, R + 1e-9, spacing)
    q = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    q = q[np.linalg.norm(q, axis=1) < R] + c
    X, _ = deployed_at(P, triangles, x, q)
    return quadric_curvatures(X[np.isfinite(X).all(1)])


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


# --------------------------------------------------------------------------- curves on the deployed surface


def deployed_at(points, triangles, x, query):
    """Deployed positions (n, 3) mm and unit normals (n, 3) at the flat points ``query`` (n, 2)
    mm of the flat mesh (points (nv, 2), triangles (m, 3)) deployed to x (nv, 3): barycentric
    interpolation in the flat triangle that holds each point, of x and of the area-weighted
    vertex normals; normals point to the deployed side of the flat +z (the front). NaN rows
    for points outside the mesh."""
    from matplotlib.tri import Triangulation

    from geometry.meshops import signed_areas, vertex_normals
    P, T, x = np.asarray(points, float), np.asarray(triangles), np.asarray(x, float)
    q = np.atleast_2d(np.asarray(query, float))
    t = Triangulation(P[:, 0], P[:, 1], T).get_trifinder()(q[:, 0], q[:, 1])
    ccw = np.where((signed_areas(P, T) < 0)[:, None], T[:, [0, 2, 1]], T)      # wound to the flat +z side
    nv = vertex_normals(x, ccw, weighting="area")
    X = np.full((len(q), 3), np.nan)
    N = np.full((len(q), 3), np.nan)
    ok = t >= 0
    tt = T[t[ok]]
    A, B, C = P[tt[:, 0]], P[tt[:, 1]], P[tt[:, 2]]
    M = np.stack([B - A, C - A], axis=2)                                  # (k, 2, 2)
    l12 = np.linalg.solve(M, (q[ok] - A)[..., None])[..., 0]
    w = np.column_stack([1 - l12.sum(1), l12])                            # (k, 3)
    X[ok] = np.einsum("kj,kjd->kd", w, x[tt])
    n = np.einsum("kj,kjd->kd", w, nv[tt])
    N[ok] = n / np.linalg.norm(n, axis=1)[:, None]
    return X, N


def normal_curvature(a, b, c, n):
    """Signed normal curvature (1/mm) at b of the circle through the 3D points a, b, c (..., 3):
    the curvature vector (towards the circle's centre, magnitude 1 / radius) dotted with the
    surface's unit normal n at b. Exact for three points on a circle; negative when the centre
    lies on the -n side (a front print bending its centre of curvature to the back), 0 for
    collinear points."""
    u, v = np.asarray(a, float) - b, np.asarray(c, float) - b
    w = np.cross(u, v)
    w2 = np.sum(w * w, axis=-1)
    off = (np.sum(u * u, -1)[..., None] * np.cross(v, w) + np.sum(v * v, -1)[..., None] * np.cross(w, u))
    tiny = w2 <= 1e-30 * (np.sum(u * u, -1) * np.sum(v * v, -1) + 1e-300)
    off = off / (2 * np.where(tiny, 1.0, w2))[..., None]                 # b -> the circle's centre
    off2 = np.sum(off * off, axis=-1)
    kvec = off / np.where(tiny, 1.0, off2)[..., None]
    return np.where(tiny, 0.0, np.sum(kvec * n, axis=-1))


def curve_curvatures(points, triangles, x, curve):
    """Normal curvatures (1/mm) at the interior points of the deployed image of the flat
    polyline ``curve`` (k, 2) mm: (k - 2,), NaN where a point of a triple is outside the mesh.
    The curve's point spacing is the scale measured."""
    X, N = deployed_at(points, triangles, x, curve)
    return normal_curvature(X[:-2], X[1:-1], X[2:], N[1:-1])


def _along(path, fractions):
    """Points (len(fractions), 2) at the arc-length fractions of the polyline ``path``."""
    path = np.asarray(path, float)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    f = np.asarray(fractions, float) * s[-1]
    return np.column_stack([np.interp(f, s, path[:, 0]), np.interp(f, s, path[:, 1])])


def _stations(points, triangles, x, lines, trim, count=13):
    """The stations across a family of flat polylines ``lines``: each line's points at ``count``
    arc-length fractions from trim to 1 - trim, flat S (n lines, count, 2) mm, and their deployed
    positions X and unit normals N (n lines, count, 3) (deployed_at)."""
    S = np.stack([_along(p, np.linspace(trim, 1 - trim, count)) for p in lines])
    X, N = deployed_at(points, triangles, x, S.reshape(-1, 2))
    return S, X.reshape(len(lines), count, 3), N.reshape(len(lines), count, 3)


DIRECTIONS_DEG = (0.0, 45.0, 90.0, 135.0)


def coarse_curvature_tensor(points, triangles, x, centres, step):
    """Curvature tensor (n, 2, 2) (1/mm, in the flat x/y frame) at the flat points ``centres``
    (n, 2) at the scale ``step`` (mm): the normal curvatures k(t) of the deployed images of the
    flat triples (c - step d, c, c + step d) along the directions d = (cos t, sin t), t in
    DIRECTIONS_DEG, fitted by least squares to k(t) = S11 cos^2 t + 2 S12 cos t sin t + S22
    sin^2 t. The directions are the flat ones: exact (to the interpolation's chords) where the
    deployment keeps angles, e.g. a cylinder rolled isometrically, and on a sphere, where every
    direction has the same normal curvature; a strongly anisotropic contraction skews them. At
    a step of the pattern's period it averages the pattern's own bumps. NaN rows where a sample
    is outside the mesh."""
    c = np.atleast_2d(np.asarray(centres, float))
    th = np.radians(DIRECTIONS_DEG)
    d = np.column_stack([np.cos(th), np.sin(th)])                          # (4, 2)
    q = np.concatenate([c[:, None, :] - step * d, np.broadcast_to(c[:, None, :], (len(c), 4, 2)),
                        c[:, None, :] + step * d], axis=1).reshape(-1, 2)   # (n * 12, 2)
    X, N = deployed_at(points, triangles, x, q)
    X, N = X.reshape(len(c), 3, 4, 3), N.reshape(len(c), 3, 4, 3)
    k = normal_curvature(X[:, 0], X[:, 1], X[:, 2], N[:, 1])               # (n, 4)
    A = np.column_stack([d[:, 0] ** 2, 2 * d[:, 0] * d[:, 1], d[:, 1] ** 2])
    s = k @ np.linalg.pinv(A).T                                             # (n, 3)
    return np.stack([np.stack([s[:, 0], s[:, 1]], -1), np.stack([s[:, 1], s[:, 2]], -1)], -2)


def ribbon_curvatures(points, triangles, x, lines, step, trim=0.2) -> dict:
    """Along / across normal curvatures (1/mm) of a family of roughly parallel centre lines
    ``lines`` (flat polylines, in order across the family, mm): along = the median over the
    curves on each line sampled every ``step`` mm; across = the median over the curves through
    the lines' points at the same arc-length fraction (the stations). Only the inner part
    counts: fractions trim..1 - trim along, and lines trim..1 - trim of the family (a free
    edge curls on its own). Returns along, across (medians), along_over_across and the counts."""
    n = len(lines)
    inner = np.arange(n)[(np.arange(n) >= trim * (n - 1)) & (np.arange(n) <= (1 - trim) * (n - 1))]
    along = []
    for i in inner:
        L = float(np.sum(np.linalg.norm(np.diff(np.asarray(lines[i], float), axis=0), axis=1)))
        m = max(3, int(round((1 - 2 * trim) * L / step)) + 1)
        along.append(curve_curvatures(points, triangles, x, _along(lines[i], np.linspace(trim, 1 - trim, m))))
    along = np.concatenate(along) if along else np.zeros(0)
    _, X, N = _stations(points, triangles, x, lines, trim)
    mid = inner[(inner > 0) & (inner < n - 1)]
    across = normal_curvature(X[mid - 1], X[mid], X[mid + 1], N[mid]).ravel()
    a, c = float(np.nanmedian(along)), float(np.nanmedian(across))
    return dict(along=a, across=c, along_over_across=abs(a) / max(abs(c), 1e-12),
                n_along=int(np.isfinite(along).sum()), n_across=int(np.isfinite(across).sum()))


def line_contractions(points, triangles, x, lines, trim=0.2, spacing=0.5) -> dict:
    """Contraction of a family of centre lines ``lines`` (flat polylines in order across the
    family, mm), deployed / printed: ``along`` (n lines,) the length of each line's deployed
    image over the fractions trim..1 - trim (sampled every ``spacing`` mm) over its flat length;
    ``across`` (n - 1 gaps,) per pair of neighbouring lines the median over 13 stations (the same
    arc-length fractions) of the deployed distance between their points over the flat one. A
    ribbon of finite width resists the contraction across it, a centre-line rod does not (seed
    Fig. 5.8): ``across`` says which the model does where the ribbons are dense or sparse."""
    along = []
    for p in lines:
        p = np.asarray(p, float)
        L = float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
        q = _along(p, np.linspace(trim, 1 - trim, max(3, int(np.ceil((1 - 2 * trim) * L / spacing)) + 1)))
        X, _ = deployed_at(points, triangles, x, q)
        along.append(np.sum(np.linalg.norm(np.diff(X, axis=0), axis=1)) / np.sum(np.linalg.norm(np.diff(q, axis=0), axis=1)))
    S, X, _ = _stations(points, triangles, x, lines, trim)
    across = np.nanmedian(np.linalg.norm(np.diff(X, axis=0), axis=2) / np.linalg.norm(np.diff(S, axis=0), axis=2), 1)
    return dict(along=np.array(along), across=across)


def _grid_inside(outline, spacing, margin):
    """Flat points of a square grid (spacing mm) inside ``outline`` shrunk by margin mm."""
    import shapely
    inner = outline.buffer(-margin)
    if inner.is_empty:
        return np.zeros((0, 2))
    x0, y0, x1, y1 = inner.bounds
    g = np.stack(np.meshgrid(np.arange(x0, x1 + 1e-9, spacing), np.arange(y0, y1 + 1e-9, spacing)), -1).reshape(-1, 2)
    return g[shapely.contains_xy(inner, g[:, 0], g[:, 1])]


def centreline_measures(name, pattern, points, triangles, x) -> dict:
    """The model-independent measures of gallery case ``name`` (studies/rods_vs_shell.py) on a
    flat mesh (points, triangles) of ``pattern`` (geometry.patterns.Pattern) deployed to x: all
    curvatures 1/mm, on the pattern's printed geometry whatever the mesh.
    tube: the coarse curvature tensor (step = the star spacing) on a grid over the sheet:
      median S11 (k_x, along x) and S22 (k_y), their ratio |large| / |small|, and the median
      principal |k| (k_max, k_min) and their ratio; the star spacing: the lattice period, so a
      triple's points sit alike on the stars' bumps (half of it would alias them);
    dome, flat_centre: gauss_centre K (1/mm^2) and mean_centre |H| of sampled_centre_quadric
      (a quadric fitted to the deployed centre sampled on a uniform flat grid), and the medians
      of det S and |tr S| / 2 of the tensor (step = the star spacing) at the grid points within
      0.3 of the largest printed distance from the centroid;
    ribbons, half_annulus: ribbon_curvatures on the ribbons' centre lines (step = the median
      distance between neighbouring lines) and line_contractions: the median along / across
      contraction (deployed / printed) of the first and the last third of the lines / gaps in
      pattern order (half_annulus: inner, outer), and the across contraction of every gap."""
    from geometry.centrelines import pattern_centrelines
    P = np.asarray(points, float)
    if name in ("tube", "dome", "flat_centre"):
        spacing = float(pattern.raw["stars"]["spacing_mm"])
        step = spacing
        g = _grid_inside(pattern.outline, 0.5 * step, step)
        if name != "tube":
            r = np.linalg.norm(P - P.mean(0), axis=1).max()
            g = g[np.linalg.norm(g - P.mean(0), axis=1) < 0.3 * r]
        S = coarse_curvature_tensor(P, triangles, x, g, step)
        S = S[np.isfinite(S).all((1, 2))]
        if not len(S):                           # the sheet is smaller than two steps
            return dict(step_mm=step, n_stations=0)
        if name == "tube":
            ev = np.sort(np.abs(np.linalg.eigvalsh(S)), axis=1)
            kx, ky = float(np.median(S[:, 0, 0])), float(np.median(S[:, 1, 1]))
            kmin, kmax = (float(v) for v in np.median(ev, 0))
            return dict(k_x=kx, k_y=ky, ratio=max(abs(kx), abs(ky)) / max(min(abs(kx), abs(ky)), 1e-12),
                        k_max=kmax, k_min=kmin, principal_ratio=kmax / max(kmin, 1e-12), step_mm=step,
                        n_stations=int(len(S)))
        K = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] ** 2
        H = 0.5 * (S[:, 0, 0] + S[:, 1, 1])
        fit = sampled_centre_quadric(P, triangles, x)
        return dict(gauss_centre=fit["gauss_centre_fit"], mean_centre=fit["mean_curv_centre_fit"],
                    height_span_mm=float(np.ptp(x[:, 2])),
                    gauss_tensor_median=float(np.median(K)), mean_tensor_median=float(abs(np.median(H))),
                    step_mm=step, n_stations=int(len(S)))
    if name in ("ribbons", "half_annulus"):
        lines = [p for p, _, _, _ in pattern_centrelines(pattern)]
        mids = np.array([_along(p, [0.5])[0] for p in lines])
        step = float(np.median(np.linalg.norm(np.diff(mids, axis=0), axis=1)))
        c = line_contractions(P, triangles, x, lines)
        third = max(1, len(lines) // 3)
        return {**ribbon_curvatures(P, triangles, x, lines, step), "step_mm": step,
                "along_contraction_first_last": [float(np.median(c["along"][:third])),
                                                 float(np.median(c["along"][-third:]))],
                "across_contraction_first_last": [float(np.median(c["across"][:third])),
                                                  float(np.median(c["across"][-third:]))],
                "across_contraction": [round(float(v), 4) for v in c["across"]]}
    return {}


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
