"""Meshing benchmark: two large patterns, one JSON line.

ribbons: 800 staggered 15 x 1.5 mm ribbons on a 200 x 200 mm fabric (80 rows 2.5 mm
apart, 10 ribbons per row every 20 mm, odd rows shifted by 10 mm, clipped at the edge).
stars: a ~300-star tiling (spacing 10 mm, arms 7 x 0.8 mm) on a 160 x 160 mm fabric.
Both with 2 mm fabric size. Per case: element count, pattern load and mesh times (wall
and CPU: on a shared machine wall time includes waiting for a core),
vertices, triangles, min angle and the share of triangles with a min angle < 30 deg.
Target: < 10 s per case. --quick: 80 ribbons on 100 x 100 mm and the tiling on 60 x 60 mm.
Run: python studies/bench_meshing.py [--quick]
"""
from __future__ import annotations

import argparse
import json
import time

from geometry.mesh_quality import mesh_quality
from geometry.meshing import mesh_pattern
from geometry.patterns import load_pattern
from validation.cases import staggered_ribbons, star_tiling


def run_case(raw: dict) -> dict:
    t0 = time.perf_counter()
    pattern = load_pattern(raw)
    t1, c1 = time.perf_counter(), time.process_time()
    sheet = mesh_pattern(pattern)
    t2, c2 = time.perf_counter(), time.process_time()
    q = mesh_quality(sheet)
    return {"n_elements": len(pattern.elements), "load_s": round(t1 - t0, 3), "mesh_s": round(t2 - t1, 3),
            "mesh_cpu_s": round(c2 - c1, 3),
            "n_vertices": q["n_vertices"], "n_triangles": q["n_triangles"], "n_regions": q["n_regions"],
            "min_angle_deg": round(q["min_angle_deg"], 2), "pct_min_angle_below_30": round(q["pct_min_angle_below_30"], 3),
            "edge_median_mm": round(q["edge_median_mm"], 3)}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two small cases")
    a = ap.parse_args(argv)
    if a.quick:
        out = {"ribbons_80": run_case(staggered_ribbons(rows=16, per_row=5, side=100.0)),
               "stars_quick": run_case(star_tiling(side=60.0))}
    else:
        out = {"ribbons_800": run_case(staggered_ribbons()), "stars_300": run_case(star_tiling())}
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
