"""Meshing benchmark: two large patterns, one JSON line.

ribbons: 800 staggered 15 x 1.5 mm ribbons on a 200 x 200 mm fabric (80 rows 2.5 mm
apart, 10 ribbons per row every 20 mm, odd rows shifted by 10 mm, clipped at the edge).
stars: a ~300-star tiling (spacing 10 mm, arms 7 x 0.8 mm) on a 160 x 160 mm fabric.
Both with 2 mm fabric size. Per case: element count, pattern load and mesh times (wall
and CPU: on a shared machine wall time includes waiting for a core),
vertices, triangles, min angle and the share of triangles with a min angle < 30 deg.
Target: < 10 s per case. Run: python -m validation.bench_meshing
"""
from __future__ import annotations

import json
import time

from geometry.mesh_quality import mesh_quality
from geometry.meshing import mesh_pattern
from geometry.patterns import load_pattern


def ribbons_pattern(rows: int = 80, per_row: int = 10, length: float = 15.0, width: float = 1.5,
                    side: float = 200.0, size_mm: float = 2.0) -> dict:
    ribbons = []
    pitch_y, pitch_x = side / rows, side / per_row
    for i in range(rows):
        y = pitch_y * (i + 0.5)
        x0 = 0.5 * (pitch_x - length) + (0.5 * pitch_x if i % 2 else 0.0)
        for j in range(per_row):
            x = x0 + j * pitch_x
            ribbons.append({"path": [[x, y], [x + length, y]], "width_mm": width, "thickness_mm": 0.4})
    return {"fabric": {"rectangle": [side, side]}, "ribbon": ribbons, "mesh": {"size_mm": size_mm}}


def stars_pattern(side: float = 160.0, size_mm: float = 2.0) -> dict:
    return {"fabric": {"rectangle": [side, side]},
            "stars": {"spacing_mm": 10.0, "arm_length": 0.7, "thickness_mm": 0.3, "arm_width_mm": 0.8},
            "mesh": {"size_mm": size_mm}}


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


def main() -> dict:
    out = {"ribbons_800": run_case(ribbons_pattern()), "stars_300": run_case(stars_pattern())}
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
