"""Seed section 4.1 in silico: parallel ribbons printed at 0 and at 90 degrees to the fabric's
course direction, over ribbon thickness and spacing, on the orthotropic fabric model.

The seed printed the same parallel-ribbon pattern in two orientations and saw the samples
bend about different axes *relative to the ribbons*; it attributes this to the fabric's
orthotropy. For each (thickness, pitch) this study simulates the pattern of
`validation.gallery._parallel_ribbons` (60 x 40 mm, ribbons 1.5 mm wide along x, s = 1.35,
TPU 72.3 MPa, orthotropic log-barrier fabric with its fitted parameters) with the course
direction at 0 and at 90 degrees to the ribbons and measures the median curvature along and
across the ribbons over the inner 60 % of the sheet. The mode is "along" when
|kappa_along| > |kappa_across|. The seed's effect is reproduced at a (thickness, pitch) where
the two orientations give different modes.

Each case is appended to OUT/rows.jsonl as soon as it is done (a rerun skips cases already
there); OUT/table.md is the comparison table; prints ONE JSON line with all rows and, per
(thickness, pitch), whether the modes differ.

Run: python -m validation.ortho_sweep [--thickness 0.2 0.4 0.8 1.2] [--pitch 3 6] [--seeds 0]
                                     [--out docs/gallery/ortho_sweep] [--table]
"""
from __future__ import annotations

import argparse
import json
import os
import time


def case(thickness_mm: float, pitch_mm: float, course_deg: float, seed: int = 0) -> dict:
    """Pattern dict of one case (the gallery's parallel ribbons with this thickness and pitch;
    seed: the solver's symmetry-breaking perturbation)."""
    from validation.gallery import _parallel_ribbons
    raw = _parallel_ribbons(pitch=pitch_mm, model="orthotropic", course=course_deg)
    for r in raw["ribbon"]:
        r["thickness_mm"] = float(thickness_mm)
    raw["solver"]["seed"] = int(seed)
    return raw


def simulate_case(thickness_mm: float, pitch_mm: float, course_deg: float, max_iterations: int = 600,
                  seed: int = 0) -> dict:
    from geometry.patterns import load_pattern
    from forward.simulate import simulate
    from validation.gallery import measure

    pat = load_pattern(case(thickness_mm, pitch_mm, course_deg, seed))
    t0 = time.perf_counter()
    sim = simulate(pat, max_iterations=max_iterations)
    m = measure("ortho_0", sim)
    along, across = m["curvature_along_ribbons"], m["curvature_across_ribbons"]
    return {"thickness_mm": thickness_mm, "pitch_mm": pitch_mm, "course_deg": course_deg, "seed": int(seed),
            "converged": bool(sim.result.converged), "newton_iterations": int(sim.result.iterations),
            "n_vertices": int(sim.sheet.n_vertices), "wall_s": round(time.perf_counter() - t0, 1),
            "kappa_along_per_mm": along, "kappa_across_per_mm": across, "twist_per_mm": m["twist"],
            "mode": "along" if abs(along) > abs(across) else "across"}


def _along_over_across(row: dict) -> float:
    return round(abs(row["kappa_along_per_mm"]) / max(abs(row["kappa_across_per_mm"]), 1e-12), 3)


def summarise(rows: list, seed: int = 0) -> list:
    """Per (thickness, pitch) with both orientations converged (solver seed ``seed``): the modes
    and whether they differ."""
    out = []
    rows = [r for r in rows if r.get("seed", 0) == seed]
    keys = sorted({(r["thickness_mm"], r["pitch_mm"]) for r in rows})
    for t, p in keys:
        by = {r["course_deg"]: r for r in rows if (r["thickness_mm"], r["pitch_mm"]) == (t, p) and r["converged"]}
        if 0.0 in by and 90.0 in by:
            out.append({"thickness_mm": t, "pitch_mm": p, "mode_0": by[0.0]["mode"], "mode_90": by[90.0]["mode"],
                        "ratio_0": _along_over_across(by[0.0]), "ratio_90": _along_over_across(by[90.0]),
                        "modes_differ": by[0.0]["mode"] != by[90.0]["mode"]})
    return out


def markdown_table(rows: list) -> str:
    """One line per (thickness, pitch) at seed 0; other seeds' modes, where run, in the last column."""
    lines = ["| thickness (mm) | pitch (mm) | course 0 deg: along/across, mode | course 90 deg: along/across, mode | "
             "modes differ | other seeds (0 / 90 deg modes) |", "|---|---|---|---|---|---|"]
    seeds = sorted({r.get("seed", 0) for r in rows} - {0})
    other = {sd: {(s["thickness_mm"], s["pitch_mm"]): s for s in summarise(rows, sd)} for sd in seeds}
    for s in summarise(rows):
        key = (s["thickness_mm"], s["pitch_mm"])
        more = "; ".join(f"seed {sd}: {other[sd][key]['mode_0']} / {other[sd][key]['mode_90']}"
                         for sd in seeds if key in other[sd])
        lines.append(f"| {s['thickness_mm']:g} | {s['pitch_mm']:g} | {s['ratio_0']:.2f}, {s['mode_0']} | "
                     f"{s['ratio_90']:.2f}, {s['mode_90']} | {'yes' if s['modes_differ'] else 'no'} | {more} |")
    return "\n".join(lines)


def main(argv=None):
    from shellfem.memory import keep_freed_memory
    keep_freed_memory()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--thickness", type=float, nargs="+", default=[0.2, 0.4, 0.8, 1.2])
    ap.add_argument("--pitch", type=float, nargs="+", default=[3.0, 6.0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="solver seeds (symmetry-breaking perturbation)")
    ap.add_argument("--max-iterations", type=int, default=600)
    ap.add_argument("--out", default="docs/gallery/ortho_sweep")
    ap.add_argument("--table", action="store_true", help="print the Markdown table of OUT/rows.jsonl and stop")
    a = ap.parse_args(argv)
    path = os.path.join(a.out, "rows.jsonl")
    rows = []
    if os.path.exists(path):
        with open(path) as f:
            rows = [json.loads(line) for line in f if line.strip()]
    if a.table:
        print(markdown_table(rows))
        return
    os.makedirs(a.out, exist_ok=True)
    done = {(r["thickness_mm"], r["pitch_mm"], r["course_deg"], r.get("seed", 0)) for r in rows}
    for sd in a.seeds:
        for t in a.thickness:
            for p in a.pitch:
                for c in (0.0, 90.0):
                    if (t, p, c, sd) in done:
                        continue
                    row = simulate_case(t, p, c, a.max_iterations, seed=sd)
                    rows.append(row)
                    with open(path, "a") as f:
                        f.write(json.dumps(row) + "\n")
    with open(os.path.join(a.out, "table.md"), "w") as f:
        f.write(markdown_table(rows) + "\n")
    print(json.dumps({"rows": rows, "summary": summarise(rows)}))


if __name__ == "__main__":
    main()
