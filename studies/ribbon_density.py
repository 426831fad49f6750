"""Issue 18 "Ribbon density": realised ribbon coverage and transverse spacing of `design()` vs
what Eq. 5.15 asked for, per target, with the losses of each layout stage.

For each target (default meshes/targets/*.obj, 110 mm, the default DesignOptions) it runs
inverse.design.design(V, F) (no verification) and re-runs the layout stages of
inverse.layout.ribbon_layout on the same inputs (the coarsened flat mesh and the clamped
stretches, as design() passes them), keeping the dashes after each stage:

    raw        dashes of l_r cut from the 0 / pi isolines (before any clipping)
    clip       clipped to the outline eroded by w_r / 2
    trim       pieces turning > 25 deg from the field removed
    layout     front/back split, pieces < 2 mm dropped (= ribbon_layout's output)
    final      simplified + separate_ribbons (gap 0.5 mm, < 2 mm dropped) (= Design.ribbons)

Coverage: the printed area fraction (inverse.coverage.printed_fraction, exact polygon areas) in a
disk of radius --radius (default 10 mm: about one dash period mu1 across, several rows) around
sample points on a --grid (default 2.5 mm) square grid inside the flat outline, against the
asked coverage l_r w_r / (mu1 mu2) (Eq. 5.15 at the clamped sigma1, sigma2 of the fine flat
mesh's faces, area-averaged over the same disk). Transverse spacing (transverse_spacing): per 1 mm
of each final ribbon and side, the distance to the nearest abreast point of a near-parallel
ribbon of the other grid (A and B rows alternate, so the next dash of the same row is never
taken for the neighbour row), against the asked mu2 there; a ribbon side with no such
neighbour within 3 mu2 although the fabric continues is a "missing row".

Dash period (dash_period, on the raw dashes): centre-to-centre distance of consecutive
full-length dashes of one row against the asked mu1.
"ideal_pattern_ratio" is the same measure on a perfect staggered pattern at the target's mean
mu1, mu2 (the window noise: at 10 mm its p10 is 0.78-0.91 and 0-12 % falls below 0.8).

    python studies/ribbon_density.py [meshes/targets/saddle.obj ...] [--radius 10] [--grid 2.5] [--png DIR]

Prints one JSON line per target. Lengths mm.
"""
from __future__ import annotations

import argparse
import copy
import glob
import json
import os
import time

import numpy as np

from inverse.coverage import asked_coverage, printed_fraction, ribbon_union

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def layout_inputs(d):
    """The (uv, F, dir1, sigma1, sigma2, kappa1) design() passed to ribbon_layout, and the fine
    mesh's clamped sigmas."""
    from geometry.meshops import face_areas
    from inverse.design import coarsen_for_layout

    b = d.bounds
    s1 = np.clip(d.flat.sigma1, b[0], b[1])
    s2 = np.clip(d.flat.sigma2, b[2], b[3])
    area = face_areas(d.V, d.F)
    uv, F, dl, s1l, s2l, kl = coarsen_for_layout(d.F_input, d.refine_levels, d.layout_levels, d.flat.uv, area,
                                                 d.flat.dir1, s1, s2, d.kappa1)
    return (uv, d.F if F is None else F, dl, s1l, s2l, kl), s1, s2


def layout_stages(uv, F, dir1, sigma1, sigma2, kappa1, s, outline, ribbon_length=15.0, ribbon_width=1.5,
                  min_length=2.0, max_angle_deg=25.0, seed=0, bound_tol=0.05):
    """inverse.layout.ribbon_layout, step by step: {stage: [Ribbon]} for raw, clip, trim, layout."""
    from geometry.stripes import stripe_field
    from inverse import layout as L
    from inverse.spacing import ribbon_spacing

    uv = np.asarray(uv, float)
    F = np.asarray(F).astype(np.int64)
    n = len(uv)
    sigma1 = np.where((sigma1 < 1.0) & (sigma1 >= 1.0 - bound_tol), 1.0, sigma1)
    sigma2 = np.where((sigma2 < 1.0) & (sigma2 >= 1.0 - bound_tol), 1.0, sigma2)
    mu1, mu2 = ribbon_spacing(sigma1, sigma2, s, ribbon_length, ribbon_width)
    region = L._outline_polygon(outline, uv, F)
    e1, e2 = uv[F[:, 1]] - uv[F[:, 0]], uv[F[:, 2]] - uv[F[:, 0]]
    areas = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    fields_v = np.column_stack([L._vertex_average(F, n, areas, v) for v in (kappa1, mu2, mu1)])
    perp = np.column_stack([-dir1[:, 1], dir1[:, 0]])
    theta = stripe_field(uv, F, dir1, 2.0 * fields_v[:, 1], seed=seed, direction_on="face")
    psi = stripe_field(uv, F, perp, fields_v[:, 2], seed=seed + 1, direction_on="face")
    eroded = region.buffer(-0.5 * ribbon_width)
    out = {k: [] for k in ("raw", "clip", "trim", "layout")}
    for grid, value in (("A", 0.0), ("B", np.pi)):
        lines, centres = L._grid_lines(uv, F, theta, psi, value, fields_v, ribbon_length)
        if len(centres) == 0:
            continue
        dash = L._dashes(lines, centres, ribbon_length)
        out["raw"] += L._records(dash, np.ones(dash.n), grid, ribbon_width)
        if dash.n:
            dash = L._clip(dash, eroded)
        out["clip"] += L._records(dash, np.ones(dash.n), grid, ribbon_width)
        if dash.n:
            dash = L._trim_angle(dash, dir1, max_angle_deg)
        out["trim"] += L._records(dash, np.ones(dash.n), grid, ribbon_width)
        if dash.n == 0:
            continue
        dash, side = L._split_sides(dash)
        keep = dash.lengths() >= min_length
        dash, side = dash.select(keep), side[keep]
        out["layout"] += L._records(dash, side, grid, ribbon_width)
    return out


def ideal_baseline(mu1, mu2, radius, h, ribbon_length=15.0, ribbon_width=1.5, size=80.0):
    """The window noise of the measure: coverage / asked of a perfect staggered pattern
    (period mu1, rows mu2) sampled like a target, far from any boundary: (mean, p10, < 0.8)."""
    import shapely

    from geometry.elements import Ribbon

    rib = []
    nr, nk = int(size / mu2) + 2, int(size / mu1) + 2
    for r in range(-nr, nr):
        y = (r + 0.5) * mu2
        for k in range(-nk, nk):
            xc = (k + 0.5 + 0.5 * (r % 2)) * mu1
            rib.append(Ribbon(path=np.array([[xc - ribbon_length / 2, y], [xc + ribbon_length / 2, y]]),
                              width_mm=ribbon_width))
    region = shapely.box(-2 * size, -2 * size, 2 * size, 2 * size)
    X, Y = np.meshgrid(np.arange(-size / 2, size / 2, h) + 0.37, np.arange(-size / 2, size / 2, h) + 0.61)
    c = printed_fraction(rib, region, np.column_stack([X.ravel(), Y.ravel()]), radius)
    c = c / (ribbon_length * ribbon_width / (mu1 * mu2))
    return round(float(c.mean()), 4), round(float(np.percentile(c, 10)), 4), round(float(np.mean(c < 0.8)), 4)


def grid_points(poly, h):
    import shapely

    x0, y0, x1, y1 = poly.bounds
    X, Y = np.meshgrid(np.arange(x0 + h / 2, x1, h), np.arange(y0 + h / 2, y1, h))
    P = np.column_stack([X.ravel(), Y.ravel()])
    return P[shapely.contains_xy(poly, P[:, 0], P[:, 1])]


def disk_mean(P, centroids, weights, values, radius):
    """Area-weighted mean of per-face values over the faces whose centroid is within radius."""
    import scipy.sparse as sp
    from scipy.spatial import cKDTree

    tree = cKDTree(centroids)
    lists = tree.query_ball_point(P, radius)
    rows = np.repeat(np.arange(len(P)), [len(li) for li in lists])
    cols = np.concatenate([np.asarray(li, dtype=np.int64) for li in lists])
    M = sp.csr_matrix((weights[cols], (rows, cols)), shape=(len(P), len(centroids)))
    return (M @ values) / np.maximum(M @ np.ones(len(centroids)), 1e-300)


def transverse_spacing(ribbons, centroids, mu2_face, mu1_face, poly, step=1.0):
    """Realised / asked transverse spacing. Points every ``step`` mm on every ribbon; for each
    ribbon i, the points q of the other grid's near-parallel ribbons (within 30 deg) within
    3 mu2 across: the distance q -> i is the local row spacing where q is abreast of i (its
    closest point on i is interior; exact on curved rows), and beyond i's ends (the staggered
    neighbour dash is never abreast when mu1 > 2 l_r) the distance across i's continuation as an
    arc of its mean geodesic curvature, up to mu1 / 2 beyond. Per 1 mm of i and side the nearest
    such q; ratio = distance / asked mu2 at the foot. A ribbon side with no neighbour row
    although the fabric continues there (mu2 away) is a missing row. Returns (ratios,
    ribbon sides, missing sides)."""
    import shapely
    from scipy.spatial import cKDTree

    P, T, lab, lines = [], [], [], []
    grid = np.array([r.meta.get("grid", "A") for r in ribbons])
    for i, r in enumerate(ribbons):
        ln = shapely.LineString(r.path)
        L = ln.length
        s = np.linspace(0, L, max(2, int(np.ceil(L / step)) + 1))
        pts = np.asarray(shapely.get_coordinates(shapely.line_interpolate_point(ln, s)))
        ahead = np.asarray(shapely.get_coordinates(shapely.line_interpolate_point(ln, np.minimum(s + 0.25, L))))
        behind = np.asarray(shapely.get_coordinates(shapely.line_interpolate_point(ln, np.maximum(s - 0.25, 0))))
        t = ahead - behind
        t /= np.linalg.norm(t, axis=1)[:, None]
        P.append(pts)
        T.append(t)
        lab.append(np.full(len(pts), i))
        lines.append(ln)
    P, T, lab = np.concatenate(P), np.concatenate(T), np.concatenate(lab)
    ctree = cKDTree(centroids)
    tree = cKDTree(P)
    cos30 = np.cos(np.deg2rad(30))
    ratios, n_sides, missing = [], 0, 0
    for i, ln in enumerate(lines):
        L = ln.length
        own = np.nonzero(lab == i)[0]
        mu2_i = mu2_face[ctree.query(P[own])[1]]
        reach = 3.0 * float(mu2_i.max())
        cand = np.unique(np.concatenate([np.asarray(c, dtype=np.int64)
                                         for c in tree.query_ball_point(P[own], reach)]))
        cand = cand[grid[lab[cand]] != grid[i]]
        sides_seen = {1.0: False, -1.0: False}
        if len(cand):
            q = P[cand]
            s = shapely.line_locate_point(ln, shapely.points(q))
            foot = np.asarray(shapely.get_coordinates(shapely.line_interpolate_point(ln, s)))
            ahead = np.asarray(shapely.get_coordinates(shapely.line_interpolate_point(ln, np.minimum(s + 0.25, L))))
            behind = np.asarray(shapely.get_coordinates(shapely.line_interpolate_point(ln, np.maximum(s - 0.25, 0))))
            t = ahead - behind
            t /= np.linalg.norm(t, axis=1)[:, None]
            v = q - foot
            dist = np.linalg.norm(v, axis=1)
            side = np.sign(t[:, 0] * v[:, 1] - t[:, 1] * v[:, 0])
            # beyond an end: continue the centre line as an arc of its mean geodesic curvature
            # (turning of the end tangents / length) and measure across that continuation
            t0, t1 = T[own[0]], T[own[-1]]
            kg = np.arctan2(t0[0] * t1[1] - t0[1] * t1[0], t0 @ t1) / max(L, 1e-9)
            for end, te, sgn_a in ((P[own[0]], t0, -1.0), (P[own[-1]], t1, 1.0)):
                at = (s <= 1e-9) if sgn_a < 0 else (s >= L - 1e-9)
                if not at.any():
                    continue
                w = q[at] - end
                a = sgn_a * (w @ te)                      # distance beyond the end, along
                c = w @ np.array([-te[1], te[0]]) - 0.5 * kg * a ** 2
                dist[at] = np.where(a <= 0.5 * mu1_face[ctree.query(q[at])[1]], np.abs(c), np.inf)
                side[at] = np.sign(c)
            mu2_q = mu2_face[ctree.query(foot)[1]]
            ok = ((np.abs(np.sum(T[cand] * t, axis=1)) >= cos30) & (dist <= 3.0 * mu2_q) & (side != 0))
            s = np.clip(s, 0.0, L)
            b = np.floor(s[ok] / step).astype(np.int64)
            for sg in (1.0, -1.0):
                m = side[ok] == sg
                if not m.any():
                    continue
                sides_seen[sg] = True
                r = dist[ok][m] / mu2_q[ok][m]
                order = np.lexsort((r, b[m]))
                first = np.ones(len(order), bool)
                first[1:] = b[m][order][1:] != b[m][order][:-1]
                ratios.extend(r[order][first])
        mid = P[own[len(own) // 2]]
        tmid = T[own[len(own) // 2]]
        for sg in (1.0, -1.0):
            probe = mid + sg * np.array([-tmid[1], tmid[0]]) * float(mu2_i[len(own) // 2])
            if not shapely.contains_xy(poly, probe[0], probe[1]):
                continue                       # the fabric ends on this side
            n_sides += 1
            missing += not sides_seen[sg]
    return np.asarray(ratios), n_sides, missing


def dash_period(ribbons, centroids, mu1_face, ribbon_length=15.0, across_tol=1.0):
    """Realised / asked dash period along the rows: for each dash of full length (within 1 %),
    the next dash of the same grid continuing its centre line (beyond its end, within
    across_tol mm of the line continued as an arc of the dash's geodesic curvature, up to 3 mu1
    on), with full length too; period = centre-to-centre distance along, against the asked mu1
    at the midpoint. Returns the ratios."""
    import shapely
    from scipy.spatial import cKDTree

    rec = []
    for r in ribbons:
        ln = shapely.LineString(r.path)
        L = ln.length
        e = [np.asarray(shapely.get_coordinates(shapely.line_interpolate_point(ln, x))).ravel()
             for x in (0.0, 0.25, L - 0.25, L, 0.5 * L)]
        t0 = (e[1] - e[0]) / np.linalg.norm(e[1] - e[0])
        t1 = (e[3] - e[2]) / np.linalg.norm(e[3] - e[2])
        kg = np.arctan2(t0[0] * t1[1] - t0[1] * t1[0], t0 @ t1) / max(L, 1e-9)
        rec.append((e[0], e[3], t1, kg, e[4], L, r.meta.get("grid", "A")))
    full = np.array([abs(x[5] - ribbon_length) <= 0.01 * ribbon_length for x in rec])
    starts = np.array([x[0] for x in rec])
    ends = np.array([x[1] for x in rec])
    grid = np.array([x[6] for x in rec])
    ctree = cKDTree(centroids)
    tree = cKDTree(np.vstack([starts, ends]))
    n = len(rec)
    out = []
    for i in np.nonzero(full)[0]:
        _, end, t, kg, mid, L, g = rec[i]
        mu1 = float(mu1_face[ctree.query(mid)[1]])
        best = None
        for j in tree.query_ball_point(end, 3 * mu1):
            j2 = j % n
            if j2 == i or grid[j2] != g or not full[j2]:
                continue
            w = (starts[j2] if j < n else ends[j2]) - end
            a = w @ t
            c = w @ np.array([-t[1], t[0]]) - 0.5 * kg * a ** 2
            if a > 0 and abs(c) <= across_tol and (best is None or a < best):
                best = a
        if best is not None:
            out.append((best + ribbon_length) / mu1)
    return np.asarray(out)


def plot_ratio(path_png, outline, P, ratio, ribbons, title):
    """Map of realised / asked coverage at the sample points, with the final ribbons."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6.3))
    sc = ax.scatter(P[:, 0], P[:, 1], c=ratio, s=9, cmap="RdBu", vmin=0.0, vmax=2.0, marker="s", linewidths=0)
    o = np.vstack([outline, outline[:1]])
    ax.plot(o[:, 0], o[:, 1], "k-", lw=0.6)
    for r in ribbons:
        ax.plot(r.path[:, 0], r.path[:, 1], "k-", lw=1.0)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9)
    fig.colorbar(sc, ax=ax, shrink=0.8, label="realised / asked coverage")
    fig.tight_layout()
    fig.savefig(path_png, dpi=90)
    plt.close(fig)


def study(path, radius, h, png_dir=None):
    import shapely

    from geometry.target import read_mesh
    from inverse.design import design
    from inverse.separation import separate_ribbons, simplify_paths
    from inverse.spacing import ribbon_spacing

    t0 = time.perf_counter()
    V, F = read_mesh(path)
    d = design(V, F, where=os.path.basename(path))
    t_design = time.perf_counter() - t0
    (uv, Fl, dl, s1l, s2l, kl), s1, s2 = layout_inputs(d)
    st = layout_stages(uv, Fl, dl, s1l, s2l, kl, d.stretch, d.outline)
    rib = copy.deepcopy(st["layout"])
    simplify_paths(rib, 0.01)
    rib, sep = separate_ribbons(rib, d.outline, 0.5, min_length=2.0)
    st["final"] = rib
    same = len(rib) == len(d.ribbons) and sep == d.separation
    poly = shapely.Polygon(d.outline)
    # asked, on the fine flat mesh
    mu1f, mu2f = ribbon_spacing(s1, s2, d.stretch)
    asked_f = asked_coverage(s1, s2, d.stretch)
    tri = d.flat.uv[d.F]
    cen = tri.mean(axis=1)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    af = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    P = grid_points(poly, h)
    asked = disk_mean(P, cen, af, asked_f, radius)
    total_asked_area = float(np.sum(af * asked_f))
    rec = {"target": os.path.basename(path), "faces": int(len(d.F)), "flat_area_mm2": round(float(af.sum()), 1),
           "design_s": round(t_design, 1), "replay_matches_design": bool(same),
           "out_of_bounds_pct": [round(float(x), 1) for x in d.flat.sigma_out_of_bounds_pct],
           "asked_sigma1_mean": round(float(np.sum(af * s1) / af.sum()), 3),
           "asked_sigma2_mean": round(float(np.sum(af * s2) / af.sum()), 3),
           "asked_mu1_mean": round(float(np.sum(af * mu1f) / af.sum()), 2),
           "asked_mu2_mean": round(float(np.sum(af * mu2f) / af.sum()), 2),
           "radius_mm": radius, "grid_mm": h, "n_points": int(len(P)),
           "asked_coverage_mean": round(float(asked.mean()), 4),
           "asked_coverage_p10": round(float(np.percentile(asked, 10)), 4),
           "asked_printed_area_mm2": round(total_asked_area, 1), "stages": {}}
    for name in ("raw", "clip", "trim", "layout", "final"):
        rs = st[name]
        u = shapely.intersection(ribbon_union(rs), poly)
        cov = printed_fraction(u, poly, P, radius)
        ratio = cov / asked
        lengths = [shapely.LineString(r.path).length for r in rs]
        rec["stages"][name] = {
            "ribbons": len(rs), "length_mm": round(float(np.sum(lengths)), 1),
            "printed_area_mm2": round(float(u.area), 1),
            "printed_over_asked_area": round(float(u.area / total_asked_area), 4),
            "coverage_mean": round(float(np.nanmean(cov)), 4),
            "coverage_p10": round(float(np.nanpercentile(cov, 10)), 4),
            "ratio_mean": round(float(np.nanmean(ratio)), 4),
            "ratio_p10": round(float(np.nanpercentile(ratio, 10)), 4),
            "area_below_80pct_of_asked": round(float(np.mean(ratio < 0.8)), 4)}
        if name == "final" and png_dir:
            os.makedirs(png_dir, exist_ok=True)
            plot_ratio(os.path.join(png_dir, os.path.splitext(os.path.basename(path))[0] + "_coverage.png"),
                       d.outline, P, ratio, rs, f"{os.path.basename(path)}: realised / asked ribbon coverage "
                       f"(disk r = {radius:g} mm)")
        if name == "final":
            # interior only: sample points more than one disk radius inside the outline
            inner = shapely.contains_xy(poly.buffer(-radius), P[:, 0], P[:, 1])
            if inner.any():
                rec["stages"][name]["interior_ratio_mean"] = round(float(np.nanmean(ratio[inner])), 4)
                rec["stages"][name]["interior_area_below_80pct"] = round(float(np.mean(ratio[inner] < 0.8)), 4)
                rec["stages"][name]["interior_points"] = int(inner.sum())
    base = ideal_baseline(rec["asked_mu1_mean"], rec["asked_mu2_mean"], radius, h)
    rec["ideal_pattern_ratio"] = {"mean": base[0], "p10": base[1], "below_80pct": base[2]}
    rec["separation"] = d.separation
    rat, n_sides, missing = transverse_spacing(st["final"], cen, mu2f, mu1f, poly)
    rec["spacing"] = {"realised_over_asked_median": round(float(np.median(rat)), 4),
                      "p10": round(float(np.percentile(rat, 10)), 4), "p90": round(float(np.percentile(rat, 90)), 4),
                      "within_10pct": round(float(np.mean(np.abs(rat - 1) <= 0.1)), 4),
                      "over_1.5x": round(float(np.mean(rat > 1.5)), 4),
                      "ribbon_sides": int(n_sides), "missing_row_fraction": round(missing / max(n_sides, 1), 4)}
    per = dash_period(st["raw"], cen, mu1f)
    if len(per):
        rec["dash_period_raw"] = {"realised_over_asked_median": round(float(np.median(per)), 4),
                                  "p10": round(float(np.percentile(per, 10)), 4),
                                  "p90": round(float(np.percentile(per, 90)), 4), "pairs": int(len(per))}
    rec["time_s"] = round(time.perf_counter() - t0, 1)
    return rec


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("targets", nargs="*", default=None)
    ap.add_argument("--radius", type=float, default=10.0, help="disk radius of the coverage window, mm")
    ap.add_argument("--grid", type=float, default=2.5, help="sample grid spacing, mm")
    ap.add_argument("--png", default=None, help="write a coverage-ratio map per target into this folder")
    ap.add_argument("--out", default=None, help="also write the JSON lines to this file")
    a = ap.parse_args(argv)
    targets = a.targets or sorted(glob.glob(os.path.join(ROOT, "meshes", "targets", "*.obj")))
    lines = []
    for p in targets:
        rec = study(p, a.radius, a.grid, a.png)
        print(json.dumps(rec), flush=True)
        lines.append(rec)
    if a.out:
        os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
        with open(a.out, "w") as f:
            for r in lines:
                f.write(json.dumps(r) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
