"""Seed section 4.1 in silico: parallel ribbons printed at 0 and at 90 degrees to the fabric's
course direction, over ribbon thickness and spacing, on the orthotropic fabric model.

The seed printed the same parallel-ribbon pattern in two orientations and saw the samples
bend about different axes *relative to the ribbons*; it attributes this to the fabric's
orthotropy. For each (thickness, pitch) this study simulates the pattern of
`validation.cases.parallel_ribbons` (60 x 40 mm, ribbons 1.5 mm wide along x, s = 1.35,
TPU 72.3 MPa, orthotropic log-barrier fabric with its fitted parameters) with the course
direction at 0 and at 90 degrees to the ribbons and measures the median curvature along and
across the ribbons over the inner 60 % of the sheet. The mode is "along" when
|kappa_along| > |kappa_across|. The seed's effect is reproduced at a (thickness, pitch) where
the two orientations give different modes (validation.ribbon_modes).

Each case is appended to OUT/rows.jsonl as soon as it is done (a rerun skips cases already
there); OUT/table.md is the comparison table; prints ONE JSON line with all rows and, per
(thickness, pitch), whether the modes differ.

Run: python studies/ortho_sweep.py [--thickness 0.2 0.4 0.8 1.2] [--pitch 3 6] [--seeds 0]
                                    [--out docs/gallery/ortho_sweep] [--table]
"""
from __future__ import annotations

import argparse
import json
import os
import time

from validation.cases import ortho_ribbons
from validation.measures import gallery_measure
from validation.ribbon_modes import markdown_table, summarise


def simulate_case(thickness_mm: float, pitch_mm: float, course_deg: float, max_iterations: int = 600,
                  seed: int = 0) -> dict:
    from geometry.patterns import load_pattern
    from forward.simulate import simulate
    pat = load_pattern(ortho_ribbons(thickness_mm, pitch_mm, course_deg, seed))
    t0 = time.perf_counter()
    sim = simulate(pat, max_iterations=max_iterations)
    m = gallery_measure("ortho_0", sim)
    along, across = m["curvature_along_ribbons"], m["curvature_across_ribbons"]
    return {"thickness_mm": thickness_mm, "pitch_mm": pitch_mm, "course_deg": course_deg, "seed": int(seed),
            "converged": bool(sim.result.converged), "newton_iterations": int(sim.result.iterations),
            "n_vertices": int(sim.sheet.n_vertices), "wall_s": round(time.perf_counter() - t0, 1),
            "kappa_along_per_mm": along, "kappa_across_per_mm": across, "twist_per_mm": m["twist"],
            "mode": "along" if abs(along) > abs(across) else "across"}


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
