"""The seed's chapter 3 tiling: 3-pointed stars on a hexagonal lattice (printed-state mm).

Star centres are the nodes of a triangular ("hexagonal") lattice of spacing d with
basis d (cos a, sin a), d (cos(a + 60), sin(a + 60)) through ``origin`` (default: the
outline's centroid); only centres inside the fabric carry a star. The three arms point
along the lattice axes at a, a + 120 and a + 240 degrees, so an arm of length d (fraction
1) just reaches the next centre. Arm length (fraction of d in [0, 1], 0 = no star),
plastic thickness and arm width are fields of (x, y, r) evaluated at the star centre,
r being the distance to the outline's centroid. Each star is one PrintedElement: the
union of its three arm rectangles (square ends), clipped to the fabric.
"""
from __future__ import annotations

import math

import numpy as np
import shapely
from shapely.geometry import Polygon

from geometry.elements import PrintedElement
from geometry.expressions import evaluate_field
from geometry.schema import MAX_STARS, MIN_ARM_MM, PATTERN_NUMBERS
from shellfem.errors import SelfshapeError

SQRT3 = math.sqrt(3.0)


def lattice_points(outline: Polygon, spacing: float, origin=None, angle_deg: float = 0.0):
    """Triangular-lattice nodes inside ``outline``: (k, 2) centres and (k, 2) integer indices (i, j).

    Node (i, j) = origin + i a1 + j a2, a1 = d (cos a, sin a), a2 = d (cos(a+60), sin(a+60)).
    Centres on the outline (within 1e-9 of its size) count as inside.
    """
    c = outline.centroid
    o = np.array([c.x, c.y] if origin is None else origin, dtype=float)
    a = math.radians(angle_deg)
    basis = spacing * np.array([[math.cos(a), math.sin(a)], [math.cos(a + math.pi / 3), math.sin(a + math.pi / 3)]])
    xmin, ymin, xmax, ymax = outline.bounds
    corners = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]]) - o
    ij = corners @ np.linalg.inv(basis)            # lattice coordinates of the bounding box
    lo, hi = np.floor(ij.min(axis=0)) - 1, np.ceil(ij.max(axis=0)) + 1
    i, j = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
    idx = np.column_stack([i.ravel(), j.ravel()]).astype(np.int64)
    pts = o + idx @ basis
    tol = 1e-9 * max(1.0, math.sqrt(outline.area))
    inside = shapely.contains_xy(outline.buffer(tol), pts[:, 0], pts[:, 1])
    return pts[inside], idx[inside]


def star_polygons(centres, arm_lengths, arm_widths, angle_deg: float = 0.0) -> np.ndarray:
    """Array of shapely Polygons: 3-armed stars (arms at a, a+120, a+240 deg, square ends).

    The outline of the union of the three rectangles [0, L] x [-w/2, w/2] is, per arm,
    the two tip corners and then the re-entrant corner towards the next arm, at
    w/(2 sqrt 3) along the arm and w/2 across it. Short arms (L <= w/(2 sqrt 3)) fall
    back to an explicit union.
    """
    c = np.asarray(centres, float).reshape(-1, 2)
    L = np.broadcast_to(np.asarray(arm_lengths, float), (len(c),))
    w = np.broadcast_to(np.asarray(arm_widths, float), (len(c),))
    th = math.radians(angle_deg) + 2.0 * np.pi / 3.0 * np.arange(3)
    u = np.column_stack([np.cos(th), np.sin(th)])          # (3, 2) arm directions
    n = np.column_stack([-np.sin(th), np.cos(th)])         # left normals
    Lk, wk = L[:, None, None], w[:, None, None]
    tip_r = Lk * u - 0.5 * wk * n
    tip_l = Lk * u + 0.5 * wk * n
    notch = wk / (2.0 * SQRT3) * u + 0.5 * wk * n
    ring = np.stack([tip_r, tip_l, notch], axis=2).reshape(len(c), 9, 2) + c[:, None, :]
    stars = shapely.polygons(ring)
    short = L <= w / (2.0 * SQRT3) * (1.0 + 1e-9)
    for k in np.flatnonzero(short):               # rare: arms shorter than the central blob
        rects = [Polygon(c[k] + np.array([0.0 * u[a] - 0.5 * w[k] * n[a], L[k] * u[a] - 0.5 * w[k] * n[a],
                                          L[k] * u[a] + 0.5 * w[k] * n[a], 0.0 * u[a] + 0.5 * w[k] * n[a]]))
                 for a in range(3)]
        stars[k] = shapely.union_all(rects)
    return stars


def star_elements(outline: Polygon, spacing: float, arm_length, thickness, arm_width, side: str = "front",
                  origin=None, angle_deg: float = 0.0, where: str = "[stars]") -> list[PrintedElement]:
    """The star tiling of ``outline`` as PrintedElements (kind "star"), mm.

    spacing: lattice spacing d (mm). arm_length: fraction of d in [0, 1] (0 omits the star);
    thickness (mm, > 0) and arm_width (mm, > 0): each a number, an expression string in
    x, y, r, or a callable f(x, y, r); evaluated at each star centre.
    Labels are "stars (i, j)" with the lattice indices of the centre.
    """
    try:
        spacing = float(spacing)
    except (TypeError, ValueError):
        raise SelfshapeError(f"{where} spacing_mm must be a number, got {spacing!r}") from None
    if not (math.isfinite(spacing) and spacing > 0):
        raise SelfshapeError(f"{where} spacing_mm must be > 0, got {spacing!r}")
    if side not in ("front", "back"):
        raise SelfshapeError(f"{where} side must be \"front\" or \"back\", got {side!r}")
    # the count is bounded before any lattice or polygon is built (geometry.schema.MAX_STARS)
    if outline.area / (spacing * spacing) > 2 * MAX_STARS:
        raise SelfshapeError(f"{where} spacing_mm = {spacing:g} gives about {outline.area / spacing ** 2:.3g} stars on "
                             f"this fabric, more than the {MAX_STARS:,} a pattern may hold (the mesh budget); use a "
                             f"larger spacing_mm")
    centres, idx = lattice_points(outline, spacing, origin, angle_deg)
    if len(centres) > MAX_STARS:
        raise SelfshapeError(f"{where} spacing_mm = {spacing:g} gives {len(centres):,} stars on this fabric, more than "
                             f"the {MAX_STARS:,} a pattern may hold (the mesh budget); use a larger spacing_mm")
    if len(centres) == 0:          # never a silent empty print
        raise SelfshapeError(f"{where} no lattice node lies inside the fabric (spacing_mm = {spacing:g}); "
                             f"use a smaller spacing or move origin")
    c = outline.centroid
    x, y = centres[:, 0], centres[:, 1]
    xr, yr = np.round(x, 9) + 0.0, np.round(y, 9) + 0.0        # for messages
    r = np.hypot(x - c.x, y - c.y)
    frac = evaluate_field(arm_length, x, y, r, f"{where} arm_length")
    h = evaluate_field(thickness, x, y, r, f"{where} thickness_mm")
    w = evaluate_field(arm_width, x, y, r, f"{where} arm_width_mm")
    ok = (frac >= 0) & (frac <= 1)
    if not ok.all():
        k = int(np.argmin(ok))
        raise SelfshapeError(f"{where} arm_length is {frac[k]:.4g} at the star centred at ({xr[k]:.4g}, {yr[k]:.4g});"
                             " it must be a fraction of spacing_mm in [0, 1]")
    keep = frac > 0
    short = keep & (frac * spacing < MIN_ARM_MM)
    if short.any():
        k = int(np.argmax(short))
        raise SelfshapeError(f"{where} arm_length gives a {frac[k] * spacing:.3g} mm arm at the star centred at "
                             f"({xr[k]:.4g}, {yr[k]:.4g}); a printed arm is at least {MIN_ARM_MM:g} mm "
                             f"(0 omits the star)")
    for name, v in (("thickness_mm", h), ("arm_width_mm", w)):
        spec = PATTERN_NUMBERS["stars"][name]          # the schema's physical range (geometry.schema)
        bad = keep & ~((v >= spec.lo) & (v <= spec.hi))
        if bad.any():
            k = int(np.argmax(bad))
            raise SelfshapeError(f"{where} {name} is {v[k]:.4g} at the star centred at ({xr[k]:.4g}, {yr[k]:.4g}); "
                                 f"it must be in {spec.describe()}")
    centres, idx, frac, h, w = centres[keep], idx[keep], frac[keep], h[keep], w[keep]
    geoms = star_polygons(centres, frac * spacing, w, angle_deg)
    inside = shapely.within(geoms, outline)
    if not inside.all():
        geoms[~inside] = shapely.intersection(geoms[~inside], outline)
    th = math.radians(angle_deg) + 2.0 * np.pi / 3.0 * np.arange(3)
    u = np.column_stack([np.cos(th), np.sin(th)])
    tips = centres[:, None, :] + (frac * spacing)[:, None, None] * u[None]          # (k, 3, 2) arm tips
    elements = []
    for k in np.flatnonzero(~shapely.is_empty(geoms) & (shapely.area(geoms) > 0)):
        arms = [np.stack([centres[k], tips[k, a]]) for a in range(3)]
        elements.append(PrintedElement(geometry=geoms[k], thickness_mm=float(h[k]), side=side, kind="star",
                                       label=f"stars ({idx[k, 0]}, {idx[k, 1]})", centrelines=arms,
                                       width_mm=float(w[k])))
    return elements
