"""The seed's qualitative results, simulated, each with the number that asserts it.

Cases (pattern files written to examples/gallery/, results to out/gallery/<name>/,
pictures to docs/gallery/<name>.png):
  tube          uniform star field, free boundary (seed Fig. 3.2): one principal curvature
                dominates: median |k_max| / |k_min| over the printed sheet.
  dome          hexagon, arm length decreasing towards the rim, boundary held on the ground
                (Fig. 3.7/3.8): the Gaussian curvature of a quadric fitted to the deployed
                centre (inner 30 % of the radius) is > 0. Per-triangle curvature would
                measure the bumps each star makes, not the sheet's shape.
  flat_centre   the same with arm length increasing towards the rim: a flatter centre, i.e.
                the fitted mean curvature |H| at the centre well below the dome's.
  ribbons       parallel ribbons along x (Fig. 4.8): a cylinder about the axis across
                the ribbons: median curvature along / across the ribbons.
  ortho_0, ortho_90   the same ribbons on the orthotropic fabric with its course direction
                at 0 and 90 deg to the ribbons (seed section 4.1): curvature along / across.
  half_annulus  ribbons along circular arcs on a half annulus, denser outside (Fig. 5.2/5.8):
                the inner edge contracts more than the outer one (deployed / printed length).
Prints ONE JSON line with every case's numbers, wall time and convergence.
Run: python -m validation.gallery [--only NAME ...]
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

FABRIC = {"stretch": 1.35, "thickness_mm": 0.8}
PLASTIC = {"young_modulus_mpa": 72.3, "poisson": 0.5}
# the seed's chapter-3 star experiments: E_plastic / E_fabric = 3.2e3 from its strip calibration
# (section 3.3); with chapter 4's 72.3 MPa a 0.3 mm star curls to a ~3 mm radius and every
# star sheet rolls up tightly whatever the arm-length field
PLASTIC_CH3 = {"young_modulus_mpa": 3.2e3 * 1.05, "poisson": 0.5}


def _stars(outline: dict, arm_length, spacing=10.0, across=1.0, size=2.5) -> dict:
    return {"fabric": {**outline, **FABRIC}, "plastic": PLASTIC_CH3,
            "stars": {"spacing_mm": spacing, "arm_length": arm_length, "thickness_mm": 0.3, "arm_width_mm": 0.8,
                      "side": "front"},
            "mesh": {"size_mm": size, "across": across}, "solver": {"seed": 0}}


def _parallel_ribbons(width=60.0, height=40.0, pitch=4.0, model="neo-hookean", course=0.0) -> dict:
    rows = np.arange(pitch / 2, height, pitch)
    ribbons = [{"path": [[2.0, float(y)], [width - 2.0, float(y)]], "width_mm": 1.5, "thickness_mm": 0.4,
                "side": "front"} for y in rows]
    fab = {"rectangle": [width, height], **FABRIC, "model": model}
    if model == "orthotropic":
        fab["course_angle_deg"] = course
    return {"fabric": fab, "plastic": PLASTIC, "ribbon": ribbons, "mesh": {"size_mm": 2.0, "across": 1},
            "solver": {"seed": 0}}


def _held_rim(raw: dict) -> dict:
    """Seed Fig. 3.8: "a hexagonal domain fixed at its boundary". The rim is held on the ground
    plane and slides (fix = "z"): held in place (xyz) a rim of long-armed stars cannot contract
    to where the bare fabric would, and a free hexagon rolls into a tube like Fig. 3.2."""
    return {**raw, "support": [{"boundary": True, "fix": "z"}]}


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


def _half_annulus(r_in=25.0, r_out=50.0, n_arc=48) -> dict:
    t = np.linspace(0.0, np.pi, n_arc + 1)
    outer = np.column_stack([r_out * np.cos(t), r_out * np.sin(t)])
    inner = np.column_stack([r_in * np.cos(t[::-1]), r_in * np.sin(t[::-1])])
    outline = np.vstack([outer, inner]) + [r_out, 0.0]
    # arcs, denser outside: gaps shrink linearly from 6 mm at the inner edge to 2 mm outside
    radii, r = [], r_in + 2.0
    while r < r_out - 1.5:
        radii.append(r)
        r += 6.0 - 4.0 * (r - r_in) / (r_out - r_in)
    ribbons = []
    for rr in radii:
        ta = np.linspace(0.05, np.pi - 0.05, 40)
        path = np.column_stack([rr * np.cos(ta) + r_out, rr * np.sin(ta)])
        ribbons.append({"path": path.round(4).tolist(), "width_mm": 1.5, "thickness_mm": 0.4, "side": "front"})
    return {"fabric": {"outline": outline.round(4).tolist(), **FABRIC}, "plastic": PLASTIC, "ribbon": ribbons,
            "mesh": {"size_mm": 2.5, "across": 1}, "solver": {"seed": 0}}


CASES = {
    "tube": lambda: _stars({"rectangle": [50.0, 35.0]}, 0.7),
    "dome": lambda: _held_rim(_stars({"hexagon": 36.0}, "clip(0.75 - 0.45 * r / 36, 0.2, 0.75)", spacing=12.0)),
    "flat_centre": lambda: _held_rim(_stars({"hexagon": 36.0}, "clip(0.3 + 0.45 * r / 36, 0.2, 0.75)", spacing=12.0)),
    "ribbons": lambda: _parallel_ribbons(),
    "ortho_0": lambda: _parallel_ribbons(model="orthotropic", course=0.0),
    "ortho_90": lambda: _parallel_ribbons(model="orthotropic", course=90.0),
    "half_annulus": lambda: _half_annulus(),
}


def _centre_rim(sheet, values, frac=0.25):
    c = sheet.points[sheet.triangles].mean(1)
    r = np.linalg.norm(c - c.mean(0), axis=1)
    R = r.max()
    return float(np.median(values[r < frac * R])), float(np.median(values[r > (1 - frac) * R]))


def _edge_length(x, idx):
    return float(np.sum(np.linalg.norm(np.diff(x[idx], axis=0), axis=1)))


def measure(name, sim) -> dict:
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


def run(names=None, out_root="out/gallery", docs="docs/gallery", examples="examples/gallery", max_iterations=400):
    import tomli_w

    from geometry.patterns import load_pattern
    from forward.outputs import write_vtu
    from forward.simulate import simulate
    os.makedirs(examples, exist_ok=True)
    os.makedirs(docs, exist_ok=True)
    results = {}
    for name in names or list(CASES):
        raw = CASES[name]()
        path = os.path.join(examples, f"{name}.toml")
        with open(path, "wb") as f:
            tomli_w.dump(raw, f)
        t0 = time.perf_counter()
        sim = simulate(load_pattern(path), max_iterations=max_iterations)
        row = {"pattern": path, "converged": bool(sim.result.converged), "newton_iterations": sim.result.iterations,
               "n_vertices": int(sim.sheet.n_vertices), "wall_s": round(time.perf_counter() - t0, 1)}
        row.update(measure(name, sim))
        d = os.path.join(out_root, name)
        os.makedirs(d, exist_ok=True)
        write_vtu(sim, os.path.join(d, "deployed.vtu"))
        try:
            from forward.render import render_deployed
            render_deployed(sim, os.path.join(docs, f"{name}.png"), title=name)
        except Exception as e:  # a picture must not lose the numbers
            row["render_error"] = str(e)
        with open(os.path.join(d, "result.json"), "w") as f:
            json.dump(row, f, indent=2)
        results[name] = row
    return results


CLAIMS = {
    "tube": ("median \\|k_max\\| / \\|k_min\\|", "median_kmax_over_kmin", "> 2: one curvature dominates"),
    "dome": ("Gaussian curvature of the centre fit (1/mm^2)", "gauss_centre_fit", "> 0: dome"),
    "flat_centre": ("\\|mean curvature\\| of the centre fit (1/mm)", "mean_curv_centre_fit", "well below the dome's"),
    "ribbons": ("curvature along / across ribbons", "along_over_across", "> 1: axis across the ribbons"),
    "ortho_0": ("curvature along / across ribbons", "along_over_across", "seed 4.1: one of 0/90 along, one across"),
    "ortho_90": ("curvature along / across ribbons", "along_over_across", "seed 4.1: one of 0/90 along, one across"),
    "half_annulus": ("inner / outer edge length ratio", None, "inner < outer"),
}


def markdown_table(out_root="out/gallery", docs="docs/gallery") -> str:
    """README table of the cases that have a result.json."""
    rows = ["| case | pattern | vertices | Newton it. | converged | measure | value | expected |",
            "|---|---|---|---|---|---|---|---|"]
    imgs = []
    for name, (label, key, expect) in CLAIMS.items():
        p = os.path.join(out_root, name, "result.json")
        if not os.path.exists(p):
            continue
        r = json.load(open(p))
        if key is None:
            value = f"{r['inner_length_ratio']:.3f} / {r['outer_length_ratio']:.3f}"
        else:
            value = f"{r[key]:.3g}"
        imgs.append(f'<img src="{docs}/{name}.png" width="210" alt="{name}">')
        rows.append(f"| {name} | `{r['pattern']}` | {r['n_vertices']} | "
                    f"{r['newton_iterations']} | {r['converged']} | {label} | {value} | {expect} |")
    return "\n".join(rows) + "\n\n" + " ".join(imgs)


def main(argv=None):
    from shellfem.memory import keep_freed_memory
    keep_freed_memory()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", choices=list(CASES))
    ap.add_argument("--max-iterations", type=int, default=400)
    ap.add_argument("--table", action="store_true", help="print the README table of existing results and stop")
    a = ap.parse_args(argv)
    if a.table:
        print(markdown_table())
        return
    print(json.dumps(run(a.only, max_iterations=a.max_iterations)))


if __name__ == "__main__":
    main()
