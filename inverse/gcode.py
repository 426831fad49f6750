"""Ribbons -> G-code: what to print and in which order, for an FDM printer printing onto
fabric held in a flippable frame (mm, mm/s, deg C).

Each ribbon (geometry.elements.Ribbon: centre line, width, thickness, side) is printed as
round(thickness / layer height) (>= 1) stacked beads. Layer by layer, the ribbons of a
layer are ordered greedily by nearest endpoint (ties go to the lower ribbon index, then to
the path's start), each printed in the direction that starts at the nearer end. Extrusion
follows the bead model of geometry.beads: filament length E = bead area * length *
multiplier / filament cross-section. The file itself (header, moves, hints, the front/back
frame convention) is geometry.gcode, which also reads it back.
"""
from __future__ import annotations

import math
import os

import numpy as np
from scipy.spatial import cKDTree

from geometry.beads import bead_area
from geometry.gcode import GcodeHeader, GcodeWriter, to_bed
from inverse.printer import Printer
from shellfem.errors import SelfshapeError

SIDES = ("front", "back")


def _ribbon_name(i, r):
    label = getattr(r, "label", "") or ""
    return f"ribbon {i}" + (f" ({label})" if label else "")


def validate_ribbons(ribbons, layer_height_mm):
    """Check every ribbon; return (paths list of (k, 2) float arrays without repeated points,
    widths (n,), thicknesses (n,), sides (n,) str). Raises SelfshapeError naming the ribbon."""
    paths, widths, thick, sides = [], [], [], []
    for i, r in enumerate(ribbons):
        name = _ribbon_name(i, r)
        try:
            p = np.asarray(r.path, dtype=float)
            w, t, s = float(r.width_mm), float(r.thickness_mm), r.side
        except AttributeError as e:
            raise SelfshapeError(f"{name}: not a Ribbon ({e})") from None
        except (TypeError, ValueError):
            raise SelfshapeError(f"{name}: path, width_mm and thickness_mm must be numbers") from None
        if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2:
            raise SelfshapeError(f"{name}: path must be (k, 2) with k >= 2, got shape {p.shape}")
        if not np.isfinite(p).all():
            raise SelfshapeError(f"{name}: path has a non-finite coordinate")
        if not (math.isfinite(w) and w > 0) or not (math.isfinite(t) and t > 0):
            raise SelfshapeError(f"{name}: width_mm and thickness_mm must be > 0, got {w:g}, {t:g}")
        if w < layer_height_mm:
            raise SelfshapeError(f"{name}: width {w:g} mm is below the layer height {layer_height_mm:g} mm "
                                 f"(the bead model needs width >= height)")
        if s not in SIDES:
            raise SelfshapeError(f"{name}: side must be \"front\" or \"back\", got {s!r}")
        keep = np.r_[True, np.any(np.diff(p, axis=0) != 0, axis=1)]
        p = p[keep]
        if len(p) < 2:
            raise SelfshapeError(f"{name}: path has zero length")
        paths.append(p)
        widths.append(w)
        thick.append(t)
        sides.append(s)
    return paths, np.array(widths), np.array(thick), np.array(sides, dtype=object)


def layer_counts(thickness_mm, layer_height_mm):
    """Layers per ribbon: thickness / layer height rounded half up, at least 1."""
    n = np.floor(np.asarray(thickness_mm, float) / layer_height_mm + 0.5 + 1e-9).astype(int)
    return np.maximum(n, 1)


def default_origin(paths, bed_size):
    """Bed offset that centres the bounding box of all ``paths`` on the bed (mm)."""
    pts = np.concatenate(paths) if paths else np.zeros((1, 2))
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2.0
    return (float(bed_size[0] / 2.0 - centre[0]), float(bed_size[1] / 2.0 - centre[1]))


def greedy_order(starts, ends, position=(0.0, 0.0)):
    """Visit every path once, always going to the nearest free endpoint.

    starts, ends: (n, 2). Returns (order (n,) path indices, reverse (n,) bool: print
    from the end), and the final position. Ties go to the lower path index, then to its start.
    """
    n = len(starts)
    order = np.empty(n, dtype=int)
    reverse = np.zeros(n, dtype=bool)
    if n == 0:
        return order, reverse, np.asarray(position, float)
    pts = np.concatenate([starts, ends])            # endpoint j belongs to path j % n
    alive = np.ones(n, dtype=bool)
    ids = np.arange(2 * n)                          # endpoints in the current tree
    tree = cKDTree(pts)
    cur = np.asarray(position, float)
    for step in range(n):
        if step and alive.sum() * 4 < len(ids):     # rebuild over live endpoints
            ids = ids[alive[ids % n]]
            tree = cKDTree(pts[ids])
        m = len(ids)
        k = min(8, m)
        while True:
            d, j = tree.query(cur, k=k)
            d, j = np.atleast_1d(d), ids[np.atleast_1d(j)]
            ok = alive[j % n]
            if ok.any():
                dmin = d[ok].min()
                tie = d <= dmin * (1 + 1e-12) + 1e-12
                # done unless an equally near endpoint may lie beyond the k found
                if k == m or not tie[-1]:
                    break
            k = min(4 * k, m)
        cand = j[ok & tie]
        best = cand[np.argmin((cand % n) * 2 + (cand >= n))]
        i = best % n
        order[step], reverse[step] = i, best >= n
        alive[i] = False
        cur = starts[i] if reverse[step] else ends[i]
    return order, reverse, cur


def _header(p: Printer, side, origin, axis, relative_e, n_ribbons, n_layers) -> GcodeHeader:
    h = p.layer_height_mm
    return GcodeHeader(
        side=side, origin_mm=(origin[0], origin[1]), mirror_axis_x_mm=axis, bed_offset_z_mm=p.bed_offset_z_mm,
        ribbons=n_ribbons, layers=n_layers, bed_shape_mm=(p.bed_size[0], p.bed_size[1]),
        nozzle_diameter_mm=p.nozzle_mm, filament_diameter_mm=p.filament_diameter_mm, layer_height_mm=h,
        first_layer_height_mm=h, extrusion_multiplier=p.extrusion_multiplier, print_speed_mm_s=p.print_speed_mm_s,
        travel_speed_mm_s=p.travel_speed_mm_s, retract_length_mm=p.retraction_mm,
        retract_speed_mm_s=p.retraction_speed_mm_s, retract_lift_mm=p.z_hop_mm,
        temperature_c=p.nozzle_temperature_c, bed_temperature_c=p.bed_temperature_c, relative_e=relative_e)


def write_gcode(ribbons, path, printer: Printer | None = None, side="front", mirror_axis_x=None,
                relative_e: bool | None = None) -> dict:
    """Write the ``side`` ribbons of ``ribbons`` as G-code to ``path``; return statistics.

    ribbons: geometry.elements.Ribbon list (printed-state mm); all of them (both sides)
    set the default origin so that front and back files agree. mirror_axis_x: bed x of the
    frame's flip line for the back side (default printer.mirror_axis_x or the bed centre).
    relative_e: M83 (True) or M82 absolute E (False); default printer.relative_e.
    Stats: counts, lengths (mm), filament (mm), volume (mm^3), estimated time (s), and
    per written ribbon the thickness actually printed (layers x layer height).
    """
    p = printer if printer is not None else Printer()
    if side not in SIDES:
        raise SelfshapeError(f"write_gcode: side must be \"front\" or \"back\", got {side!r}")
    rel = p.relative_e if relative_e is None else bool(relative_e)
    try:
        axis = p.flip_axis_x if mirror_axis_x is None else float(mirror_axis_x)
    except (TypeError, ValueError):
        axis = math.nan
    if not math.isfinite(axis):
        raise SelfshapeError(f"write_gcode: mirror_axis_x must be finite, got {mirror_axis_x!r}")
    h = p.layer_height_mm
    paths, widths, thick, sides = validate_ribbons(ribbons, h)
    origin = p.origin if p.origin is not None else default_origin(paths, p.bed_size)

    sel = np.flatnonzero(sides == side)
    bed_paths = [np.round(to_bed(paths[i], origin, side, axis), 3) for i in sel]
    bed_paths = [b[np.r_[True, np.any(np.diff(b, axis=0) != 0, axis=1)]] for b in bed_paths]
    for i, b in zip(sel, bed_paths):
        r = widths[i] / 2.0
        lo, hi = b.min(axis=0) - r, b.max(axis=0) + r
        if (lo < 0).any() or hi[0] > p.bed_size[0] or hi[1] > p.bed_size[1]:
            raise SelfshapeError(
                f"{_ribbon_name(i, ribbons[i])}: falls outside the {p.bed_size[0]:g} x {p.bed_size[1]:g} mm bed "
                f"(bed bbox [{lo[0]:.2f}, {lo[1]:.2f}]-[{hi[0]:.2f}, {hi[1]:.2f}] with origin "
                f"({origin[0]:.2f}, {origin[1]:.2f}), side {side}); move the pattern (printer.origin)")
        if len(b) < 2:
            raise SelfshapeError(f"{_ribbon_name(i, ribbons[i])}: path is shorter than the 0.001 mm G-code resolution")
    n_layers_each = layer_counts(thick[sel], h)
    n_layers = int(n_layers_each.max()) if len(sel) else 0
    e_per_mm = bead_area(widths[sel], h) * p.extrusion_multiplier / p.filament_area_mm2

    writer = GcodeWriter(_header(p, side, origin, axis, rel, len(sel), n_layers), p.z_speed_mm_s,
                         p.retract_min_travel_mm)
    pos = np.zeros(2)
    starts = np.array([b[0] for b in bed_paths]).reshape(-1, 2)
    ends = np.array([b[-1] for b in bed_paths]).reshape(-1, 2)
    for layer in range(1, n_layers + 1):
        z = p.bed_offset_z_mm + layer * h
        writer.layer_change(z, h)
        live = np.flatnonzero(n_layers_each >= layer)
        order, rev, pos = greedy_order(starts[live], ends[live], pos)
        for k, r in zip(live[order], rev):
            b = bed_paths[k][::-1] if r else bed_paths[k]
            writer.travel(b[0], z)
            writer.feature("Ribbon", widths[sel[k]], f"{_ribbon_name(int(sel[k]), ribbons[sel[k]])} layer {layer}")
            writer.extrude(b, e_per_mm[k])
    writer.finish()
    writer.write(path)
    bbox = (np.concatenate(bed_paths).min(0).tolist() + np.concatenate(bed_paths).max(0).tolist()
            if bed_paths else [])
    stats = dict(writer.stats)
    stats.update(
        path=str(path), side=side, n_ribbons=int(len(sel)), n_layers=n_layers, layer_height_mm=h,
        n_lines=len(writer.lines), relative_e=rel, origin_mm=[float(origin[0]), float(origin[1])],
        mirror_axis_x_mm=axis, bed_bbox_mm=bbox,
        plastic_volume_mm3=stats["extruded_filament_mm"] * p.filament_area_mm2,
        ribbon_indices=sel.tolist(), thickness_printed_mm=(n_layers_each * h).tolist(),
        thickness_error_max_mm=float(np.abs(n_layers_each * h - thick[sel]).max()) if len(sel) else 0.0,
        warnings=[] if len(sel) else [f"no {side} ribbons: the file prints nothing"],
    )
    return stats


def ribbons_to_gcode_files(ribbons, out_dir, printer: Printer | None = None) -> list:
    """Write ``out_dir``/front.gcode and, when any ribbon is on the back, back.gcode.
    Both share the origin and flip axis. Returns the written paths."""
    os.makedirs(out_dir, exist_ok=True)
    out = [os.path.join(out_dir, "front.gcode")]
    write_gcode(ribbons, out[0], printer, side="front")
    if any(getattr(r, "side", "front") == "back" for r in ribbons):
        out.append(os.path.join(out_dir, "back.gcode"))
        write_gcode(ribbons, out[1], printer, side="back")
    return out
