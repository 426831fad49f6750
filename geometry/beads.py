"""Bead geometry: what extruded G-code segments deposit on the fabric (printed-state mm).

Bead model (Slic3r's flow): a bead of width w and height h has the cross-section
(w - h) h + pi h^2 / 4 (a rectangle with semicircular sides, needs w >= h); a segment of
length L that deposits filament length E of diameter d has A = E pi d^2 / (4 L), so
w = A / h + h (1 - pi / 4). ``;WIDTH:`` hints, when present, give w directly.

Consecutive segments of one path with similar width and the same height form a *run*,
buffered into one bead polygon. Beads stacked over several layers are overlaid into
connected pieces of constant thickness (the sum of the layer heights covering them): one
PrintedElement per piece.
"""
from __future__ import annotations

import math

import numpy as np
import shapely

from geometry.elements import PrintedElement
from shellfem.errors import SelfshapeError

#: Widest (and highest) bead a G-code move may make, mm: the ;WIDTH: / ;HEIGHT: hints and the
#: width the deposited volume implies. No FDM nozzle lays a bead near 100 mm.
MAX_BEAD_MM = 100.0


def bead_area(width_mm, height_mm):
    """Cross-section (mm^2) of an extruded bead: a rectangle with semicircular sides
    (Slic3r's flow model), area = (w - h) h + pi h^2 / 4. Needs w >= h. Vectorised."""
    return (width_mm - height_mm) * height_mm + math.pi * height_mm * height_mm / 4.0


def bead_width(area_mm2, height_mm):
    """Inverse of :func:`bead_area`: the width (mm) of a bead of given cross-section
    and height. Vectorised."""
    return area_mm2 / height_mm + height_mm * (1.0 - math.pi / 4.0)


def segment_widths(seg, heights, filament_diameter_mm):
    """Bead width (mm) per segment: the ;WIDTH: hint or the bead model inverted from the
    deposited volume. heights: (n,) layer heights (mm). Vectorised."""
    length = np.hypot(seg["x1"] - seg["x0"], seg["y1"] - seg["y0"])
    area = seg["e_mm"] * (math.pi * filament_diameter_mm ** 2 / 4.0) / length
    w_volume = bead_width(area, heights)
    hint = seg["width_hint"]
    return np.where(np.isfinite(hint), hint, w_volume), w_volume, length


def _runs(seg, widths, heights, rel_tol=0.05):
    """Run id per segment: consecutive segments of one path with similar width and the same height."""
    n = len(seg)
    brk = np.ones(n, dtype=bool)
    if n > 1:
        same = ((seg["path"][1:] == seg["path"][:-1])
                & (np.abs(widths[1:] - widths[:-1]) <= rel_tol * widths[:-1])
                & (heights[1:] == heights[:-1]))
        brk[1:] = ~same
    return np.cumsum(brk) - 1, brk


def _thin(parts, min_feature):
    """Mask of polygons thinner than min_feature (2 area / perimeter), i.e. overlay slivers."""
    a = shapely.area(parts)
    p = shapely.length(parts)
    return 2 * a < min_feature * np.maximum(p, 1e-300)


def printed_elements(seg, p0, p1, heights, filament_diameter_mm, min_width_mm, cap, side, name):
    """The printed elements of extruded segments, in print order, and the run statistics.

    seg: segments (geometry.gcode.SEGMENT_DTYPE), p0, p1 (k, 2) their end points in pattern
    coordinates (mm), heights (k,) their layer heights (mm). Runs narrower than min_width_mm
    are dropped; cap: "square", "round" or "flat" bead ends; side, name: for the elements and
    their labels. Returns (elements, info) with info: widths and w_volume (k,) per segment
    (effective and from the deposited volume), path_widths_mm (runs,), n_runs,
    dropped_thin_paths.
    """
    widths, w_volume, length = segment_widths(seg, heights, filament_diameter_mm)
    run, first = _runs(seg, widths, heights)
    n_runs = int(run[-1]) + 1
    run_len = np.bincount(run, length, n_runs)
    run_w = np.bincount(run, widths * length, n_runs) / run_len
    run_h = heights[first]
    run_layer = seg["layer"][first]
    run_line = seg["line"][first]
    run_path = seg["path"][first]

    # one polyline per run
    start_idx = np.flatnonzero(first)
    pos1 = np.arange(len(seg)) + run + 1
    coords = np.empty((len(seg) + n_runs, 2))
    coords[pos1] = p1
    coords[start_idx + np.arange(n_runs)] = p0[start_idx]
    counts = np.bincount(run, minlength=n_runs) + 1
    # canonical direction (lexicographically smaller end first): equal paths buffer equally
    ends_idx = np.cumsum(counts)
    beg_idx = ends_idx - counts
    a, b = coords[beg_idx], coords[ends_idx - 1]
    flip = (a[:, 0] > b[:, 0]) | ((a[:, 0] == b[:, 0]) & (a[:, 1] > b[:, 1]))
    order = np.arange(len(coords))
    rid = np.repeat(np.arange(n_runs), counts)
    local = order - beg_idx[rid]
    order = np.where(flip[rid], beg_idx[rid] + counts[rid] - 1 - local, order)
    lines = shapely.linestrings(coords[order], indices=rid)

    keep = run_w >= min_width_mm
    if not keep.any():
        raise SelfshapeError(f"{name}: line {seg['line'][0]}: every extruded path is thinner than "
                             f"min_width_mm = {min_width_mm:g} mm")
    # E1e12 on a 30 mm move made a 1e11 mm bead and a fabric to match (exit 0); under a ;WIDTH:
    # hint the hint was drawn and the absurd E ignored: the file contradicts itself either way
    wide = np.flatnonzero(~(np.maximum(widths, w_volume) <= MAX_BEAD_MM))
    if len(wide):
        k = int(wide[0])
        raise SelfshapeError(f"{name}: line {int(seg['line'][k])}: the extrusion deposits a bead {w_volume[k]:.4g} mm "
                             f"wide (more than {MAX_BEAD_MM:g} mm): E is not filament mm of diameter "
                             f"{filament_diameter_mm:g} mm (volumetric E, or a wrong filament_diameter)")
    beads = shapely.buffer(lines[keep], run_w[keep] / 2.0, cap_style=cap, join_style="round", quad_segs=8) \
        if shapely.is_simple(lines[keep]).all() else _beads(lines[keep], run_w[keep], cap)
    r_layer, r_h, r_line, r_path = run_layer[keep], run_h[keep], run_line[keep], run_path[keep]

    pieces = stack_beads(beads, r_layer, r_h, sliver=0.2 * min_width_mm)
    elements = _elements(pieces, beads, r_line, r_path, side, name)
    return elements, dict(widths=widths, w_volume=w_volume, path_widths_mm=run_w, n_runs=n_runs,
                          dropped_thin_paths=int((~keep).sum()))


def _beads(lines, widths, cap):
    """Bead polygons of path runs some of which retrace or cross themselves. GEOS buffers a
    self-overlapping line by noding every pair of its overlapping segments (a 2 mm segment
    retraced 1,000 times in a 20 KB file exhausts 4 GB), so such a run is built from its
    distinct segments instead (end points rounded to the 0.001 mm G-code resolution):
    the union of their flat-capped rectangles, discs at the inner vertices (the round
    joins) and the two end segments with the run's cap: the same set as the buffer, at the
    cost of a cascaded union of at most (distinct segments) simple polygons."""
    simple = shapely.is_simple(lines)
    out = np.empty(len(lines), dtype=object)
    out[simple] = shapely.buffer(lines[simple], widths[simple] / 2.0, cap_style=cap, join_style="round", quad_segs=8)
    for k in np.flatnonzero(~simple):
        xy = np.round(shapely.get_coordinates(lines[k]), 3)
        keep = np.r_[True, np.any(xy[1:] != xy[:-1], axis=1)]
        xy = xy[keep]
        r = widths[k] / 2.0
        if len(xy) < 3:         # one segment, retraced: its own bead
            out[k] = shapely.buffer(shapely.linestrings(xy), r, cap_style=cap, quad_segs=8)
            continue
        seg = np.concatenate([xy[:-1], xy[1:]], axis=1)
        flip = (seg[:, 0] > seg[:, 2]) | ((seg[:, 0] == seg[:, 2]) & (seg[:, 1] > seg[:, 3]))
        seg[flip] = seg[flip][:, [2, 3, 0, 1]]
        seg = np.unique(seg, axis=0)
        rects = shapely.buffer(shapely.linestrings(seg.reshape(-1, 2, 2)), r, cap_style="flat", quad_segs=8)
        joints = shapely.buffer(shapely.points(np.unique(xy[1:-1], axis=0)), r, quad_segs=8)
        ends = shapely.buffer(shapely.linestrings([xy[:2], xy[-2:]]), r, cap_style=cap, quad_segs=8)
        out[k] = shapely.union_all(np.concatenate([rects, joints, ends]))
    return out


def stack_beads(beads, layer, height, sliver=0.02):
    """Stacked deposit of beads (shapely polygons, one per path run) with their layer index
    and height (mm): a list of (polygon, thickness_mm), each polygon a connected piece of
    constant thickness = sum of the heights of the layers covering it. Pieces thinner than
    ``sliver`` (2 area / perimeter, mm) are overlay noise and dropped.

    Overlapping beads are grouped first (connected components of the intersection graph),
    so each overlay only sees its own group; a group that is one path printed k times on
    the same footprint (to 1e-4 mm: the usual stacked ribbon) needs no overlay at all.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    m = len(beads)
    a, b = shapely.STRtree(beads).query(beads, predicate="intersects")
    _, comp = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(m, m)), directed=False)
    order = np.argsort(comp, kind="stable")
    bounds = np.flatnonzero(np.r_[True, comp[order][1:] != comp[order][:-1], True])
    out = []
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        idx = order[lo:hi]
        if len(idx) == 1 or (len(np.unique(layer[idx])) == len(idx)
                             and shapely.equals_exact(beads[idx[1:]], beads[idx[0]], tolerance=1e-4).all()):
            out.append((beads[idx[0]], float(np.round(height[idx].sum(), 9))))
        else:
            out.extend(_overlay(beads[idx], layer[idx], height[idx], sliver))
    return out


def _overlay(beads, layer, height, sliver):
    """Overlay the per-layer unions of ``beads`` into connected pieces of constant
    stacked thickness: list of (polygon, thickness)."""
    pieces: dict[float, object] = {}
    h9 = np.round(height, 9)
    for lay, h in sorted(set(zip(layer.tolist(), h9.tolist()))):
        sheet = shapely.union_all(beads[(layer == lay) & (h9 == h)])
        new: dict[float, list] = {}
        for t, g in pieces.items():
            new.setdefault(round(t + h, 9), []).append(shapely.intersection(g, sheet))
            new.setdefault(t, []).append(shapely.difference(g, sheet))
        fresh = shapely.difference(sheet, shapely.union_all(list(pieces.values()))) if pieces else sheet
        new.setdefault(round(h, 9), []).append(fresh)
        pieces = {}
        for t, gs in new.items():
            parts = _polygons(shapely.union_all(gs), sliver)
            if len(parts):
                pieces[t] = shapely.union_all(parts)
    return [(g, t) for t, g in sorted(pieces.items()) for g in _polygons(g, sliver)]


def _polygons(geom, sliver):
    """The polygons of ``geom`` that are not slivers (2 area / perimeter < sliver)."""
    parts = np.asarray(shapely.get_parts(geom))
    parts = parts[shapely.get_type_id(parts) == 3]
    return parts[~_thin(parts, sliver)] if len(parts) else parts


def _elements(pieces, beads, run_line, run_path, side, name):
    """One PrintedElement per piece, ordered by the first source line that prints it;
    the label names the file and the paths that print it."""
    polys = np.array([g for g, _ in pieces], dtype=object)
    thick = [t for _, t in pieces]
    pi_, bi = shapely.STRtree(beads).query(polys, predicate="intersects")
    first_line = np.full(len(polys), np.iinfo(np.int64).max)
    np.minimum.at(first_line, pi_, run_line[bi])
    out = []
    for k in np.argsort(first_line, kind="stable"):
        paths = np.unique(run_path[bi[pi_ == k]])
        shown = ", ".join(str(p) for p in paths[:6]) + (", ..." if len(paths) > 6 else "")
        out.append(PrintedElement(geometry=polys[k], thickness_mm=float(thick[k]), side=side, kind="gcode",
                                  label=f"{name} path{'s' if len(paths) > 1 else ''} {shown}"))
    return out
