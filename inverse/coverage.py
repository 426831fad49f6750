"""Printed-area fraction (ribbon coverage) of a ribbon layout, and the coverage Eq. 5.15 asks for.

A staggered dashed pattern with dash length l_r, width w_r, dash period mu1 and row spacing mu2
covers the fraction l_r w_r / (mu1 mu2) of the fabric (one dash per mu1 x mu2 cell);
`asked_coverage` gives it from the stretches through Eq. 5.15 (inverse.spacing.ribbon_spacing).
`printed_fraction` measures what a layout realises: the area of the union of the printed
ribbon polygons (flat ends, geometry.patterns.ribbon_polygon) inside a window around each
sample point, divided by the window's area inside the fabric region. Exact polygon areas
(shapely); the disk window is a 4 * quad_segs-gon. Units mm.
"""
from __future__ import annotations

import numpy as np

from geometry.meshops import signed_areas
from inverse.spacing import ribbon_spacing
from shellfem.errors import SelfshapeError


def asked_coverage(sigma1, sigma2, s: float, ribbon_length: float = 15.0, ribbon_width: float = 1.5) -> np.ndarray:
    """Printed area fraction l_r w_r / (mu1 mu2) of the staggered pattern Eq. 5.15 lays out for
    the stretches (sigma1 along, sigma2 across the ribbons; 1 <= sigma < s)."""
    mu1, mu2 = ribbon_spacing(sigma1, sigma2, s, ribbon_length, ribbon_width)
    return ribbon_length * ribbon_width / (mu1 * mu2)


def ribbon_union(ribbons):
    """Union of the printed polygons of Ribbon records (path, width_mm), flat ends."""
    import shapely

    from geometry.patterns import ribbon_polygon

    if not ribbons:
        return shapely.Polygon()
    return shapely.union_all([ribbon_polygon(np.asarray(r.path, float), float(r.width_mm)) for r in ribbons])


def printed_fraction(printed, region, points, radius: float, window: str = "disk", quad_segs: int = 16) -> np.ndarray:
    """Fraction of region ∩ window(p) covered by ``printed`` for each point p (k, 2).

    printed: a shapely (Multi)Polygon (e.g. ribbon_union) or a list of Ribbon records; region:
    the fabric (shapely polygon or (k, 2) outline); window: "disk" of the given radius or
    "square" (axis-aligned, side 2 radius). Points whose window misses the region get NaN."""
    import shapely

    if window not in ("disk", "square"):
        raise SelfshapeError(f"printed_fraction: window must be 'disk' or 'square', got {window!r}")
    if not (np.isfinite(radius) and radius > 0):
        raise SelfshapeError(f"printed_fraction: radius must be > 0, got {radius}")
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if not isinstance(printed, shapely.Geometry):
        printed = ribbon_union(list(printed))
    if not isinstance(region, shapely.Geometry):
        region = shapely.Polygon(np.asarray(region, dtype=float))
    if window == "disk":
        win = shapely.buffer(shapely.points(pts), radius, quad_segs=quad_segs)
    else:
        win = shapely.box(pts[:, 0] - radius, pts[:, 1] - radius, pts[:, 0] + radius, pts[:, 1] + radius)
    fab = shapely.intersection(win, region)
    a_fab = shapely.area(fab)
    shapely.prepare(printed)
    a_pr = shapely.area(shapely.intersection(fab, printed))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(a_fab > 0, a_pr / np.where(a_fab > 0, a_fab, 1.0), np.nan)


def printed_over_asked(d) -> float:
    """Printed area of a design's ribbons (inside its outline) over the printed area Eq. 5.15 asks
    for on its flat mesh (asked coverage at the stretches clamped into the bounds, integrated
    over the flat faces): 1 when the layout prints what the flattening's bounds assume, less
    where clipping, trimming, separation or the dash placement thin the pattern."""
    import shapely

    from geometry.flattening import project_stretches
    s1, s2 = project_stretches(d.flat.sigma1, d.flat.sigma2, d.bounds)
    area = np.abs(signed_areas(d.flat.uv, d.F))
    asked = float(np.sum(area * asked_coverage(s1, s2, d.stretch)))
    printed = float(shapely.intersection(ribbon_union(d.ribbons), d.fabric_polygon()).area)
    return printed / asked if asked > 0 else float("nan")
