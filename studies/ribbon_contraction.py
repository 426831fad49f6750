"""Issue 18 "Contraction model": the in-plane contraction of simulated parallel-ribbon patches
against Eq. 5.15 (inverse/spacing.py) and the flattening's bounds (stretch_bounds).

Each patch is validation.law_tables.patch_pattern (staggered 15 x 1.5 mm dashes, mu1 = 22.5 mm,
rows mu2 apart along x) released by forward.simulate.simulate_sheet with the plastic of
``--calibration`` (default the shipped inverse/data/strips_S1_calibration.json). The effective
stretch is measured intrinsically, so that the patch's bending does not enter: with a = the
deployed first fundamental form in printed coordinates (model.cartesian_forms), a printed length
dX along x deploys to sqrt(a_xx) dX, so over the central box (printed W/4..3W/4 x H/4..3H/4, a
whole number of motifs when rows and motifs are even)

    sigma_along  = 1 / mean_area(sqrt(a_xx))     (printed / deployed, along the ribbons: sigma1)
    sigma_across = 1 / mean_area(sqrt(a_yy))     (across them: sigma2)

(the printed / deployed length of straight printed lines, averaged over the box). The same over
the bare-fabric triangles only (region 0) and over the plastic ones shows where the contraction
happens. --both-sides prints each ribbon on the front and the back: the patch cannot bend, so
its contraction is the in-plane one alone (what Eq. 5.15 models). Also a chord check: deployed / printed distance between the vertices nearest the box's
edge midpoints (includes the bending, so it is <= the intrinsic value).

    OMP_NUM_THREADS=1 python studies/ribbon_contraction.py --thickness 0.2 0.3 0.4 --spacing 3.9 6.5 \
        --rows 6 --motifs 4 --mesh-size 3 --across 1 --out out/contraction.json

Prints one JSON line per patch and writes all rows with the command and git hash to --out.
Lengths mm.
"""
from __future__ import annotations

import argparse
import datetime
import itertools
import json
import os
import sys
import time
from dataclasses import replace

import numpy as np

from inverse.spacing import stretch_from_spacing
from validation.law_tables import MU1, RIBBON_LENGTH, RIBBON_WIDTH, git_hash, patch_pattern, read_modulus_ratio

DEFAULT_CALIBRATION = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "inverse", "data",
                                   "strips_S1_calibration.json")


def intrinsic_stretch(sim, box, mask=None) -> tuple[float, float]:
    """(sigma_along, sigma_across) = 1 / area-mean sqrt(a_xx), 1 / area-mean sqrt(a_yy) over the
    triangles whose printed centroid lies in box (x0, y0, x1, y1) (and ``mask``)."""
    a, _ = sim.model.cartesian_forms(sim.result.q)
    P = sim.sheet.points[sim.sheet.triangles]
    cen = P.mean(axis=1)
    inside = (cen[:, 0] >= box[0]) & (cen[:, 0] <= box[2]) & (cen[:, 1] >= box[1]) & (cen[:, 1] <= box[3])
    if mask is not None:
        inside &= mask
    e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    w = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])[inside]
    w = w / w.sum()
    return (float(1.0 / np.sum(w * np.sqrt(a[inside, 0, 0]))), float(1.0 / np.sum(w * np.sqrt(a[inside, 1, 1]))))


def chord_stretch(sim, box) -> tuple[float, float]:
    """printed / deployed straight distance between the vertices nearest the midpoints of the
    box's left and right (along) and bottom and top (across) edges."""
    X = sim.sheet.points
    x = sim.positions
    xm, ym = 0.5 * (box[0] + box[2]), 0.5 * (box[1] + box[3])
    near = lambda p: int(np.argmin(np.sum((X - p) ** 2, axis=1)))  # noqa: E731
    out = []
    for p, q in (((box[0], ym), (box[2], ym)), ((xm, box[1]), (xm, box[3]))):
        i, j = near(np.array(p)), near(np.array(q))
        out.append(float(np.linalg.norm(X[i] - X[j]) / np.linalg.norm(x[i] - x[j])))
    return out[0], out[1]


def run_patch(t, mu2, stretch, plastic, *, rows, motifs, mesh_size, across, max_iterations, side="front", mu1=MU1, both_sides=False):
    from forward.simulate import simulate_sheet
    from geometry.meshing import mesh_pattern
    from geometry.patterns import load_pattern
    from validation.law_tables import curvature_state, patch_motifs

    raw = patch_pattern(t, mu2, side, stretch, mu1=mu1, n_rows=rows, n_motifs=motifs, mesh_size=mesh_size, across=across,
                        aspect=0.0, plastic=plastic)
    if both_sides:          # the same ribbons on the back too: no bending moment, in-plane contraction only
        raw["ribbon"] += [dict(r, side="back") for r in raw["ribbon"]]
        side = "both"
    pat = load_pattern(raw)
    t0 = time.perf_counter()
    sheet = mesh_pattern(pat)
    sim = simulate_sheet(sheet, pat.fabric, pat.plastic, pat.supports, seed=pat.seed, max_iterations=max_iterations)
    n_m = patch_motifs(motifs, rows, mu2, mu1, aspect=0.0)
    W, H = n_m * mu1, rows * mu2
    box = (W / 4, H / 4, 3 * W / 4, 3 * H / 4)
    s_al, s_ac = intrinsic_stretch(sim, box)
    bare = sheet.region == 0
    f_al, f_ac = intrinsic_stretch(sim, box, bare)
    p_al, p_ac = intrinsic_stretch(sim, box, ~bare)
    c_al, c_ac = chord_stretch(sim, box)
    e1, e2 = stretch_from_spacing(mu1, mu2, stretch, RIBBON_LENGTH, RIBBON_WIDTH)
    st = curvature_state(sim, box)
    return {"thickness_mm": t, "spacing_mm": mu2, "side": side, "both_sides": bool(both_sides), "mu1_mm": mu1, "stretch": stretch,
            "rows": rows, "motifs": n_m, "patch_mm": [W, H], "mesh_size_mm": mesh_size, "across": across,
            "n_triangles": int(sheet.n_triangles), "converged": bool(sim.result.converged),
            "reason": sim.result.reason, "newton_iterations": int(sim.result.iterations),
            "time_s": round(time.perf_counter() - t0, 2),
            "sigma_along": round(s_al, 4), "sigma_across": round(s_ac, 4),
            "eq515_sigma1": round(float(e1), 4), "eq515_sigma2": round(float(e2), 4),
            "sigma_along_bare_fabric": round(f_al, 4), "sigma_across_bare_fabric": round(f_ac, 4),
            "sigma_along_plastic": round(p_al, 4), "sigma_across_plastic": round(p_ac, 4),
            "chord_sigma_along": round(c_al, 4), "chord_sigma_across": round(c_ac, 4),
            "kappa_along_per_mm": round(st["kappa_along_signed"], 4), "k1_per_mm": round(st["k1_per_mm"], 4),
            "k1_angle_deg": st["k1_angle_deg"]}


def main(argv=None):
    from shellfem.materials import Fabric, Plastic

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--thickness", type=float, nargs="+", default=[0.2, 0.3, 0.4])
    ap.add_argument("--spacing", type=float, nargs="+", default=[3.9, 6.5])
    ap.add_argument("--mu1", type=float, nargs="+", default=[MU1], help="dash periods along, mm")
    ap.add_argument("--both-sides", action="store_true",
                    help="print every ribbon on the front and the back (symmetric: the patch stays flat)")
    ap.add_argument("--stretch", type=float, default=1.6)
    ap.add_argument("--rows", type=int, default=6)
    ap.add_argument("--motifs", type=int, default=4)
    ap.add_argument("--mesh-size", type=float, default=3.0)
    ap.add_argument("--across", type=float, default=1.0)
    ap.add_argument("--max-iterations", type=int, default=1000)
    ap.add_argument("--calibration", default=DEFAULT_CALIBRATION)
    ap.add_argument("--out", default=None, help="JSON file with all rows, the command and the git hash")
    ap.add_argument("--append", action="store_true", help="add the rows to an existing --out file")
    ap.add_argument("--from-json", nargs="+", default=None,
                    help="no simulation: read the rows of these --out files (for --table)")
    ap.add_argument("--table", default=None,
                    help="write the contraction table (inverse.contraction format) of the converged one-sided "
                         "rows at --stretch and the first --thickness to this CSV")
    a = ap.parse_args(argv)
    if a.from_json:
        rows = []
        for path in a.from_json:
            with open(path) as f:
                rows += json.load(f)["rows"]
        if a.table:
            write_table(a.table, rows, a.stretch, a.thickness[0], a.from_json)
        return 0
    fabric = Fabric()
    ratio, se, _ = read_modulus_ratio(a.calibration)
    plastic = replace(Plastic(), young_modulus=ratio * fabric.young_modulus)
    cmd = "python studies/ribbon_contraction.py " + " ".join(argv if argv is not None else sys.argv[1:])
    rows = []
    for mu1, mu2, t in itertools.product(a.mu1, a.spacing, a.thickness):
        r = run_patch(t, mu2, a.stretch, plastic, rows=a.rows, motifs=a.motifs, mesh_size=a.mesh_size,
                      across=a.across, max_iterations=a.max_iterations, mu1=mu1,
                      both_sides=a.both_sides)
        r["command"] = cmd
        print(json.dumps(r), flush=True)
        rows.append(r)
    if a.out:
        doc = {"what": "intrinsic in-plane stretch (printed / deployed) of simulated staggered-ribbon patches vs "
                       "Eq. 5.15 (studies/ribbon_contraction.py)",
               "plastic_young_modulus_mpa": plastic.young_modulus,
               "git": git_hash(), "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
               "rows": []}
        if a.append and os.path.exists(a.out):
            with open(a.out) as f:
                doc["rows"] = json.load(f)["rows"]
        doc["rows"] += rows
        os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
        with open(a.out, "w") as f:
            json.dump(doc, f, indent=1)
            f.write("\n")
    if a.table:
        write_table(a.table, rows, a.stretch, a.thickness[0], [a.out or "(this run)"])
    return 0


def write_table(path, rows, stretch, thickness, sources):
    """The inverse.contraction table of the converged one-sided rows at (stretch, thickness)."""
    from inverse.contraction import format_contraction, parse_contraction
    keep = [r for r in rows if r.get("converged") and not r.get("both_sides") and r.get("side", "front") == "front"
            and abs(r["stretch"] - stretch) < 1e-9 and abs(r["thickness_mm"] - thickness) < 1e-9]
    data = sorted({(float(r["mu1_mm"]), float(r["spacing_mm"])): (float(r["sigma_along"]), float(r["sigma_across"]))
                   for r in keep}.items())
    head = ["selfshape contraction table: homogenised stretch (printed / deployed length) of staggered dashed-ribbon",
            "patches (studies/ribbon_contraction.py: intrinsic, over the patch's central quarter) against the dash",
            "period mu1 and row spacing mu2 (printed mm); sigma1 along the ribbons, sigma2 across",
            f"rows from {', '.join(os.path.basename(str(x)) for x in sources)}, git {git_hash()}",
            f"fabric_stretch = {stretch:g}", f"ribbon_length_mm = {RIBBON_LENGTH:g}",
            f"ribbon_width_mm = {RIBBON_WIDTH:g}", f"thickness_mm = {thickness:g}"]
    text = format_contraction([(k[0], k[1], v[0], v[1]) for k, v in data], head)
    m = parse_contraction(text, path)          # refuses a table the design could not use
    with open(path, "w") as f:
        f.write(text)
    print(f"{path}: {len(data)} patches, fit rms {m.rms[0]:.4f} / {m.rms[1]:.4f}, "
          f"polygon {np.round(m.bounds(), 3).tolist()}", flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
