"""Build the curvature law kappa(thickness, transverse spacing, side) (seed Fig. 5.6-5.7).

Two sources, written as inverse/thickness_law.py CSV tables with a provenance header:

* ``--model sim`` (the law the pipeline is meant to use): forward simulation, in silico
  Fig. 5.6-5.7. For each thickness, transverse spacing mu2 and side, a rectangular patch of
  fabric at the design stretch carries staggered l_r x w_r ribbons (rows mu2 apart along x,
  dashes of length l_r with period mu1, odd rows shifted by mu1 / 2: the stagger of
  inverse/layout.py), is meshed (geometry.meshing.mesh_pattern) and released
  (forward.simulate.simulate_sheet). The curvature along the ribbons is the area-weighted
  mean over the patch's central quarter of the normal curvature in the ribbon direction,
  b(u, u) / a(u, u) with u = the printed x axis (per unit deployed length). Rows whose
  simulation did not converge are dropped and counted, never written.
* ``--model strip`` (a placeholder until the simulated table exists): the uniform-state strip
  model shellfem.strip.strip_curvature, blended by the ribbon coverage fraction
  phi = w_r / mu2 across the rows: kappa = phi kappa_plate + (1 - phi) kappa_narrow (a fully
  covered sheet rolls as a plate, isolated ribbons as narrow strips). A heuristic, labelled so.

Prints ONE JSON line (rows written, dropped, timings). Lengths mm, curvature 1/mm.
The command is studies/thickness_law_sim.py, which calls :func:`main` (kept here with the
builders it drives, so that the law's options are tested with it):

    python studies/thickness_law_sim.py --model strip
    python studies/thickness_law_sim.py --model sim --thickness 0.4 0.8 --spacing 4 8 \
        --sides front --mesh-size 3 --out out/law.csv
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import time
from dataclasses import replace

import numpy as np

from inverse.thickness_law import DEFAULT_LAW, PLASTIC_KEY, format_thickness_law, parse_thickness_law
from shellfem.errors import SelfshapeError
from shellfem.materials import Fabric, Plastic

RIBBON_LENGTH, RIBBON_WIDTH, MU1 = 15.0, 1.5, 22.5      # seed 5.4.1 and Fig. 5.6 (mu1 = 22.5 mm)
THICKNESSES = (0.4, 0.6, 0.8, 1.0, 1.2, 1.4, 1.6)       # mm; thinner plastic is past the curvature peak
SPACINGS = (3.9, 5.0, 6.5, 8.5, 11.0, 15.0)             # mm: sigma2 in [1.3, 1.509] at s = 1.6


def git_hash() -> str:
    try:
        here = os.path.dirname(os.path.abspath(__file__))
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True,
                              text=True, timeout=10).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


# ----------------------------------------------------------------------------- strip model
def strip_rows(thicknesses, spacings, stretch, fabric: Fabric, plastic: Plastic, ribbon_width=RIBBON_WIDTH):
    """Rows (t, mu2, side, kappa) of the coverage-blended uniform-state strip model."""
    from shellfem.strip import strip_curvature

    T, S = np.meshgrid(np.asarray(thicknesses, float), np.asarray(spacings, float), indexing="ij")
    kw = dict(plastic_poisson=plastic.poisson, fabric_poisson=fabric.poisson,
              rest_curvature=plastic.rest_curvature)
    ratio = plastic.young_modulus / fabric.young_modulus
    narrow = strip_curvature(T, fabric.thickness, stretch, ratio, mode="narrow", **kw)
    plate = strip_curvature(T, fabric.thickness, stretch, ratio, mode="plate", **kw)
    phi = np.clip(ribbon_width / S, 0.0, 1.0)
    K = np.abs(phi * plate + (1 - phi) * narrow)
    return [(float(T[i, j]), float(S[i, j]), side, float(K[i, j]))
            for side in ("front", "back") for i in range(T.shape[0]) for j in range(T.shape[1])]


# ----------------------------------------------------------------------------- simulation
def patch_motifs(n_motifs, n_rows, spacing, mu1=MU1) -> int:
    """Dash periods along the patch: at least ``n_motifs`` and enough for the patch to be
    twice as long (along the ribbons) as it is wide, so that it rolls about the axis across
    the ribbons like the seed's cylinders; a patch wider than long can roll the other way
    (measured: 45 x 60 mm patches of 1.2-1.6 mm ribbons at mu2 >= 6.5 mm did)."""
    return max(int(n_motifs), int(np.ceil(2.0 * n_rows * spacing / mu1)))


def patch_pattern(thickness, spacing, side, stretch, *, mu1=MU1, n_rows=6, n_motifs=3, mesh_size=2.0,
                  across=2.0, fabric: Fabric | None = None, plastic: Plastic | None = None, seed=0) -> dict:
    """Pattern dict: a (n_motifs mu1) x (n_rows mu2) fabric rectangle with staggered ribbons
    along x (row r at y = (r + 1/2) mu2, dash centres at (k + 1/2 + (r mod 2)/2) mu1)."""
    fabric = fabric or Fabric()
    plastic = plastic or Plastic()
    n_motifs = patch_motifs(n_motifs, n_rows, spacing, mu1)
    W, H = n_motifs * mu1, n_rows * spacing
    ribbons = []
    for r in range(n_rows):
        y = (r + 0.5) * spacing
        for k in range(-1, n_motifs + 1):
            xc = (k + 0.5 + 0.5 * (r % 2)) * mu1
            x0, x1 = max(xc - RIBBON_LENGTH / 2, 0.0), min(xc + RIBBON_LENGTH / 2, W)
            if x1 - x0 >= 2.0:                      # the layout drops pieces < 2 mm
                ribbons.append({"path": [[x0, y], [x1, y]], "width_mm": RIBBON_WIDTH,
                                "thickness_mm": float(thickness), "side": side})
    return {
        "fabric": {"rectangle": [W, H], "stretch": float(stretch), "thickness_mm": fabric.thickness,
                   "model": fabric.model, "young_modulus_mpa": fabric.young_modulus, "poisson": fabric.poisson,
                   "bending_stiffness_nmm": fabric.bending_stiffness},
        "plastic": {"young_modulus_mpa": plastic.young_modulus, "poisson": plastic.poisson,
                    "rest_curvature_per_mm": plastic.rest_curvature},
        "ribbon": ribbons,
        "mesh": {"size_mm": float(mesh_size), "across": float(across)},
        "solver": {"seed": int(seed)},
    }


def curvature_along_x(sim, box) -> float:
    """Area-weighted mean normal curvature along the printed x axis (1/mm, per deployed length)
    over the faces whose printed centroid lies in box = (x0, y0, x1, y1)."""
    sheet = sim.sheet
    a, b = sim.model.fundamental_forms(sim.result.q)      # edge-basis components (11, 12, 22)
    P = sheet.points[sheet.triangles]
    R = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]], axis=2)   # columns: reference edges
    c = np.linalg.solve(R, np.broadcast_to([1.0, 0.0], (len(R), 2))[..., None])[..., 0]
    quad = lambda s: s[:, 0] * c[:, 0] ** 2 + 2 * s[:, 1] * c[:, 0] * c[:, 1] + s[:, 2] * c[:, 1] ** 2  # noqa: E731
    kx = quad(b) / quad(a)
    cen = P.mean(axis=1)
    inside = (cen[:, 0] >= box[0]) & (cen[:, 0] <= box[2]) & (cen[:, 1] >= box[1]) & (cen[:, 1] <= box[3])
    area = 0.5 * np.abs(np.linalg.det(R))
    return float(np.sum(area[inside] * kx[inside]) / np.sum(area[inside]))


def simulate_row(thickness, spacing, side, stretch, *, mesh_size=2.0, across=2.0, max_iterations=200,
                 n_rows=6, n_motifs=3, seed=0, fabric=None, plastic=None) -> dict:
    """Simulate one patch; returns kappa (magnitude), converged, reason and sizes."""
    from geometry.meshing import mesh_pattern
    from geometry.patterns import load_pattern
    from forward.simulate import simulate_sheet

    raw = patch_pattern(thickness, spacing, side, stretch, n_rows=n_rows, n_motifs=n_motifs, mesh_size=mesh_size,
                        across=across, fabric=fabric, plastic=plastic, seed=seed)
    pat = load_pattern(raw)
    t0 = time.perf_counter()
    sheet = mesh_pattern(pat)
    sim = simulate_sheet(sheet, pat.fabric, pat.plastic, pat.supports, seed=pat.seed, max_iterations=max_iterations)
    W, H = patch_motifs(n_motifs, n_rows, spacing) * MU1, n_rows * spacing
    k = curvature_along_x(sim, (W / 4, H / 4, 3 * W / 4, 3 * H / 4))
    return {"thickness_mm": thickness, "spacing_mm": spacing, "side": side, "kappa_per_mm": abs(k),
            "kappa_signed": k, "converged": bool(sim.result.converged), "reason": sim.result.reason,
            "n_triangles": int(sheet.n_triangles), "newton_iterations": int(sim.result.iterations),
            "time_s": round(time.perf_counter() - t0, 2)}


def read_modulus_ratio(path: str):
    """(modulus_ratio, standard error, data file) from a `selfshape calibrate strips` parameters.json;
    SystemExit with one line if the file is missing or is not one."""
    try:
        with open(path) as f:
            p = json.load(f)
        ratio, se = (float(v) for v in p["modulus_ratio"])
    except FileNotFoundError:
        raise SystemExit(f"thickness_law_sim: {path}: file not found") from None
    except (OSError, ValueError, KeyError, TypeError):
        raise SystemExit(f"thickness_law_sim: {path}: not a `selfshape calibrate strips` parameters.json "
                         "(needs modulus_ratio [value, standard error])") from None
    if not (np.isfinite(ratio) and ratio > 0):
        raise SystemExit(f"thickness_law_sim: {path}: modulus_ratio must be > 0, got {ratio:g}")
    return ratio, se, p.get("fit", {}).get("data", "?")


# ----------------------------------------------------------------------------- main
def main(argv=None):
    from shellfem.memory import keep_freed_memory
    keep_freed_memory()
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", choices=["strip", "sim"], default="strip")
    ap.add_argument("--stretch", type=float, default=1.6)
    ap.add_argument("--thickness", type=float, nargs="+", default=list(THICKNESSES))
    ap.add_argument("--spacing", type=float, nargs="+", default=list(SPACINGS))
    ap.add_argument("--sides", nargs="+", choices=["front", "back"], default=["front", "back"])
    ap.add_argument("--mesh-size", type=float, default=1.0, help="fabric edge length, mm (sim)")
    ap.add_argument("--across", type=float, default=2.0, help="triangle rows across a ribbon (sim)")
    ap.add_argument("--rows", type=int, default=6, help="ribbon rows in the patch (sim)")
    ap.add_argument("--motifs", type=int, default=3, help="dash periods along the patch (sim)")
    ap.add_argument("--max-iterations", type=int, default=200)
    ap.add_argument("--back", choices=["simulate", "mirror"], default="simulate",
                    help="back-side rows: simulate each, or copy the front rows (the model is mirror-symmetric "
                         "through the fabric mid-surface without gravity) after one simulated check row (sim)")
    ap.add_argument("--from-json", default=None,
                    help="reuse the simulated rows of an earlier run's JSON line instead of simulating (sim)")
    ap.add_argument("--table-thickness", type=float, nargs="+", default=None,
                    help="thicknesses written to the table (default: all simulated); the rest stay in the provenance")
    ap.add_argument("--table-spacing", type=float, nargs="+", default=None,
                    help="spacings written to the table (default: all simulated)")
    ap.add_argument("--calibration", default=None,
                    help="parameters.json of `selfshape calibrate strips` (measured strips): the plastic's Young's "
                         "modulus = its modulus_ratio x the fabric's (default: the seed's Table 4.1 plastic)")
    ap.add_argument("--out", default=None, help=f"output CSV (default {DEFAULT_LAW})")
    a = ap.parse_args(argv)
    out = a.out or DEFAULT_LAW
    fabric, plastic = Fabric(), Plastic()
    plastic_source = "seed Table 4.1 defaults"
    if a.calibration:
        ratio, se, data = read_modulus_ratio(a.calibration)
        plastic = replace(plastic, young_modulus=ratio * fabric.young_modulus)
        plastic_source = (f"E = modulus_ratio {ratio:.1f} +- {se:.1f} x fabric E, from {os.path.basename(a.calibration)} "
                          f"(selfshape calibrate strips on {data})")
    t0 = time.perf_counter()
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    head = [f"selfshape curvature law kappa(thickness, transverse spacing, side) at fabric stretch {a.stretch:g}",
            "columns: thickness_mm (printed plastic, mm), spacing_mm (transverse ribbon spacing mu2, printed mm),",
            "  side (front|back), kappa_per_mm (|normal curvature| along the ribbons, 1/mm of deployed length)",
            f"generated {stamp} by studies/thickness_law_sim.py --model {a.model}, git {git_hash()}",
            f"fabric: E {fabric.young_modulus:g} MPa, nu {fabric.poisson:g}, thickness {fabric.thickness:g} mm, "
            f"k_B {fabric.bending_stiffness:g} N mm ({fabric.model}); plastic: E {plastic.young_modulus:g} MPa, "
            f"nu {plastic.poisson:g}, rest curvature {plastic.rest_curvature:g} /mm ({plastic_source})",
            f"ribbons {RIBBON_LENGTH:g} x {RIBBON_WIDTH:g} mm",
            f"{PLASTIC_KEY} = {plastic.young_modulus:.6g}"]
    dropped, log = [], []
    if a.model == "strip":
        rows = [r for r in strip_rows(a.thickness, a.spacing, a.stretch, fabric, plastic) if r[2] in a.sides]
        head += ["SOURCE: uniform-state strip model (shellfem.strip.strip_curvature), NOT a simulation of",
                 "  ribbon sheets: kappa = phi kappa_plate + (1 - phi) kappa_narrow, phi = w_r / spacing (ribbon",
                 "  coverage across the rows). A heuristic placeholder so the pipeline works before the",
                 "  simulated table exists; front and back are identical in this model."]
    else:
        rows = []
        previous = {}
        if a.from_json:
            try:
                with open(a.from_json) as f:
                    loaded = json.load(f)["rows"]
            except (OSError, ValueError, KeyError, TypeError) as e:
                raise SystemExit(f"thickness_law_sim: {a.from_json}: cannot read its rows "
                                 f"({type(e).__name__}: {str(e)[:80]})") from None
            for r in loaded:
                previous[(float(r["thickness_mm"]), float(r["spacing_mm"]), r["side"])] = r

        def run_row(t, mu, side, *args, **kw):           # simulate, or reuse a previous run's row
            if a.from_json:
                if (t, mu, side) not in previous:
                    raise SystemExit(f"thickness_law_sim: {a.from_json} has no row t={t:g} mu2={mu:g} {side}")
                return previous[(t, mu, side)]
            return simulate_row(t, mu, side, *args, **kw)
        mirror = a.back == "mirror" and "back" in a.sides
        simulated_sides = [sd for sd in a.sides if not (mirror and sd == "back")]
        for side in simulated_sides:
            for t in a.thickness:
                for mu in a.spacing:
                    r = run_row(t, mu, side, a.stretch, mesh_size=a.mesh_size, across=a.across,
                                max_iterations=a.max_iterations, n_rows=a.rows, n_motifs=a.motifs,
                                fabric=fabric, plastic=plastic)
                    log.append(r)
                    if r["converged"] and np.isfinite(r["kappa_per_mm"]):
                        rows.append((t, mu, side, r["kappa_per_mm"]))
                    else:
                        dropped.append(r)
        mirror_note = []
        if mirror:
            front = {(t, mu): k for t, mu, sd, k in rows if sd == "front"}
            if not front:
                raise SystemExit("thickness_law_sim: --back mirror needs converged front rows")
            t_c, mu_c = sorted(front)[len(front) // 2]
            chk = run_row(t_c, mu_c, "back", a.stretch, mesh_size=a.mesh_size, across=a.across,
                          max_iterations=a.max_iterations, n_rows=a.rows, n_motifs=a.motifs,
                          fabric=fabric, plastic=plastic)
            log.append(chk)
            rel = abs(chk["kappa_per_mm"] - front[(t_c, mu_c)]) / front[(t_c, mu_c)]
            mirror_note = [f"  back rows = front rows by mirror symmetry through the fabric mid-surface (no gravity);",
                           f"  check: back simulated at t={t_c:g} mu2={mu_c:g}: |kappa| {chk['kappa_per_mm']:.6g} vs front "
                           f"{front[(t_c, mu_c)]:.6g} (relative difference {rel:.1e}, converged={chk['converged']})"]
            if not chk["converged"] or rel > 1e-3:
                # the model is exactly mirror-symmetric; a difference means the (unmirrored) seeded
                # perturbation led the back patch to another equilibrium: say so, keep the rows
                mirror_note.append("  the check landed in a different equilibrium of the same patch (the seeded "
                                   "perturbation is not mirrored): the patch has more than one stable shape here")
            rows += [(t, mu, "back", k) for (t, mu), k in front.items()]
        head += ["SOURCE: forward simulation of parallel staggered ribbon sheets (forward.simulate.simulate_sheet):",
                 f"  patch max({a.motifs}, ceil(2 rows mu2 / mu1)) x mu1 along (at least twice its width), {a.rows} rows across, mu1 {MU1:g} mm, "
                 f"odd rows shifted mu1/2; mesh size {a.mesh_size:g} mm, {a.across:g} rows across a ribbon;",
                 "  kappa = area-weighted mean of b(x,x)/a(x,x) over the central quarter of the patch.",
                 f"  rows simulated {len(log)}, not converged (dropped, not written) {len(dropped)}"] + mirror_note
        for r in log:
            head.append(f"  row t={r['thickness_mm']:g} mu2={r['spacing_mm']:g} {r['side']}: "
                        f"converged={r['converged']} ({r['reason']}), {r['newton_iterations']} Newton it., "
                        f"{r['n_triangles']} triangles, {r['time_s']:g} s")
    if a.model == "sim" and (a.table_thickness or a.table_spacing):
        tt = set(a.table_thickness or a.thickness)
        ts = set(a.table_spacing or a.spacing)
        left = [r for r in rows if not (r[0] in tt and r[1] in ts)]
        rows = [r for r in rows if r[0] in tt and r[1] in ts]
        head += [f"  TABLE: the sub-grid thickness {sorted(tt)} x spacing {sorted(ts)} mm; simulated rows left out:"]
        head += [f"    t={t:g} mu2={mu:g} {sd}: kappa {k:.4g}" for t, mu, sd, k in left]
    text = format_thickness_law(rows, head)
    summary = {"law": a.model, "out": out, "rows_written": len(rows), "rows_dropped": len(dropped),
               "time_s": round(time.perf_counter() - t0, 2),
               "rows": [{k: r[k] for k in ("thickness_mm", "spacing_mm", "side", "kappa_per_mm", "converged",
                                           "reason", "newton_iterations", "n_triangles", "time_s")} for r in log]}
    try:
        parse_thickness_law(text, out)    # never write a table the pipeline cannot load
    except SelfshapeError as e:
        summary.update(rows_written=0, error=str(e))
        print(json.dumps(summary))
        return 1
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    tmp = out + ".tmp"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, out)
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
