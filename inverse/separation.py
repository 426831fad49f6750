"""Ribbon clean-up after the layout: simplified centre lines without tiny segments, and ribbons
kept a gap apart and inside the outline so that the pattern meshes without slivers (mm)."""
from __future__ import annotations

import numpy as np


def clean_path(p: np.ndarray, min_seg: float) -> np.ndarray:
    """Drop interior points closer than ``min_seg`` to the previous kept point, and the last
    interior point if the final segment would be shorter than ``min_seg``: a tiny end segment
    turns the flat end of the printed ribbon askew (and the mesh gets slivers). (k, 2)"""
    if len(p) <= 2:
        return p
    keep = [0]
    for i in range(1, len(p) - 1):
        if np.hypot(*(p[i] - p[keep[-1]])) >= min_seg:
            keep.append(i)
    if len(keep) > 1 and np.hypot(*(p[-1] - p[keep[-1]])) < min_seg:
        keep.pop()
    keep.append(len(p) - 1)
    return p[keep]


def simplify_paths(ribbons, tol_mm: float):
    """Simplify every ribbon centre line within ``tol_mm`` (Douglas-Peucker, in place), then
    drop points closer than 0.25 mm (`clean_path`); a path that would keep < 2 points is left."""
    import shapely

    if not ribbons:
        return
    idx = np.repeat(np.arange(len(ribbons)), [len(r.path) for r in ribbons])
    lines = shapely.simplify(shapely.linestrings(np.concatenate([r.path for r in ribbons]), indices=idx), tol_mm)
    for r, ln in zip(ribbons, lines):
        p = clean_path(np.asarray(shapely.get_coordinates(ln)), 0.25)
        if len(p) >= 2:
            r.path = p


def _longest_line(geom):
    """The longest LineString of a (multi)line geometry (None if there is none)."""
    import shapely

    parts = [g for g in shapely.get_parts(shapely.line_merge(geom) if geom.geom_type == "MultiLineString" else geom)
             if g.geom_type == "LineString" and not g.is_empty]
    return max(parts, key=lambda g: g.length) if parts else None


def separate_ribbons(ribbons, outline, gap_mm: float = 0.5, min_length: float = 2.0):
    """Make the printed ribbons meshable: every ribbon polygon (flat ends) at least ``gap_mm``
    inside the outline (a (k, 2) polygon, or a shapely Polygon with holes) and ``gap_mm`` away
    from every other ribbon (no overlaps, no slivers).

    Centre lines are clipped to the outline eroded by w/2 + gap (then the whole ribbon, which lies
    within w/2 of its centre line, is >= gap inside). Where two ribbons come closer than the gap
    (dashes that meet end to end where sigma1 = 1, stripes merging near singularities), the
    ribbon processed later (shorter ones later) loses the part of its centre line within
    w/2 + gap of the other ribbon; only the longest remaining piece is kept. Pieces shorter than
    ``min_length`` are dropped. Returns (ribbons, {"clipped", "trimmed", "dropped"})."""
    import shapely
    from shapely.geometry import LineString

    from geometry.patterns import ribbon_polygon

    region = outline if isinstance(outline, shapely.Geometry) else shapely.Polygon(outline)
    stats = {"clipped": 0, "trimmed": 0, "dropped": 0}
    inner = {}
    out = []
    for r in ribbons:
        w = float(r.width_mm)
        if w not in inner:
            inner[w] = region.buffer(-(w / 2 + gap_mm))
            shapely.prepare(inner[w])
        line = LineString(r.path)
        if not inner[w].contains(line):
            line = _longest_line(line.intersection(inner[w]))
            stats["clipped"] += 1
            if line is None or line.length < min_length:
                stats["dropped"] += 1
                continue
            r.path = clean_path(np.asarray(line.coords), 0.25)
        out.append(r)
    if not out:
        return out, stats
    polys = np.array([ribbon_polygon(r.path, r.width_mm) for r in out], dtype=object)
    tree = shapely.STRtree(polys)
    a, b = tree.query(polys, predicate="dwithin", distance=gap_mm)
    conflict = np.zeros(len(out), bool)
    conflict[a[a != b]] = True
    lengths = np.array([LineString(r.path).length for r in out])
    order = np.lexsort((np.arange(len(out)), -lengths))
    kept = np.zeros(len(out), bool)
    for i in order:
        if conflict[i]:
            near = tree.query(polys[i], predicate="dwithin", distance=gap_mm)
            near = near[kept[near] & (near != i)]
            if len(near):
                r = out[i]
                block = shapely.union_all([p.buffer(r.width_mm / 2 + gap_mm) for p in polys[near]])
                line = _longest_line(LineString(r.path).difference(block))
                stats["trimmed"] += 1
                if line is None or line.length < min_length:
                    stats["dropped"] += 1
                    continue
                r.path = clean_path(np.asarray(line.coords), 0.25)
                polys[i] = ribbon_polygon(r.path, r.width_mm)
        kept[i] = True
    result = [r for i, r in enumerate(out) if kept[i]]
    for i, r in enumerate(result):
        r.label = f"ribbon[{i}]"
    return result, stats
