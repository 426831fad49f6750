"""Fabric outlines and printed polygons as validated shapely Polygons (printed-state mm).

Shapes: ``rectangle`` (origin at (0, 0)), ``disk`` (centred at (0, 0), polygonised),
``hexagon`` (centred at (0, 0), a vertex on +x) and ``polygon`` (a simple polygon from a
point list, any orientation); :func:`with_holes` cuts polygons out of any of them (fabric with
holes). ``polygon`` is also the validator used for every printed [[region]]: bad input raises
SelfshapeError with a one-line message naming ``where``; detail below geometry.schema.DETAIL_MM
(0.1 um) is dropped.
"""
from __future__ import annotations

import math
import re

import numpy as np
import shapely
from shapely.geometry import Polygon

from geometry.schema import COORD_MAX_MM, DETAIL_MM
from shellfem.errors import SelfshapeError


def rectangle(width: float, height: float) -> Polygon:
    """[0, width] x [0, height] (mm), counter-clockwise."""
    return Polygon([(0.0, 0.0), (width, 0.0), (width, height), (0.0, height)])


def disk_segments(radius: float, segment_mm: float, min_segments: int = 48) -> int:
    """Number of polygon edges so that each edge is about ``segment_mm`` long."""
    return int(max(min_segments, math.ceil(2.0 * math.pi * radius / max(segment_mm, 1e-9))))


def disk(radius: float, segment_mm: float = 1.0) -> Polygon:
    """Regular polygon inscribed in the circle of ``radius`` (mm) centred at (0, 0).

    The edge length is about ``segment_mm`` (use the mesh size, so that polygon
    vertices and mesh boundary nodes coincide; at least 48 edges).
    """
    n = disk_segments(radius, segment_mm)
    t = 2.0 * np.pi * np.arange(n) / n
    return Polygon(np.column_stack([radius * np.cos(t), radius * np.sin(t)]))


def hexagon(side: float) -> Polygon:
    """Regular hexagon of the given side length (mm) centred at (0, 0), a vertex on +x."""
    t = np.pi / 3.0 * np.arange(6)
    return Polygon(np.column_stack([side * np.cos(t), side * np.sin(t)]))


def _location(reason: str) -> str:
    m = re.search(r"\[\s*([-+0-9.eE]+)\s+([-+0-9.eE]+)\s*\]", reason)
    if not m:
        return ""
    return f" at ({float(m.group(1)):.6g}, {float(m.group(2)):.6g})"


def as_points(value, where: str, min_points: int = 1, dim: int = 2) -> np.ndarray:
    """A list of [x, y] pairs (or [x, y, z] with dim=3) as a finite (k, dim) float array,
    every coordinate within +-COORD_MAX_MM (10 m: a larger value is a typo, and 1e300 would
    overflow areas and mesh sizes downstream). Bools and strings are never coordinates."""
    try:
        if isinstance(value, (str, bytes)) or any(isinstance(v, (str, bytes, bool)) for row in value for v in row):
            raise TypeError
        a = np.array(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise SelfshapeError(f"{where} must be a list of [{', '.join('xyz'[:dim])}] points, got {value!r:.80}") from None
    if a.ndim != 2 or a.shape[1] != dim:
        raise SelfshapeError(f"{where} must be a list of [{', '.join('xyz'[:dim])}] points, got {value!r:.80}")
    if len(a) < min_points:
        raise SelfshapeError(f"{where} needs at least {min_points} points, got {len(a)}")
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise SelfshapeError(f"{where}: point {i + 1} {value[i]!r:.80} is not finite")
    far = np.abs(a).max(axis=1) > COORD_MAX_MM
    if far.any():
        i = int(np.argmax(far))
        raise SelfshapeError(f"{where}: point {i + 1} has a coordinate {np.abs(a[i]).max():.3g} mm beyond "
                             f"+-{COORD_MAX_MM:g} mm (10 m)")
    return a


def polygon(points, where: str = "polygon") -> Polygon:
    """A validated simple polygon from (k, 2) points, any orientation, closing point optional.

    Raises SelfshapeError naming ``where`` if there are fewer than 3 distinct points, a
    non-finite coordinate, zero area or a self-intersection (with its location).
    """
    p = as_points(points, f"{where}: polygon", min_points=1)
    keep = np.ones(len(p), bool)
    keep[1:] = np.any(p[1:] != p[:-1], axis=1)      # drop consecutive duplicates
    p = p[keep]
    if len(p) > 1 and np.all(p[0] == p[-1]):
        p = p[:-1]
    if len(p) < 3:
        raise SelfshapeError(f"{where}: polygon needs at least 3 distinct points, got {len(p)}")
    poly = Polygon(p)
    if not poly.is_valid:
        reason = shapely.is_valid_reason(poly)
        if "elf-intersection" in reason:
            raise SelfshapeError(f"{where}: polygon is self-intersecting{_location(reason)}")
        raise SelfshapeError(f"{where}: polygon is invalid ({reason})")
    scale = float(np.max(np.ptp(p, axis=0)))
    if poly.area <= 1e-12 * max(scale, 1e-300) ** 2:
        raise SelfshapeError(f"{where}: polygon has zero area")
    poly = without_detail(poly)                 # detail below DETAIL_MM is none
    return shapely.orient_polygons(poly) if hasattr(shapely, "orient_polygons") else shapely.geometry.polygon.orient(poly)


def with_holes(shape: Polygon, holes, where: str = "holes", min_bridge_mm: float = 0.1) -> Polygon:
    """``shape`` (a simple Polygon, mm) with the polygons of ``holes`` (a list of point lists,
    each validated as :func:`polygon`) cut out: the fabric with holes. Each hole lies inside the
    shape, and the fabric left between a hole and the edge or another hole is at least
    ``min_bridge_mm`` wide (a hole touching the edge is a notch: put it into the outline; a
    narrower bridge would be a thread the mesh cannot resolve). Raises SelfshapeError naming
    ``where`` and the hole (1-based) otherwise."""
    if isinstance(holes, (str, bytes, dict)) or not isinstance(holes, (list, tuple)):
        raise SelfshapeError(f"{where} must be a list of polygons (each a list of [x, y] points), got {holes!r:.80}")
    if not holes:
        return shape
    polys = [polygon(h, f"{where}[{i + 1}]") for i, h in enumerate(holes)]
    edge = shape.exterior
    for i, h in enumerate(polys):
        if not shape.covers(h):
            far = h.difference(shape)
            at = (far if not far.is_empty else h).representative_point()
            raise SelfshapeError(f"{where}[{i + 1}]: the hole is not inside the fabric (near ({at.x:.4g}, {at.y:.4g})); "
                                 f"a cut through the edge belongs in the outline")
        gap = float(edge.distance(h.exterior))
        if gap < min_bridge_mm:
            raise SelfshapeError(f"{where}[{i + 1}]: the hole is {gap:.3g} mm from the fabric's edge; at least "
                                 f"{min_bridge_mm:g} mm of fabric must stay between them (a cut through the edge "
                                 f"belongs in the outline)")
    for i in range(len(polys)):
        for j in range(i + 1, len(polys)):
            gap = float(polys[i].distance(polys[j])) if not polys[i].intersects(polys[j]) else 0.0
            if gap < min_bridge_mm:
                how = "overlaps" if polys[i].intersects(polys[j]) and polys[i].intersection(polys[j]).area > 0 else \
                    f"is {gap:.3g} mm from"
                raise SelfshapeError(f"{where}[{j + 1}]: the hole {how} hole {i + 1}; at least {min_bridge_mm:g} mm of "
                                     f"fabric must stay between holes (merge overlapping holes into one polygon)")
    out = Polygon(np.asarray(edge.coords), [np.asarray(h.exterior.coords) for h in polys])
    if not out.is_valid:                # not expected after the checks above
        raise SelfshapeError(f"{where}: the fabric with its holes is not a valid polygon ({shapely.is_valid_reason(out)})")
    return shapely.orient_polygons(out) if hasattr(shapely, "orient_polygons") else shapely.geometry.polygon.orient(out)


def _ring_without_detail(xy: np.ndarray, tol: float) -> np.ndarray:
    """The vertices of a closed ring (k, 2), without its repeated end, that stay when every
    vertex closer than ``tol`` to the segment between its two neighbours is dropped: in passes
    over alternate vertices (never two neighbours at once), until a pass drops nothing. Each
    pass is one vectorised sweep (no recursion: GEOS's Douglas-Peucker simplify recursed once
    per vertex of a zig-zag and crashed the process at 60,000 vertices); a dropped vertex is
    within ~tol of the kept ring (a few tol after many passes on a pathological ring)."""
    idle, parity = 0, 0
    while len(xy) > 3 and idle < 2:
        a, b = np.roll(xy, 1, axis=0), np.roll(xy, -1, axis=0)
        ab = b - a
        L2 = np.einsum("ij,ij->i", ab, ab)
        t = np.clip(np.einsum("ij,ij->i", xy - a, ab) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
        near = np.hypot(*(xy - a - t[:, None] * ab).T) < tol
        drop = near & (np.arange(len(xy)) % 2 == parity)
        if len(xy) % 2:
            drop[-1] = False            # the last and the first are neighbours of one parity
        k = int(drop.sum())
        if len(xy) - k < 3:
            break
        xy = xy[~drop]
        idle = 0 if k else idle + 1
        parity ^= 1
    return xy


def without_detail(geom, tol: float = DETAIL_MM):
    """A Polygon or MultiPolygon without vertices within ``tol`` (mm, default
    geometry.schema.DETAIL_MM) of their neighbours' segment (see _ring_without_detail); the
    kept vertices are original ones (still on any grid the input was snapped to). A part that
    would become invalid (a ring touching itself) is kept as it was."""
    if geom.is_empty or geom.geom_type not in ("Polygon", "MultiPolygon"):
        return geom
    out = []
    for part in shapely.get_parts(geom):
        rings = [_ring_without_detail(np.asarray(r.coords)[:-1, :2], tol) for r in [part.exterior, *part.interiors]]
        if sum(len(r) for r in rings) == shapely.get_num_coordinates(part) - 1 - len(part.interiors):
            out.append(part)                                    # nothing dropped
            continue
        new = Polygon(rings[0], rings[1:])
        out.append(new if new.is_valid and not new.is_empty else part)
    return out[0] if geom.geom_type == "Polygon" else shapely.MultiPolygon(out)


def check_inside(outline: Polygon, geom, where: str, what: str = "polygon") -> None:
    """Raise SelfshapeError unless ``geom`` lies inside ``outline`` (up to 1e-9 of its size)."""
    tol = 1e-9 * max(1.0, math.sqrt(outline.area))
    if outline.buffer(tol).covers(geom):
        return
    outside = geom.difference(outline)
    at = outside.representative_point() if not outside.is_empty else geom.representative_point()
    if outline.interiors and Polygon(outline.exterior).buffer(tol).covers(geom):
        how = "lies in a hole of the fabric" if not geom.intersects(outline) else "crosses a hole of the fabric"
    else:
        how = "is outside the fabric" if not geom.intersects(outline) else "crosses the fabric outline"
    raise SelfshapeError(f"{where}: {what} {how} ({outside.area:.3g} mm^2 outside, e.g. near ({at.x:.4g}, {at.y:.4g}))")
