"""Contact on a rolled tube: a star pattern simulated without and with self-contact (issue 20).

For each pattern (default: the gallery's tube, examples/gallery/tube.toml) the study solves the
same mesh twice, ``[contact] enabled = false`` and ``true`` (nested iteration as `selfshape
simulate` does), and reports per run: converged, Newton iterations, wall time (s), energy (N mm),
the triangle pairs that pass through each other over ALL pairs of triangles that share no vertex
(an exact triangle-triangle test, tests/test_contact.intersecting_pairs: independent of ipctk
and of the engine's printed-distance exclusion), the smallest distance between parts of the sheet
printed far apart (exact triangle distances over the pairs a KD-tree finds within reach; mm; the
offset is the sheet's largest total thickness), the active contact pairs; and a picture of each
deployed shape (forward.render.render_roll: isometric view and a section across the roll axis;
the triangles that intersect another in black without contact, those in contact with it).

    python studies/contact_tube.py [--pattern examples/gallery/tube.toml ...] [--out out/contact_tube]
        [--max-iterations N] [--only off|on] [--strip] [--png DIR]

prints ONE JSON line and writes OUT/contact_tube.json (contact_tube_{off,on}.json with --only) and
OUT/<name>_{off,on}.png (with --png
also DIR/<name>_no_contact.png and DIR/<name>_contact.png, the README's pictures).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time

import numpy as np


def _tests():
    """tests/test_contact (its exact triangle tests), importable from the repository root."""
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))
    import test_contact
    return test_contact


def _far_min_distance(sim, contact):
    """Smallest exact distance (mm) between triangles farther apart in the printed state than the
    contact's exclusion (tests/test_contact.far_pairs_min_distance), inf if none is within reach."""
    sheet = sim.sheet
    edge = float(np.linalg.norm(np.diff(sim.positions[sheet.triangles][:, [0, 1, 2, 0]], axis=1), axis=2).max())
    return _tests().far_pairs_min_distance(sheet, sim.positions, np.sqrt(2) * contact.exclusion_mm,
                                           contact.offset + 2 * edge)


def run_pattern(path: str, out: str, max_iterations: int | None = None, runs=("off", "on")) -> dict:
    from forward.render import render_roll
    from forward.simulate import make_contact, simulate
    from geometry.patterns import load_pattern

    name = os.path.splitext(os.path.basename(path))[0]
    rows = {}
    for on in [tag == "on" for tag in runs]:
        pat = load_pattern(path)
        pat.contact = on
        t0, c0 = time.perf_counter(), time.process_time()
        sim = simulate(pat, max_iterations=max_iterations)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        load = os.getloadavg()
        c = sim.model.contact or make_contact(sim.sheet, pat.fabric, sim.fixed, True, None)
        rep = sim.contact_report() if on else {}
        tag = "on" if on else "off"
        t0 = time.perf_counter()
        crossing = _tests().intersecting_pairs(sim.positions, sim.sheet.triangles)
        t_check = time.perf_counter() - t0
        mark = np.zeros(sim.sheet.n_triangles, bool)
        mark[crossing.ravel()] = True
        if on:
            mark |= rep["in_contact"]
        render_roll(sim, os.path.join(out, f"{name}_{tag}.png"),
                    title=f"{name}: {'with' if on else 'without'} contact ({len(crossing)} crossing pairs; black: "
                          f"{'in contact' if on else 'crossing'})", highlight=mark)
        d = _far_min_distance(sim, c)
        lv = sim.result.timings.get("levels") or []
        rows[tag] = dict(converged=bool(sim.result.converged), reason=sim.result.reason,
                         iterations=int(sim.result.iterations), wall_s=round(wall, 1), cpu_s=round(cpu, 1),
                         load_1min_after=round(load[0], 2), energy_nmm=float(sim.result.energy),
                         crossing_pairs=int(len(crossing)), crossing_check_s=round(t_check, 1),
                         far_min_distance_mm=None if not np.isfinite(d) else round(d, 4),
                         offset_mm=c.offset, exclusion_mm=round(c.exclusion_mm, 2),
                         min_distance_mm=rep.get("min_distance_mm"), active_pairs=int(rep.get("active_pairs", 0)),
                         contact_builds=int(c.builds), contact_skips=int(c.skips),
                         contact_cuts=int(sim.result.timings.get("contact_cuts", 0)),
                         levels=[(v["n_vertices"], v["iterations"], v["seconds"]) for v in lv])
    rows["n_vertices"] = int(sim.sheet.n_vertices)
    if len(runs) == 2:
        rows["time_ratio"] = round(rows["on"]["wall_s"] / max(rows["off"]["wall_s"], 1e-9), 2)
        rows["cpu_ratio"] = round(rows["on"]["cpu_s"] / max(rows["off"]["cpu_s"], 1e-9), 2)
    return rows


def run_strip(out: str) -> dict:
    """The 70 mm bilayer strip of tests/test_contact.py (0.25 mm fabric + 0.1 mm plastic,
    pre-stretched 1.1 along it, 1 mm mesh, one level): without contact from flat (it rolls about
    2.9 turns through itself), with contact from a loose spiral (the branch of a single roll; from
    flat it rolls from both ends); per run as run_pattern's rows plus the turns and inner / outer
    radii (mm) of its centre line, and the pictures OUT/strip_{off,on}.png (no highlight: without
    contact nearly every triangle crosses another)."""
    from forward.render import render_roll
    from forward.simulate import simulate_sheet
    from geometry.meshing import mesh_pattern

    t = _tests()
    s, L = 1.1, 70.0
    pat = t._strip(L=L, size=1.0, stretch=(s, 1.0))
    sheet = mesh_pattern(pat)
    rows, kappa0 = {}, None
    for on in (False, True):
        start = None if not on else t._rolled(sheet.points, 1.0 / kappa0, 0.7, s)
        t0, c0 = time.perf_counter(), time.process_time()
        sim = simulate_sheet(sheet, pat.fabric, pat.plastic, contact=on, start=start)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        if not on:
            kappa0 = float(np.median(np.abs(sim.model.curvatures(sim.result.q)[0]).max(1)))
        crossing = t.intersecting_pairs(sim.positions, sheet.triangles)
        turns, r_in, r_out = t.centreline_turns(sheet, sim.positions)
        rep = sim.contact_report() if on else {}
        tag = "on" if on else "off"
        render_roll(sim, os.path.join(out, f"strip_{tag}.png"), size=(1000, 450),
                    title=f"70 mm strip {'with' if on else 'without'} contact: {turns:.2f} turns, "
                          f"{len(crossing)} crossing pairs")
        rows[tag] = dict(converged=bool(sim.result.converged), iterations=int(sim.result.iterations),
                         wall_s=round(wall, 1), cpu_s=round(cpu, 1), energy_nmm=float(sim.result.energy),
                         crossing_pairs=int(len(crossing)), turns=round(turns, 3), r_in_mm=round(r_in, 3),
                         r_out_mm=round(r_out, 3), min_distance_mm=rep.get("min_distance_mm"),
                         active_pairs=int(rep.get("active_pairs", 0)))
    rows["n_vertices"] = int(sheet.n_vertices)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pattern", nargs="*", default=["examples/gallery/tube.toml"])
    ap.add_argument("--out", default="out/contact_tube")
    ap.add_argument("--max-iterations", type=int, default=None)
    ap.add_argument("--strip", action="store_true",
                    help="also the 70 mm strip that rolls ~2.9 turns (tests/test_contact.py), OUT/strip_{off,on}.png")
    ap.add_argument("--only", choices=["off", "on"], default=None,
                    help="one run only (two such processes side by side: compare their CPU times)")
    ap.add_argument("--png", default=None, help="also copy the pictures to DIR/<name>_no_contact.png / _contact.png")
    a = ap.parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    runs = ("off", "on") if a.only is None else (a.only,)
    result = {os.path.basename(p): run_pattern(p, a.out, a.max_iterations, runs) for p in a.pattern}
    if a.strip:
        result["strip"] = run_strip(a.out)
    if a.png:
        os.makedirs(a.png, exist_ok=True)
        for p in a.pattern:
            name = os.path.splitext(os.path.basename(p))[0]
            for tag, suffix in [(t, {"off": "no_contact", "on": "contact"}[t]) for t in runs]:
                shutil.copyfile(os.path.join(a.out, f"{name}_{tag}.png"), os.path.join(a.png, f"{name}_{suffix}.png"))
        if a.strip:
            for tag, suffix in (("off", "no_contact"), ("on", "contact")):
                shutil.copyfile(os.path.join(a.out, f"strip_{tag}.png"), os.path.join(a.png, f"strip_{suffix}.png"))
    with open(os.path.join(a.out, "contact_tube.json" if a.only is None else f"contact_tube_{a.only}.json"), "w") as f:
        json.dump(result, f, indent=1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
