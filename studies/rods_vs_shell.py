"""The seed's chapter-3 rods model beside the shell model on the gallery's cases (issue 22).

Each case of validation.cases.GALLERY_CASES is simulated with [solver] model = "shell" (the
default: printed areas as bilayer shell regions) and model = "rods" (rods on the centre lines
of the stars' arms and the ribbons, bare fabric; shellfem.rods), and measured twice:
- validation.measures.gallery_measure: the gallery's per-triangle / centre-fit measures, each
  on the model's own mesh;
- validation.measures.centreline_measures: the same measure for both models, on the printed
  geometry: the deployed surface sampled along the pattern's centre lines and across them at
  the same stations (normal curvatures of those 3D curves, 1/mm), and for the star cases a
  coarse curvature tensor at the star spacing (the lattice period averages each star's bump).
Prints ONE JSON line: per case and model both sets of measures, Newton iterations, vertices,
convergence and wall time (s, single process; timings only compare within one run).

--save DIR writes each solve's flat mesh and deployed positions (DIR/<case>_<model>.npz) and
its row (DIR/<case>_<model>.json), so --remeasure DIR re-measures them without solving;
--png DIR writes DIR/rods_vs_shell_<case>.png (shell left, rods right; each model's own
picture <case>_<model>.png beside its --save files; the gallery's
renderer, forward.render.render_deployed; the rods model's rods drawn as lines on its bare
fabric); --render DIR [--png PNGDIR] redraws them from the saved solves; --table DIR
[--bench-json FILE] prints the README table of the saved rows. --benchmark solves the
10,000-vertex star benchmark (validation.cases.star_benchmark as studies/bench_solver.py
builds it: nested iteration, no contact) with the shell model and then with the rods model in
the same process and reports vertices, Newton iterations, wall time and convergence.
--cross-start DIR solves the rods model from the shell's saved shapes (see cross_start).
--strips CSV compares both models' strip curvature with measured strips (see strip_check).
--size-sweep solves the tube's star pattern on sheets from 30 x 21 to 85 x 60 mm (--sizes WxH ...,
--stars KEY=VALUE overrides of its [stars] table) in --models: where each model's cap turns into
a tube (see size_sweep, sheet_tensor); --rods-variant KEY=FACTOR ... [--sizes] the diagnostics of
the rods model behind that (see rods_variant); --sweep-table DIR ... their table; --arms DIR the
arms' own curl in those solves (see arm_measures).

Run: python studies/rods_vs_shell.py [--only NAME ...] [--models shell rods] [--save DIR] [--png DIR]
     python studies/rods_vs_shell.py --remeasure DIR | --render DIR | --table DIR [--bench-json FILE]
     python studies/rods_vs_shell.py --benchmark | --cross-start DIR [--only NAME ...] | --strips CSV
     python studies/rods_vs_shell.py --size-sweep [--sizes WxH ...] [--stars KEY=VALUE ...] [--save DIR]
     python studies/rods_vs_shell.py --rods-variant KEY=FACTOR ... [--sizes WxH ...] [--save DIR]
     python studies/rods_vs_shell.py --sweep-table DIR ...
"""
from __future__ import annotations

import argparse
import copy
import glob
import json
import os
import time
from types import SimpleNamespace

import numpy as np

from validation.cases import GALLERY_CASES
from validation.measures import centreline_measures, gallery_measure

STUDY_CASES = ("tube", "dome", "flat_centre", "ribbons", "half_annulus")


def _pattern(name, model):
    from geometry.patterns import parse_pattern
    raw = copy.deepcopy(GALLERY_CASES[name]())
    raw.setdefault("solver", {})["model"] = model
    return parse_pattern(raw, f"{name} ({model})")


def _render(folder, name, model, points, triangles, x, side, rod_edges=None):
    """One model's picture of a case, folder/<case>_<model>.png (forward.render.render_deployed):
    the shell's printed regions coloured by side; the rods model's bare fabric with its rods
    drawn as lines."""
    from forward.render import render_deployed
    from shellfem.sheet import Sheet
    side = np.asarray(side)
    front, back = np.isin(side, (1, 2)), np.isin(side, (-1, 2))
    sheet = Sheet(points, triangles, thickness_front=0.3 * front, thickness_back=0.3 * back)
    path = os.path.join(folder, f"{name}_{model}.png")
    render_deployed(SimpleNamespace(sheet=sheet, positions=x), path, title=f"{name}: {model}", size=(600, 480),
                    lines=rod_edges)
    return path


def render_saved(save, png, names=None):
    """The side-by-side pictures (png/rods_vs_shell_<case>.png) of the solves saved in ``save``,
    and each model's own picture (save/<case>_<model>.png)."""
    os.makedirs(png, exist_ok=True)
    done = []
    for name in names or STUDY_CASES:
        files = [os.path.join(save, f"{name}_{m}.npz") for m in ("shell", "rods")]
        if not all(os.path.exists(f) for f in files):
            continue
        pics = []
        for m, f in zip(("shell", "rods"), files):
            d = np.load(f)
            rods = d["rod_edges"] if "rod_edges" in d else None
            side = d["side"] if rods is None else np.zeros(len(d["triangles"]))     # the rods model's fabric is bare
            pics.append(_render(save, name, m, d["points"], d["triangles"], d["x"], side, rods))
        out = os.path.join(png, f"rods_vs_shell_{name}.png")
        side_by_side(pics, out)
        done.append(out)
    return done


def _measure(name, pattern, points, triangles, x) -> dict:
    try:
        return centreline_measures(name, pattern, points, triangles, x)
    except Exception as e:          # a solve's numbers are kept: --remeasure recomputes from --save
        return {"error": repr(e)}


def run(names=None, models=("shell", "rods"), max_iterations=400, save=None, png=None) -> dict:
    from forward.simulate import simulate
    out = {}
    for name in names or STUDY_CASES:
        out[name] = {}
        pics = {}
        for model in models:
            pattern = _pattern(name, model)
            t0 = time.perf_counter()
            sim = simulate(pattern, max_iterations=max_iterations)
            row = {"converged": bool(sim.result.converged), "newton_iterations": int(sim.result.iterations),
                   "n_vertices": int(sim.sheet.n_vertices), "wall_s": round(time.perf_counter() - t0, 1)}
            row.update(gallery_measure(name, sim))
            P, T, x = sim.sheet.points, sim.sheet.triangles, sim.positions
            row["centreline"] = _measure(name, pattern, P, T, x)
            out[name][model] = row
            if save:
                os.makedirs(save, exist_ok=True)
                extra = {"rod_edges": sim.model.rods.edges} if model == "rods" else {}
                np.savez_compressed(os.path.join(save, f"{name}_{model}.npz"), points=P, triangles=T, x=x,
                                    side=sim.sheet.side, **extra)
                with open(os.path.join(save, f"{name}_{model}.json"), "w") as f:
                    json.dump(row, f, indent=1)
            if png:
                os.makedirs(png, exist_ok=True)
                pics[model] = _render(save or png, name, model, P, T, x, sim.sheet.side,
                                      sim.model.rods.edges if model == "rods" else None)
        if png and len(pics) == 2:
            side_by_side([pics["shell"], pics["rods"]], os.path.join(png, f"rods_vs_shell_{name}.png"))
            if not save:                # each model's picture stays beside its saved solve only
                for p in pics.values():
                    os.remove(p)
    return out


def side_by_side(paths, out, height=360):
    """One PNG of the pictures ``paths`` left to right, each scaled to ``height`` px, a
    256-colour palette (the gallery pictures are flat-shaded: no visible loss, a small file)."""
    from PIL import Image
    ims = [Image.open(p).convert("RGB") for p in paths]
    ims = [im.resize((round(im.width * height / im.height), height), Image.LANCZOS) for im in ims]
    canvas = Image.new("RGB", (sum(im.width for im in ims), height), "white")
    xo = 0
    for im in ims:
        canvas.paste(im, (xo, 0))
        xo += im.width
    canvas.quantize(256).save(out, optimize=True)


def remeasure(save) -> dict:
    """Recompute the centre-line measures of every saved solve in ``save`` (rows rewritten)."""
    out = {}
    for js in sorted(glob.glob(os.path.join(save, "*.json"))):
        name, model = os.path.basename(js)[:-5].rsplit("_", 1)
        d = np.load(js[:-5] + ".npz")
        row = json.load(open(js))
        row["centreline"] = _measure(name, _pattern(name, model), d["points"], d["triangles"], d["x"])
        with open(js, "w") as f:
            json.dump(row, f, indent=1)
        out.setdefault(name, {})[model] = row
    return out


def _cell(name, r) -> str:
    """One model's measures of case ``name`` for the README table (curvatures 1/mm)."""
    c = r["centreline"]
    if name == "tube":
        pt = f" (per triangle {r['median_kmax_over_kmin']:.2f})" if "median_kmax_over_kmin" in r else ""
        return f"k_x / k_y {c['k_x']:.3f} / {c['k_y']:.3f}, ratio {c['ratio']:.3g}{pt}"
    if name in ("dome", "flat_centre"):
        return f"centre K {c['gauss_centre']:.2e} /mm^2, \\|H\\| {c['mean_centre']:.4f}"
    if name == "ribbons":
        return (f"along {c['along']:.3f}, across {c['across']:.3f}; contraction along / across "
                f"{c['along_contraction_first_last'][0]:.3f} / {c['across_contraction_first_last'][0]:.3f} "
                f"(per triangle {r['curvature_along_ribbons']:.3f} / {r['curvature_across_ribbons']:.3f})")
    if name == "half_annulus":
        ca, cl = c["across_contraction_first_last"], c["along_contraction_first_last"]
        return (f"contraction across inner / outer gaps {ca[0]:.3f} / {ca[1]:.3f}, along inner / outer lines "
                f"{cl[0]:.3f} / {cl[1]:.3f} (edges {r['inner_length_ratio']:.3f} / {r['outer_length_ratio']:.3f})")
    return ""


def markdown_table(save, png_dir="docs/gallery", bench=None) -> str:
    """README table (case | shell | rods | iterations | time) of the rows saved in ``save``, and
    the benchmark's row from ``bench`` (the JSON line of --benchmark) when given."""
    rows = ["| case | shell | rods | Newton it. shell / rods | vertices shell / rods | wall s shell / rods |",
            "|---|---|---|---|---|---|"]
    imgs = []
    for name in STUDY_CASES:
        try:
            s, r = (json.load(open(os.path.join(save, f"{name}_{m}.json"))) for m in ("shell", "rods"))
        except FileNotFoundError:
            continue
        rows.append(f"| {name} | {_cell(name, s)} | {_cell(name, r)} | {s['newton_iterations']} / "
                    f"{r['newton_iterations']} | {s['n_vertices']} / {r['n_vertices']} | "
                    f"{s['wall_s']:.0f} / {r['wall_s']:.0f} |")
        imgs.append(f'<img src="{png_dir}/rods_vs_shell_{name}.png" width="400" alt="{name}: shell left, rods right">')
    if bench and os.path.exists(bench):
        b = json.load(open(bench))
        s, r = b["shell"], b["rods"]
        rows.append(f"| star benchmark 85 x 60 mm | {_cell('tube', s)} | {_cell('tube', r)} | "
                    f"{s['newton_iterations']} / {r['newton_iterations']} | {s['n_vertices']} / {r['n_vertices']} | "
                    f"{s['wall_s']:.0f} / {r['wall_s']:.0f} |")
    return "\n".join(rows) + "\n\n" + "\n".join(imgs)


def cross_start(save, names=None, max_iterations=400) -> dict:
    """Which equilibrium the rods model prefers: each case solved with the rods model from its
    own (perturbed flat) start and from the shell model's saved deployed shape (DIR/<case>_shell.npz,
    interpolated at the rods mesh's vertices, validation.measures.deployed_at); per start the
    energy (N mm), Newton iterations, convergence and the centre-line measures. The lower
    energy is the rods model's preferred state of the two; if the shell's shape stays an
    equilibrium, the two models differ by the branch they find, not by what they allow."""
    from forward.simulate import simulate_sheet
    from geometry.centrelines import mesh_pattern_rods
    from shellfem.rods.coupled import rod_shell_model
    from validation.measures import deployed_at
    out = {}
    for name in names or STUDY_CASES:
        f = os.path.join(save, f"{name}_shell.npz")
        if not os.path.exists(f):
            continue
        d = np.load(f)
        pattern = _pattern(name, "rods")
        rm = mesh_pattern_rods(pattern)
        P, T = rm.sheet.points, rm.sheet.triangles
        start, _ = deployed_at(d["points"], d["triangles"], d["x"], P)
        if not np.isfinite(start).all():        # a rods vertex outside the shell's mesh: nearest shell vertex
            bad = ~np.isfinite(start).all(1)
            near = np.argmin(((P[bad, None, :] - d["points"][None]) ** 2).sum(-1), axis=1)
            start[bad] = d["x"][near]

        def factory(sheet, fabric, plastic):
            return rod_shell_model(sheet, fabric, plastic, rm.edges, rm.thickness, rm.width, side=rm.side)
        out[name] = {}
        for label, st in (("own start", None), ("from the shell's shape", start)):
            t0 = time.perf_counter()
            sim = simulate_sheet(rm.sheet, pattern.fabric, pattern.plastic, pattern.supports, seed=pattern.seed,
                                 max_iterations=max_iterations, metric_floor=pattern.metric_floor,
                                 model_factory=factory, start=st)
            out[name][label] = {"energy_nmm": float(sim.model.energy(sim.result.q)),
                                "newton_iterations": int(sim.result.iterations),
                                "converged": bool(sim.result.converged), "reason": sim.result.reason,
                                "wall_s": round(time.perf_counter() - t0, 1),
                                "centreline": _measure(name, pattern, P, T, sim.positions)}
    return out


def strip_check(csv_path, ratios=None) -> dict:
    """The two models' strip curvatures against a strips CSV (validation.strips schema): the
    shell's (validation.strips.strip_model, the layered plate of the calibration) and the rods'
    (shellfem.rods.monolayer.monolayer_curvature, the beam of seed Eq. 3.13). Per model: the
    least-squares modulus ratio E_plastic / E_fabric (plastic flat at rest, as `selfshape
    calibrate strips` fits it) and the RMS relative residual; and at the gallery's ratios
    (``ratios``: {label: ratio}, default the stars' and the ribbons' plastic over the default
    fabric modulus) each model's curvature beside the measured mean per plastic thickness (1/mm)."""
    from scipy.optimize import minimize_scalar
    from shellfem.materials import Fabric
    from shellfem.rods.monolayer import monolayer_curvature
    from validation.cases import PLASTIC, PLASTIC_CH3
    from validation.strips import MEASURED, fit_modulus_ratio, read_strips, strip_model
    rows = read_strips(csv_path)
    h1, h2, st, y = rows["plastic_thickness_mm"], rows["fabric_thickness_mm"], rows["stretch"], rows[MEASURED]
    rods = lambda n: monolayer_curvature(h1, h2, n, 1.0, st)          # noqa: E731
    shell_fit = fit_modulus_ratio(rows)
    r = minimize_scalar(lambda t: float(((rods(np.exp(t)) - y) ** 2).sum()), bounds=(0.0, 12.0), method="bounded")
    fits = {"shell": (shell_fit["value"], strip_model(h1, h2, st, shell_fit["value"])),
            "rods": (float(np.exp(r.x)), rods(float(np.exp(r.x))))}
    out = {"file": os.path.basename(csv_path), "rows": int(y.size), "fit": {}}
    for m, (n, k) in fits.items():
        out["fit"][m] = {"modulus_ratio": round(n, 1), "rms_relative_residual": float(np.sqrt(np.mean(((k - y) / y) ** 2)))}
    E2 = Fabric().young_modulus
    ratios = ratios or {"stars": PLASTIC_CH3["young_modulus_mpa"] / E2, "ribbons": PLASTIC["young_modulus_mpa"] / E2}
    out["at_gallery_ratios"] = {}
    for label, n in ratios.items():
        per = {}
        for h in np.unique(h1):
            sel = h1 == h
            per[f"{h:g}"] = {"measured": float(np.mean(y[sel])),
                             "shell": float(np.mean(strip_model(h1[sel], h2[sel], st[sel], n))),
                             "rods": float(np.mean(monolayer_curvature(h1[sel], h2[sel], n, 1.0, st[sel])))}
        out["at_gallery_ratios"][label] = {"modulus_ratio": round(float(n), 1), "per_thickness": per}
    return out


def benchmark(max_iterations=300, width=85.0, height=60.0) -> dict:
    """The 10,000-vertex star benchmark in both models, one after the other in this process:
    the shell as studies/bench_solver.py solves it (nested iteration, no contact; wall time
    includes meshing), then the rods model as `selfshape simulate` solves a model = "rods"
    pattern (one mesh; wall time includes meshing); per model vertices, Newton iterations,
    wall time (s), convergence, bounding box (mm) and the tube's centre-line measures."""
    import bench_solver
    from forward.simulate import simulate
    from geometry.patterns import parse_pattern
    from validation.cases import star_benchmark
    out = {}
    t0 = time.perf_counter()
    kept = {}
    b = bench_solver.run(width, height, max_iterations=max_iterations, keep=kept)
    sim = kept["simulation"]
    out["shell"] = {"n_vertices": b["n_vertices"], "newton_iterations": b["newton_iterations"],
                    "converged": b["converged"], "reason": b["reason"], "wall_s": round(time.perf_counter() - t0, 1),
                    "levels": b["levels"], "bbox_mm": sim.summary().get("bbox_mm"),
                    "centreline": _measure("tube", kept["pattern"], sim.sheet.points, sim.sheet.triangles,
                                           sim.positions)}
    raw = star_benchmark(width, height)
    raw["solver"]["model"] = "rods"
    pattern = parse_pattern(raw, "star benchmark (rods)")
    t0 = time.perf_counter()
    sim = simulate(pattern, max_iterations=max_iterations)
    out["rods"] = {"n_vertices": int(sim.sheet.n_vertices), "n_rod_edges": int(len(sim.model.rods.edges)),
                   "newton_iterations": int(sim.result.iterations), "converged": bool(sim.result.converged),
                   "reason": sim.result.reason, "wall_s": round(time.perf_counter() - t0, 1),
                   "bbox_mm": sim.summary().get("bbox_mm"),
                   "centreline": _measure("tube", pattern, sim.sheet.points, sim.sheet.triangles, sim.positions)}
    return out


SWEEP_SIZES = ((30.0, 21.0), (40.0, 28.0), (50.0, 35.0), (65.0, 45.0), (85.0, 60.0))


def sheet_tensor(pattern, points, triangles, x, grid=1.0) -> dict:
    """The tube measure for any sheet size: the coarse curvature tensor at the star spacing
    (validation.measures.coarse_curvature_tensor, as centreline_measures) at every point of a
    ``grid`` mm lattice centred on the sheet whose four triples lie inside it (centreline_measures'
    5 mm grid with a 10 mm margin finds no station on a 30 x 21 mm sheet); medians of k_x, k_y,
    their ratio, and the median principal |k| and their ratio (1/mm)."""
    from validation.measures import coarse_curvature_tensor
    step = float(pattern.raw["stars"]["spacing_mm"])
    x0, y0, x1, y1 = pattern.outline.bounds
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    hx, hy = (x1 - x0) / 2 - step - 0.25, (y1 - y0) / 2 - step - 0.25
    if hx < 0 or hy < 0:
        return {"n_stations": 0}
    gx = cx + grid * np.arange(-np.floor(hx / grid), np.floor(hx / grid) + 1)
    gy = cy + grid * np.arange(-np.floor(hy / grid), np.floor(hy / grid) + 1)
    g = np.stack(np.meshgrid(gx, gy), -1).reshape(-1, 2)
    S = coarse_curvature_tensor(np.asarray(points, float), triangles, x, g, step)
    S = S[np.isfinite(S).all((1, 2))]
    if not len(S):
        return {"n_stations": 0}
    ev = np.sort(np.abs(np.linalg.eigvalsh(S)), axis=1)
    kx, ky = float(np.median(S[:, 0, 0])), float(np.median(S[:, 1, 1]))
    kmin, kmax = (float(v) for v in np.median(ev, 0))
    return dict(k_x=kx, k_y=ky, ratio=max(abs(kx), abs(ky)) / max(min(abs(kx), abs(ky)), 1e-12), k_max=kmax,
                k_min=kmin, principal_ratio=kmax / max(kmin, 1e-12), n_stations=int(len(S)))


def size_sweep(sizes=SWEEP_SIZES, models=("rods", "shell"), save=None, max_iterations=400, stars=None) -> list:
    """Where each model's star sheet turns from a cap into a tube: the gallery's tube pattern
    (validation.cases.GALLERY_CASES["tube"]: stars every 10 mm, arms 0.7 of it, 0.3 mm plastic at
    E ratio 3200, mesh 2.5 mm) on rectangles of the given (width, height) mm, the star pattern
    the same, the sheet larger (50 x 35 is the gallery's tube, 85 x 60 the benchmark's outline).
    Per size and model: vertices, Newton iterations, wall time (s, includes meshing),
    convergence, energy (N mm) and the tube's centre-line measures (k_x, k_y and their ratio at
    the star spacing; validation.measures.centreline_measures). ``save``: each solve's mesh and
    deployed state (DIR/tube_<w>x<h>_<model>.npz) and its row (.json), written as it finishes.
    ``stars``: overrides of the [stars] table (e.g. {"arm_width_mm": 0.4}; the files then
    carry them in their names)."""
    from forward.simulate import simulate
    from geometry.patterns import parse_pattern
    rows = []
    for w, h in sizes:
        for model in models:
            raw = copy.deepcopy(GALLERY_CASES["tube"]())
            raw["fabric"]["rectangle"] = [float(w), float(h)]
            raw["solver"]["model"] = model
            raw["stars"].update(stars or {})
            pattern = parse_pattern(raw, f"tube {w:g} x {h:g} ({model})")
            t0 = time.perf_counter()
            sim = simulate(pattern, max_iterations=max_iterations)
            P, T, x = sim.sheet.points, sim.sheet.triangles, sim.positions
            row = {"size_mm": [w, h], "model": model, "stars": stars or {}, "n_vertices": int(sim.sheet.n_vertices),
                   "newton_iterations": int(sim.result.iterations), "converged": bool(sim.result.converged),
                   "wall_s": round(time.perf_counter() - t0, 1),
                   "energy_nmm": float(sim.model.energy(sim.result.q)),
                   "bbox_mm": sim.summary().get("bbox_mm"),
                   "centreline": _measure("tube", pattern, P, T, x),
                   "sheet_tensor": sheet_tensor(pattern, P, T, x)}
            rows.append(row)
            print(json.dumps(row), flush=True)
            if save:
                os.makedirs(save, exist_ok=True)
                tag = "".join(f"_{k}{v:g}" for k, v in sorted((stars or {}).items()))
                stem = os.path.join(save, f"tube_{w:g}x{h:g}_{model}{tag}")
                extra = {"rod_edges": sim.model.rods.edges} if model == "rods" else {}
                np.savez_compressed(stem + ".npz", points=P, triangles=T, x=x, side=sim.sheet.side, **extra)
                with open(stem + ".json", "w") as f:
                    json.dump(row, f, indent=1)
    return rows


def arm_measures(folder) -> dict:
    """Per saved tube solve in ``folder`` (--size-sweep / --rods-variant files): the normal
    curvature (1/mm) of the deployed surface along each printed arm, through its points at 5,
    50 and 95 % of its length (validation.measures.curve_curvatures: the arm's own curl, the
    same measure for both models), as the median, the fraction of arms flatter than -0.02 /mm
    or reversed, and the median per arm direction; for plain rods solves (not --rods-variant
    ones) also the median axial force of the rod edges (N, < 0 compression; EA of
    shellfem.rods.monolayer.arm_section times the edge strain |e| / l - 1)."""
    from geometry.centrelines import pattern_centrelines
    from geometry.patterns import parse_pattern
    from shellfem.materials import Fabric
    from shellfem.rods.monolayer import arm_section
    from validation.cases import PLASTIC_CH3
    from validation.measures import _along, curve_curvatures
    out = {}
    for f in sorted(glob.glob(os.path.join(folder, "tube_*.npz"))):
        d = np.load(f)
        r = json.load(open(f[:-4] + ".json"))
        raw = copy.deepcopy(GALLERY_CASES["tube"]())
        raw["fabric"]["rectangle"] = list(r["size_mm"])
        raw["stars"].update(r.get("stars", {}))
        raw["solver"]["model"] = "rods"
        pattern = parse_pattern(raw, "tube")
        st = raw["stars"]
        k, ang = [], []
        for line, *_ in pattern_centrelines(pattern):
            line = np.asarray(line, float)
            v = line[-1] - line[0]
            k.append(curve_curvatures(d["points"], d["triangles"], d["x"], _along(line, [0.05, 0.5, 0.95]))[0])
            ang.append(int(round(np.degrees(np.arctan2(v[1], v[0])))) % 360)
        k, ang = np.array(k), np.array(ang)
        ok = np.isfinite(k)
        row = {"arms": int(ok.sum()), "median_arm_curvature": round(float(np.median(k[ok])), 4),
               "fraction_flatter_than_0.02": round(float(np.mean(k[ok] > -0.02)), 3),
               "median_by_direction_deg": {int(a): round(float(np.median(k[ok & (ang == a)])), 4)
                                           for a in sorted(set(ang[ok].tolist()))}}
        if "rod_edges" in d and not r.get("factors"):     # the plain rods model (not a variant's constants)
            E, P, x = d["rod_edges"], d["points"], d["x"]
            sec = arm_section(st["thickness_mm"], st["arm_width_mm"], raw["fabric"]["thickness_mm"],
                              PLASTIC_CH3["young_modulus_mpa"], Fabric().young_modulus, raw["fabric"]["stretch"])
            l0 = np.linalg.norm(P[E[:, 1]] - P[E[:, 0]], axis=1)
            l1 = np.linalg.norm(x[E[:, 1]] - x[E[:, 0]], axis=1)
            row["median_axial_force_n"] = round(float(np.median(sec.EA * (l1 / l0 - 1))), 3)
        out[os.path.basename(f)[:-4]] = row
    return out


def sweep_table(folder) -> str:
    """Markdown table of the size sweep's and the variants' rows saved in ``folder`` (size,
    model, variant, vertices, Newton iterations, wall s, energy, k_x / k_y and their ratio of
    sheet_tensor, recomputed from the saved solve where a row predates it)."""
    from geometry.patterns import parse_pattern
    rows = ["| size mm | model | variant | vertices | Newton it. | wall s | k_x / k_y (1/mm) | ratio |",
            "|---|---|---|---|---|---|---|---|"]
    recs = []
    for js in glob.glob(os.path.join(folder, "tube_*.json")):
        r = json.load(open(js))
        if "sheet_tensor" not in r:
            d = np.load(js[:-5] + ".npz")
            raw = copy.deepcopy(GALLERY_CASES["tube"]())
            raw["fabric"]["rectangle"] = list(r["size_mm"])
            raw["stars"].update(r.get("stars", {}))
            r["sheet_tensor"] = sheet_tensor(parse_pattern(raw, "tube"), d["points"], d["triangles"], d["x"])
            with open(js, "w") as f:
                json.dump(r, f, indent=1)
        recs.append(r)
    recs.sort(key=lambda r: (r["size_mm"][0], r["model"] != "shell", json.dumps(r.get("factors", {})),
                             json.dumps(r.get("stars", {}))))
    for r in recs:
        t = r["sheet_tensor"]
        var = ", ".join(f"{k} {v:g}" for k, v in {**r.get("factors", {}), **r.get("stars", {})}.items()) or "-"
        conv = "" if r["converged"] else " (not converged)"
        rows.append(f"| {r['size_mm'][0]:g} x {r['size_mm'][1]:g} | {r['model']} | {var} | {r['n_vertices']} | "
                    f"{r['newton_iterations']}{conv} | {r['wall_s']:.0f} | {t.get('k_x', float('nan')):.3f} / "
                    f"{t.get('k_y', float('nan')):.3f} | {t.get('ratio', float('nan')):.2f} |")
    return "\n".join(rows)


VARIANT_KEYS = ("EA", "B1", "B2", "T", "rest", "band", "offset", "junction", "junction_B2")


def _banded_rod_model(sheet, fabric, plastic, rm, band_nmm, band_mpa=3.36e5):
    """The rods model (shellfem.rods.coupled.rod_shell_model) with every fabric triangle that
    has a rod edge stiffened in-plane by a layer centred on the mid-surface (no bending offset,
    no misfit: rest metric = the printed one) of membrane stiffness ``band_nmm`` N/mm, thickness
    band_nmm / band_mpa mm (so its bending stiffness, E t^3 / 12, is negligible: 1e-3 N mm at
    1000 N/mm). Emulates a printed arm that is a plate stiff in-plane in every direction, in a
    band wider than the arm (a triangle of the 2.5 mm mesh each side against the arm's 0.4 mm):
    an upper bound on what candidate (a) can change."""
    from shellfem.layers import QuadraticForm, bending_quadratic, layer_form, rest_area
    from shellfem.materials import MEMBRANE_MODELS, RestState
    from shellfem.model import ShellModel, edge_metric
    from shellfem.rods.coupled import RodShellModel, arm_rods
    from shellfem.sheet import Sheet
    bare = Sheet(sheet.points, sheet.triangles, region=sheet.region)
    m = bare.n_triangles
    P2 = bare.points[bare.triangles]
    sx, sy = fabric.stretch
    Prest = P2 / np.array([sx, sy])
    abar_print = edge_metric(np.concatenate([P2, np.zeros((m, 3, 1))], 2))
    abar_fab = edge_metric(Prest)
    tri_edges = {tuple(sorted(e)) for e in np.asarray(rm.edges).tolist()}
    T = bare.triangles
    band = np.array([any(tuple(sorted((t[i], t[(i + 1) % 3]))) in tri_edges for i in range(3)) for t in T.tolist()])
    quad = QuadraticForm(m)
    quad.add(*bending_quadratic(abar_fab, fabric.bending_stiffness, fabric.poisson))
    half = 0.5 * band_nmm / band_mpa
    quad.add(*layer_form(abar_print, np.zeros((m, 3)), band_mpa, plastic.poisson, -half, half, exact_metric=False),
             mask=band)
    everywhere = np.ones(m, bool)
    membrane = MEMBRANE_MODELS[fabric.model](RestState(points=Prest, metric=abar_fab, area=rest_area(abar_fab)),
                                             fabric).energy
    shell = ShellModel(bare, quad, everywhere, membrane, None)
    return RodShellModel(shell, arm_rods(bare, rm.edges, rm.thickness, rm.width, fabric, plastic, rm.side))


def _junction(rods) -> np.ndarray:
    """The stencils at the stars' centres (vertices where three or more rod edges meet: the
    pairwise stencils of weight 1 / (d - 1) < 1)."""
    e = rods.edges
    deg = np.bincount(e.ravel(), minlength=rods.n_vertices)
    return deg[rods.points[:, 1]] >= 3


def rods_variant(w, h, factors: dict, save=None, max_iterations=400) -> dict:
    """A diagnostic (not a model): the rods model of the tube pattern on a w x h mm sheet (as
    size_sweep) with its rod network's constants scaled by ``factors`` {key: factor}, keys in
    VARIANT_KEYS: EA (stretching), B1 (bending about the width axis), B2 (in-plane bending),
    T (twist; 0 removes the twist energy: an upper bound on what a free material frame can
    relieve), rest (the bilayer's normal rest curvature k1: the curvature drive). EA and B2
    together stiffen the stars in-plane (candidate (a)); T tests the twist (candidate (b));
    rest scales the drive; junction scales B1, B2 and T of the stars' centre stencils (a
    plate centre in the shell), junction_B2 their B2 only (it holds the 3D angle between two
    arms, so a star cannot cone without bending its pairs in-plane); offset=1 (not a factor) puts the arms on the fabric
    (shellfem.rods.coupled.arm_rods offset=True: the model change this study tests, not a
    scaling); band (N/mm, not a factor) stiffens the fabric next to the rods
    in-plane (_banded_rod_model). The same row as size_sweep, with the factors."""
    from forward.simulate import simulate_sheet
    from geometry.centrelines import mesh_pattern_rods
    from geometry.patterns import parse_pattern
    from shellfem.rods.coupled import rod_shell_model
    bad = sorted(set(factors) - set(VARIANT_KEYS))
    if bad:
        raise ValueError(f"unknown rod constants {bad}; known: {VARIANT_KEYS}")
    raw = copy.deepcopy(GALLERY_CASES["tube"]())
    raw["fabric"]["rectangle"] = [float(w), float(h)]
    raw["solver"]["model"] = "rods"
    pattern = parse_pattern(raw, f"tube {w:g} x {h:g} (rods variant)")
    rm = mesh_pattern_rods(pattern)

    def factory(sheet, fabric, plastic):
        if factors.get("band", 0.0) > 0:
            m = _banded_rod_model(sheet, fabric, plastic, rm, factors["band"])
        else:
            m = rod_shell_model(sheet, fabric, plastic, rm.edges, rm.thickness, rm.width, side=rm.side,
                                offset=bool(factors.get("offset", 0.0)))
        r = m.rods
        for key, f in factors.items():
            if key in ("band", "offset"):
                continue
            if key in ("junction", "junction_B2"):       # the stars' centres: the pairwise stencils
                at = _junction(r)
                for name in (("B1", "B2", "T") if key == "junction" else ("B2",)):
                    setattr(r, name, np.where(at, getattr(r, name) * f, getattr(r, name)))
                continue
            if key == "rest":
                r.rest[:, 0] = r.rest[:, 0] * f        # printed k1 is 0 on every stencil: the bilayer's part
            else:
                setattr(r, key, getattr(r, key) * f)
        return m
    t0 = time.perf_counter()
    sim = simulate_sheet(rm.sheet, pattern.fabric, pattern.plastic, pattern.supports, seed=pattern.seed,
                         max_iterations=max_iterations, metric_floor=pattern.metric_floor, model_factory=factory)
    P, T, x = rm.sheet.points, rm.sheet.triangles, sim.positions
    row = {"size_mm": [w, h], "model": "rods", "factors": factors, "n_vertices": int(rm.sheet.n_vertices),
           "newton_iterations": int(sim.result.iterations), "converged": bool(sim.result.converged),
           "wall_s": round(time.perf_counter() - t0, 1), "energy_nmm": float(sim.model.energy(sim.result.q)),
           "centreline": _measure("tube", pattern, P, T, x), "sheet_tensor": sheet_tensor(pattern, P, T, x)}
    if save:
        os.makedirs(save, exist_ok=True)
        tag = "_".join(f"{k}{v:g}" for k, v in sorted(factors.items())) or "base"
        stem = os.path.join(save, f"tube_{w:g}x{h:g}_rods_{tag}")
        np.savez_compressed(stem + ".npz", points=P, triangles=T, x=x, rod_edges=rm.edges)
        with open(stem + ".json", "w") as f:
            json.dump(row, f, indent=1)
    return row


def main(argv=None):
    from shellfem.memory import keep_freed_memory
    keep_freed_memory()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", default=None, choices=list(GALLERY_CASES))
    ap.add_argument("--models", nargs="*", default=["shell", "rods"], choices=["shell", "rods"])
    ap.add_argument("--max-iterations", type=int, default=400)
    ap.add_argument("--save", default=None, help="folder for each solve's mesh, deployed state and row")
    ap.add_argument("--png", default=None, help="folder for the side-by-side pictures")
    ap.add_argument("--remeasure", default=None, help="re-measure the solves saved in this folder and stop")
    ap.add_argument("--render", default=None, help="draw the --png pictures of the solves saved in this folder and stop")
    ap.add_argument("--table", default=None, help="print the README table of the rows saved in this folder")
    ap.add_argument("--bench-json", default=None, help="with --table: the --benchmark output to add as a row")
    ap.add_argument("--benchmark", action="store_true", help="the 10k-vertex star benchmark in both models")
    ap.add_argument("--strips", default=None, help="compare both models' strip curvature with this strips CSV")
    ap.add_argument("--cross-start", default=None,
                    help="solve the rods model from the shell shapes saved in this folder (and from its own start)")
    ap.add_argument("--size-sweep", action="store_true",
                    help="the tube's star pattern on sheets 30 x 21 ... 85 x 60 mm in --models (see size_sweep)")
    ap.add_argument("--sizes", nargs="*", default=None, help="with --size-sweep: sizes as WxH mm, e.g. 30x21 50x35")
    ap.add_argument("--stars", nargs="*", default=None, metavar="KEY=VALUE",
                    help="with --size-sweep: overrides of the [stars] table, e.g. arm_width_mm=0.4")
    ap.add_argument("--rods-variant", nargs="*", default=None, metavar="KEY=FACTOR",
                    help="with --sizes: the rods model with its constants scaled (diagnostic; see rods_variant)")
    ap.add_argument("--sweep-table", nargs="*", default=None, metavar="DIR",
                    help="print the table of the --size-sweep / --rods-variant rows saved in these folders")
    ap.add_argument("--arms", default=None, metavar="DIR",
                    help="the arms' curl (and the rods' axial force) of the tube solves saved in DIR")
    a = ap.parse_args(argv)
    if a.arms:
        print(json.dumps(arm_measures(a.arms), indent=1))
    elif a.sweep_table:
        print("\n".join(sweep_table(d) if i == 0 else "\n".join(sweep_table(d).splitlines()[2:])
                        for i, d in enumerate(a.sweep_table)))
    elif a.rods_variant is not None:
        factors = {k: float(v) for k, v in (t.split("=") for t in a.rods_variant)}
        for s in a.sizes or ["50x35"]:
            w, h = (float(v) for v in s.split("x"))
            print(json.dumps(rods_variant(w, h, factors, a.save, a.max_iterations)), flush=True)
    elif a.size_sweep:
        sizes = [tuple(float(v) for v in s.split("x")) for s in a.sizes] if a.sizes else SWEEP_SIZES
        stars = {k: float(v) for k, v in (t.split("=") for t in a.stars)} if a.stars else None
        size_sweep(sizes, a.models, a.save, a.max_iterations, stars)
    elif a.table:
        print(markdown_table(a.table, bench=a.bench_json))
    elif a.render:
        print(json.dumps(render_saved(a.render, a.png or "docs/gallery", a.only)))
    elif a.remeasure:
        print(json.dumps(remeasure(a.remeasure)))
    elif a.strips:
        print(json.dumps(strip_check(a.strips)))
    elif a.cross_start:
        print(json.dumps(cross_start(a.cross_start, a.only)))
    elif a.benchmark:
        print(json.dumps(benchmark()))
    else:
        print(json.dumps(run(a.only, a.models, a.max_iterations, a.save, a.png)))


if __name__ == "__main__":
    main()
