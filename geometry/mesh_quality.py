"""Quality measures of a triangle mesh (Sheet): counts, angles (deg), areas (mm^2), edge lengths (mm)."""
from __future__ import annotations

import numpy as np

from geometry.meshops import signed_areas, triangle_angles, unique_edges
from shellfem.sheet import Sheet


def mesh_quality(sheet: Sheet) -> dict:
    """Counts, angles (deg), areas (mm^2) and edge lengths (mm) of a Sheet."""
    ang = triangle_angles(sheet.points, sheet.triangles)
    area = np.abs(signed_areas(sheet.points, sheet.triangles))
    e, _, _ = unique_edges(sheet.triangles)
    L = np.linalg.norm(sheet.points[e[:, 0]] - sheet.points[e[:, 1]], axis=1)
    tmin = ang.min(axis=1)
    printed = sheet.printed
    return dict(
        n_vertices=int(sheet.n_vertices), n_triangles=int(sheet.n_triangles),
        n_regions=int(len(np.unique(sheet.region[sheet.region > 0]))),
        min_angle_deg=float(tmin.min()), max_angle_deg=float(ang.max()),
        mean_min_angle_deg=float(tmin.mean()), pct_min_angle_below_30=float(100.0 * (tmin < 30).mean()),
        area_mm2=float(area.sum()), printed_area_mm2=float(area[printed].sum()),
        edge_min_mm=float(L.min()), edge_median_mm=float(np.median(L)), edge_max_mm=float(L.max()),
    )
