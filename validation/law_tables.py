"""Build the curvature law kappa(thickness, transverse spacing, side) (seed Fig. 5.6-5.7).

Two sources, written as inverse/thickness_law.py CSV tables with a provenance header:

* ``--model sim`` (the law the pipeline is meant to use): forward simulation, in silico
  Fig. 5.6-5.7. For each thickness, transverse spacing mu2 and side, a rectangular patch of
  fabric at the design stretch carries staggered l_r x w_r ribbons (rows mu2 apart along x,
  dashes of length l_r with period mu1, odd rows shifted by mu1 / 2: the stagger of
  inverse/layout.py), is meshed (geometry.meshing.mesh_pattern) and released
  (forward.simulate.simulate_sheet). The curvature along the ribbons is the area-weighted
  mean over the patch's central quarter of the normal curvature in the ribbon direction,
  b(u, u) / a(u, u) with u = the printed x axis (per unit deployed length); each row also
  records the curvature across the ribbons and the principal curvatures and direction
  (curvature_state), so that a patch that bends across the ribbons is seen as such. A patch
  can start rolled along (or across) the ribbons (--start-curvature) to pick a branch where
  it is multistable. Rows whose simulation did not converge are dropped and counted, never
  written.
* ``--model strip`` (a placeholder until the simulated table exists): the uniform-state strip
  model shellfem.strip.strip_curvature, blended by the ribbon coverage fraction
  phi = w_r / mu2 across the rows: kappa = phi kappa_plate + (1 - phi) kappa_narrow (a fully
  covered sheet rolls as a plate, isolated ribbons as narrow strips). A heuristic, labelled so.

Prints ONE JSON line (rows written, dropped, timings). Lengths mm, curvature 1/mm.
``--workers N`` / ``--scheduler ADDRESS`` simulate the patches as Dask tasks (shellfem.cluster:
a local cluster of N single-threaded processes, or a running scheduler's workers); the rows
and the table are those of the serial default, in the same order.
The command is studies/thickness_law_sim.py, which calls :func:`main` (kept here with the
builders it drives, so that the law's options are tested with it):

    python studies/thickness_law_sim.py --model strip
    python studies/thickness_law_sim.py --model sim --thickness 0.4 0.8 --spacing 4 8 \
        --sides front --mesh-size 3 --out out/law.csv
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np

from inverse.thickness_law import DEFAULT_LAW, PLASTIC_KEY, STRETCH_KEY, format_thickness_law, parse_thickness_law
from shellfem.errors import SelfshapeError
from shellfem.materials import Fabric, Plastic

RIBBON_LENGTH, RIBBON_WIDTH, MU1 = 15.0, 1.5, 22.5      # seed 5.4.1 and Fig. 5.6 (mu1 = 22.5 mm)
THICKNESSES = (0.4, 0.6, 0.8, 1.0, 1.2, 1.4, 1.6)       # mm; thinner plastic is past the curvature peak
SPACINGS = (3.9, 5.0, 6.5, 8.5, 11.0, 15.0)             # mm: sigma2 in [1.3, 1.509] at s = 1.6


#: the keys of a row in the JSON line (the first ones are what --from-json needs), then the curvature state
ROW_KEYS = ("thickness_mm", "spacing_mm", "side", "kappa_per_mm", "converged", "reason", "newton_iterations",
            "n_triangles", "time_s")
EXTRA_ROW_KEYS = ("kappa_across_per_mm", "kappa_along_signed", "kappa_across_signed", "k1_per_mm", "k2_per_mm",
                  "k1_angle_deg", "gaussian_per_mm2", "sigma_along", "sigma_across", "stable", "energy_nmm", "rows",
                  "motifs", "patch_mm", "start_curvature_per_mm", "start_direction")


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
def patch_motifs(n_motifs, n_rows, spacing, mu1=MU1, aspect=2.0) -> int:
    """Dash periods along the patch: at least ``n_motifs`` and enough for the patch to be
    twice as long (along the ribbons) as it is wide, so that it rolls about the axis across
    the ribbons like the seed's cylinders; a patch wider than long can roll the other way
    (measured: 45 x 60 mm patches of 1.2-1.6 mm ribbons at mu2 >= 6.5 mm did)."""
    return max(int(n_motifs), int(np.ceil(aspect * n_rows * spacing / mu1)))


def patch_pattern(thickness, spacing, side, stretch, *, mu1=MU1, n_rows=6, n_motifs=3, mesh_size=2.0,
                  across=2.0, aspect=2.0, fabric: Fabric | None = None, plastic: Plastic | None = None, seed=0) -> dict:
    """Pattern dict: a (n_motifs mu1) x (n_rows mu2) fabric rectangle with staggered ribbons
    along x (row r at y = (r + 1/2) mu2, dash centres at (k + 1/2 + (r mod 2)/2) mu1)."""
    fabric = fabric or Fabric()
    plastic = plastic or Plastic()
    n_motifs = patch_motifs(n_motifs, n_rows, spacing, mu1, aspect)
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


def curvature_state(sim, box) -> dict:
    """The deployed patch's curvature over the faces whose printed centroid lies in box =
    (x0, y0, x1, y1), all per deployed length (1/mm): area-weighted mean normal curvature along
    the ribbons (printed x, = curvature_along_x) and across them (printed y); the principal
    curvatures of the box's mean forms (k1 the larger in magnitude) with the angle of k1's
    direction from the ribbons (printed coordinates, degrees in [0, 90]: 0 = bent along the
    ribbons, 90 = bent across them); the area-weighted mean Gaussian curvature (1/mm^2); and the
    in-plane contraction printed / deployed length along and across the ribbons, 1 / area-mean
    sqrt(a_xx) and 1 / area-mean sqrt(a_yy) (intrinsic, so the bending does not enter; the
    ``contraction_*`` columns a lab measures on a calibration patch, validation.calibration_prints)."""
    from scipy.linalg import eigh
    a, b = sim.model.cartesian_forms(sim.result.q)         # (m, 2, 2) in printed (X, Y)
    P = sim.sheet.points[sim.sheet.triangles]
    cen = P.mean(axis=1)
    inside = (cen[:, 0] >= box[0]) & (cen[:, 0] <= box[2]) & (cen[:, 1] >= box[1]) & (cen[:, 1] <= box[3])
    e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    w = area[inside] / area[inside].sum()
    a, b = a[inside], b[inside]
    mean = lambda v: float(np.sum(w * v))                  # noqa: E731
    kx, ky = mean(b[:, 0, 0] / a[:, 0, 0]), mean(b[:, 1, 1] / a[:, 1, 1])
    gauss = mean(np.linalg.det(b) / np.linalg.det(a))
    A, B = np.einsum("m,mij->ij", w, a), np.einsum("m,mij->ij", w, b)
    k, v = eigh(0.5 * (B + B.T), 0.5 * (A + A.T))
    i = int(np.argmax(np.abs(k)))
    angle = float(np.degrees(np.arctan2(abs(v[1, i]), abs(v[0, i]))))
    return {"kappa_along_signed": kx, "kappa_across_signed": ky, "k1_per_mm": float(k[i]),
            "k2_per_mm": float(k[1 - i]), "k1_angle_deg": round(angle, 2), "gaussian_per_mm2": gauss,
            "sigma_along": 1.0 / mean(np.sqrt(a[:, 0, 0])), "sigma_across": 1.0 / mean(np.sqrt(a[:, 1, 1]))}


def rolled_start(points, curvature, seed=0, direction="along") -> np.ndarray:
    """Start positions (n, 3): the printed patch rolled isometrically to ``curvature`` (1/mm of
    printed length), centred on the patch, plus the seeded 1 % perturbation of the flat start.
    direction "along": the ribbons bent (generators along printed y); "across": the ribbons
    straight, bent across them (generators along x)."""
    from shellfem.boundary import smooth_perturbation
    u, v = (0, 1) if direction == "along" else (1, 0)
    X = points[:, u]
    xc = 0.5 * (X.min() + X.max())
    size = float(np.linalg.norm(points.max(0) - points.min(0)))
    out = np.zeros((len(points), 3))
    out[:, v] = points[:, v]
    if curvature == 0:
        out[:, u] = X
    else:
        R = 1.0 / curvature
        out[:, u], out[:, 2] = xc + R * np.sin((X - xc) / R), R * (1 - np.cos((X - xc) / R))
    out[:, 2] += smooth_perturbation(points, seed, 0.01 * size)
    return out


def simulate_row(thickness, spacing, side, stretch, *, mesh_size=2.0, across=2.0, max_iterations=200,
                 n_rows=6, n_motifs=3, aspect=2.0, seed=0, fabric=None, plastic=None, start_curvature=0.0,
                 start_direction="along", shape_png=None) -> dict:
    """Simulate one patch; returns kappa (magnitude along the ribbons), converged, reason, sizes
    and the curvature state over the central quarter (curvature_state: along, across, principal).
    ``start_curvature`` (1/mm, printed; a magnitude, the roll bends the plastic side convex as the
    patch curls): start rolled along the ribbons (or across them: ``start_direction``;
    rolled_start) instead of from the perturbed flat state (0, the
    default). ``shape_png``: write the deployed shape."""
    from geometry.meshing import mesh_pattern
    from geometry.patterns import load_pattern
    from forward.simulate import simulate_sheet

    raw = patch_pattern(thickness, spacing, side, stretch, n_rows=n_rows, n_motifs=n_motifs, mesh_size=mesh_size,
                        across=across, aspect=aspect, fabric=fabric, plastic=plastic, seed=seed)
    pat = load_pattern(raw)
    t0 = time.perf_counter()
    sheet = mesh_pattern(pat)
    # the roll's sense: the plastic side convex, as the patch curls (front: centre of curvature on -z)
    signed = -abs(start_curvature) if side == "front" else abs(start_curvature)
    start = rolled_start(sheet.points, signed, pat.seed, start_direction) if start_curvature else None
    sim = simulate_sheet(sheet, pat.fabric, pat.plastic, pat.supports, seed=pat.seed, max_iterations=max_iterations,
                         start=start)
    n_motifs = patch_motifs(n_motifs, n_rows, spacing, aspect=aspect)
    W, H = n_motifs * MU1, n_rows * spacing
    box = (W / 4, H / 4, 3 * W / 4, 3 * H / 4)
    k = curvature_along_x(sim, box)
    state = curvature_state(sim, box)
    row = {"thickness_mm": thickness, "spacing_mm": spacing, "side": side, "kappa_per_mm": abs(k),
           "kappa_signed": k, "converged": bool(sim.result.converged), "reason": sim.result.reason,
           "n_triangles": int(sheet.n_triangles), "newton_iterations": int(sim.result.iterations),
           "time_s": round(time.perf_counter() - t0, 2),
           "kappa_across_per_mm": abs(state["kappa_across_signed"]), **state,
           "stable": bool(sim.result.stable), "energy_nmm": float(sim.result.energy),
           "rows": int(n_rows), "motifs": int(n_motifs), "patch_mm": [W, H],
           "start_curvature_per_mm": float(start_curvature),
           "start_direction": start_direction if start_curvature else "flat"}
    if shape_png:
        from forward.render import render_deployed
        os.makedirs(os.path.dirname(os.path.abspath(shape_png)), exist_ok=True)
        render_deployed(sim, shape_png, title=f"t {thickness:g} mm, mu2 {spacing:g} mm, {side}, {n_rows} rows x "
                        f"{n_motifs} motifs: along {k:+.4f}, across {state['kappa_across_signed']:+.4f} /mm")
    return row


def simulate_row_task(call: dict) -> dict:
    """``simulate_row(**call)``: one patch as a task of shellfem.cluster.map_tasks (module level,
    so that Dask workers import it by name)."""
    return simulate_row(**call)


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
def main(argv=None, status=None):
    """The command line of studies/thickness_law_sim.py (see the module doc); returns the exit
    status. ``status(enabled)`` makes the progress callback of the simulated patches (events
    {"stage": "tasks", "done", "total", "unit": "patches", "last"}, and a ``close()``), e.g. a
    terminal status line from the script above this layer; ``enabled`` is False under --quiet."""
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
    ap.add_argument("--min-aspect", type=float, default=2.0,
                    help="more motifs if needed for the patch to be this many times as long as wide (sim)")
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
    ap.add_argument("--start-curvature", type=float, default=0.0,
                    help="start each patch rolled along the ribbons to this curvature (1/mm, printed) instead of "
                         "the perturbed flat state (0, default): picks the along-the-ribbons branch where the patch "
                         "is multistable (sim)")
    ap.add_argument("--start-direction", choices=["along", "across"], default="along",
                    help="the roll of --start-curvature: the ribbons bent (along, default) or straight (across) (sim)")
    ap.add_argument("--rows-json", default=None,
                    help="also write the JSON line (all simulated rows, with the command and git hash) to this file (sim)")
    ap.add_argument("--shapes", default=None, help="write each simulated row's deployed shape as a PNG in this folder (sim)")
    ap.add_argument("--note", action="append", default=[],
                    help="a line of free text added to the provenance header (repeatable)")
    ap.add_argument("--out", default=None, help=f"output CSV (default {DEFAULT_LAW})")
    ap.add_argument("--scheduler", default=None,
                    help="simulate the patches as Dask tasks on this running scheduler, e.g. tcp://host:8786 (sim)")
    ap.add_argument("--workers", type=int, default=None,
                    help="simulate the patches on a local Dask cluster of this many processes (sim; default: "
                         "serially in this process; shellfem.cluster)")
    ap.add_argument("-q", "--quiet", action="store_true", help="no progress line on a terminal (sim)")
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
            f"{PLASTIC_KEY} = {plastic.young_modulus:.6g}",
            f"{STRETCH_KEY} = {a.stretch:g}"]
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

        def row_call(t, mu, side, *args, **kw):
            png = (os.path.join(a.shapes, f"t{t:g}_mu{mu:g}_{side}_r{a.rows}_m{a.motifs}_s{a.start_curvature:g}{a.start_direction[:2]}.png")
                   if a.shapes else None)
            return dict(thickness=t, spacing=mu, side=side, stretch=args[0], start_curvature=a.start_curvature,
                        start_direction=a.start_direction, shape_png=png, **kw)

        distributed = (a.scheduler is not None or a.workers is not None) and not a.from_json
        mapped = {}

        def run_row(t, mu, side, *args, **kw):           # simulate, or reuse a previous run's row
            if a.from_json:
                if (t, mu, side) not in previous:
                    raise SystemExit(f"thickness_law_sim: {a.from_json} has no row t={t:g} mu2={mu:g} {side}")
                return previous[(t, mu, side)]
            if (t, mu, side) in mapped:
                return mapped[(t, mu, side)]
            if distributed:                              # the mirror check row: one more task
                return map_rows([row_call(t, mu, side, *args, **kw)])[0]
            return patch_done(simulate_row_task(row_call(t, mu, side, *args, **kw)))
        mirror = a.back == "mirror" and "back" in a.sides
        simulated_sides = [sd for sd in a.sides if not (mirror and sd == "back")]
        # progress: patches done / total (the grid, and the mirror's check row)
        progress = status(not a.quiet) if status is not None and not a.from_json else None
        n_patches = len(simulated_sides) * len(a.thickness) * len(a.spacing) + mirror
        finished = [0]

        def patch_done(r):
            finished[0] += 1
            if progress is not None:
                progress({"stage": "tasks", "done": finished[0], "total": n_patches, "unit": "patches",
                          "last": f"t {r['thickness_mm']:g} mu2 {r['spacing_mm']:g} {r['side']}"})
            return r
        common = dict(mesh_size=a.mesh_size, across=a.across, max_iterations=a.max_iterations, n_rows=a.rows,
                      n_motifs=a.motifs, aspect=a.min_aspect, fabric=fabric, plastic=plastic)
        cluster = contextlib.nullcontext()
        if distributed:                                  # every patch of the grid as one Dask task, in order
            from shellfem.cluster import check_options, dask_client, map_tasks
            try:
                check_options(a.scheduler, a.workers)
            except SelfshapeError as e:
                raise SystemExit(f"thickness_law_sim: {e}") from None
            if a.workers == 0 and a.scheduler is None:
                cluster = contextlib.nullcontext(None)
            else:
                cluster = dask_client(a.scheduler, a.workers)
        with cluster as client, (contextlib.closing(progress) if progress is not None else contextlib.nullcontext()):
            if progress is not None:                     # the time left is timed from here (cluster started)
                progress({"stage": "tasks", "done": 0, "total": n_patches, "unit": "patches"})
            if distributed:
                def map_rows(calls):
                    return map_tasks(simulate_row_task, calls, workers=0 if client is None else None,
                                     client=client, on_result=lambda i, r: patch_done(r))
                grid = [(t, mu, side) for side in simulated_sides for t in a.thickness for mu in a.spacing]
                for key, r in zip(grid, map_rows([row_call(*g, a.stretch, **common) for g in grid])):
                    mapped[key] = r
            for side in simulated_sides:
                for t in a.thickness:
                    for mu in a.spacing:
                        r = run_row(t, mu, side, a.stretch, mesh_size=a.mesh_size, across=a.across,
                                    max_iterations=a.max_iterations, n_rows=a.rows, n_motifs=a.motifs, aspect=a.min_aspect,
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
                              max_iterations=a.max_iterations, n_rows=a.rows, n_motifs=a.motifs, aspect=a.min_aspect,
                              fabric=fabric, plastic=plastic)
                log.append(chk)
                rel = abs(chk["kappa_per_mm"] - front[(t_c, mu_c)]) / front[(t_c, mu_c)]
                mirror_note = ["  back rows = front rows by mirror symmetry through the fabric mid-surface (no gravity);",
                               f"  check: back simulated at t={t_c:g} mu2={mu_c:g}: |kappa| {chk['kappa_per_mm']:.6g} vs front "
                               f"{front[(t_c, mu_c)]:.6g} (relative difference {rel:.1e}, converged={chk['converged']})"]
                if not chk["converged"] or rel > 1e-3:
                    # the model is exactly mirror-symmetric; a difference means the (unmirrored) seeded
                    # perturbation led the back patch to another equilibrium: say so, keep the rows
                    mirror_note.append("  the check landed in a different equilibrium of the same patch (the seeded "
                                       "perturbation is not mirrored): the patch has more than one stable shape here")
                rows += [(t, mu, "back", k) for (t, mu), k in front.items()]
        head += ["SOURCE: forward simulation of parallel staggered ribbon sheets (forward.simulate.simulate_sheet):",
                 f"  patch max({a.motifs}, ceil({a.min_aspect:g} rows mu2 / mu1)) x mu1 along (at least {a.min_aspect:g} x its width), {a.rows} rows across, mu1 {MU1:g} mm, "
                 f"odd rows shifted mu1/2; mesh size {a.mesh_size:g} mm, {a.across:g} rows across a ribbon;",
                 "  kappa = area-weighted mean of b(x,x)/a(x,x) over the central quarter of the patch.",
                 ("  start: the perturbed flat state" if not a.start_curvature else
                  f"  start: rolled {a.start_direction} the ribbons to {a.start_curvature:g} /mm (printed) + the "
                  "perturbation"),
                 f"  rows simulated {len(log)}, not converged (dropped, not written) {len(dropped)}"]
        if a.from_json:
            head.append(f"  rows reused from {os.path.basename(a.from_json)}; a row line naming its patch and start "
                        "overrides the patch and start above")
        head += mirror_note
        for r in log:
            head.append(f"  row t={r['thickness_mm']:g} mu2={r['spacing_mm']:g} {r['side']}: "
                        f"converged={r['converged']} ({r['reason']}), {r['newton_iterations']} Newton it., "
                        f"{r['n_triangles']} triangles, {r['time_s']:g} s"
                        + (f"; kappa along {r['kappa_per_mm']:.4g}, across {r['kappa_across_per_mm']:.4g} /mm, "
                           f"k1 at {r['k1_angle_deg']:g} deg" if "k1_angle_deg" in r else "")
                        + (f"; patch {r['rows']} rows x {r['motifs']} motifs ({r['patch_mm'][0]:g} x "
                           f"{r['patch_mm'][1]:g} mm), start {r.get('start_direction', 'flat')}"
                           if "patch_mm" in r else ""))
    if a.model == "sim" and (a.table_thickness or a.table_spacing):
        tt = set(a.table_thickness or a.thickness)
        ts = set(a.table_spacing or a.spacing)
        left = [r for r in rows if not (r[0] in tt and r[1] in ts)]
        rows = [r for r in rows if r[0] in tt and r[1] in ts]
        head += [f"  TABLE: the sub-grid thickness {sorted(tt)} x spacing {sorted(ts)} mm; simulated rows left out:"]
        head += [f"    t={t:g} mu2={mu:g} {sd}: kappa {k:.4g}" for t, mu, sd, k in left]
    head += [f"NOTE: {n}" for n in a.note]
    text = format_thickness_law(rows, head)
    summary = {"law": a.model, "out": out, "rows_written": len(rows), "rows_dropped": len(dropped),
               "time_s": round(time.perf_counter() - t0, 2),
               "rows": [{k: r[k] for k in ROW_KEYS + EXTRA_ROW_KEYS if k in r} for r in log]}
    if a.model == "sim":
        summary["provenance"] = {"command": "python studies/thickness_law_sim.py " + " ".join(argv if argv is not None
                                                                                            else sys.argv[1:]),
                                 "git": git_hash(), "date": stamp}

    def write_rows_json():
        if a.rows_json and a.model == "sim":
            os.makedirs(os.path.dirname(os.path.abspath(a.rows_json)), exist_ok=True)
            with open(a.rows_json, "w") as f:
                json.dump(summary, f, indent=1)
                f.write("\n")

    try:
        parse_thickness_law(text, out)    # never write a table the pipeline cannot load
    except SelfshapeError as e:
        summary.update(rows_written=0, error=str(e))
        print(json.dumps(summary))
        write_rows_json()
        return 1
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    tmp = out + ".tmp"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, out)
    print(json.dumps(summary))
    write_rows_json()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
