"""Ribbons -> G-code for an FDM printer printing onto fabric held in a flippable frame.

Units: mm, mm/s, deg C. Each ribbon (geometry.elements.Ribbon: centre line, width,
thickness, side) is printed as round(thickness / layer height) (>= 1) stacked beads. Layer
by layer, the ribbons of a layer are ordered greedily by nearest endpoint (ties go to the
lower ribbon index, then to the path's start), each printed in the direction that starts at
the nearer end. Extrusion follows Slic3r's bead model: cross-section (w - h) h + pi h^2 / 4,
filament length E = area * length * multiplier / filament cross-section. Travel longer than
``printer.retract_min_travel_mm`` retracts and hops in z.

Frame convention (seed section 5.5): a pattern point (x, y) is printed on the front at bed
(x + ox, y + oy), (ox, oy) = printer.origin. To print the back, the frame is flipped about
the bed line x = a (``mirror_axis_x``, default the bed centre), which sends the fabric point
at bed x to bed 2a - x, y unchanged. The back side is therefore printed at bed
(2a - (x + ox), y + oy), which lands on the same fabric point as the front. The origin and
axis are written in the header so that :func:`geometry.gcode_import.read_gcode` maps a
file back to pattern coordinates.
"""
from __future__ import annotations

import math
import os
import tempfile

import numpy as np
from scipy.spatial import cKDTree

from inverse.printer import Printer, bead_area
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


def to_bed(xy, origin, side, mirror_axis_x):
    """Pattern (printed-state) coordinates -> bed coordinates for the given side. (k, 2)."""
    b = np.asarray(xy, float) + np.asarray(origin, float)
    if side == "back":
        b = b.copy()
        b[:, 0] = 2.0 * mirror_axis_x - b[:, 0]
    return b


def from_bed(xy, origin, side, mirror_axis_x):
    """Inverse of :func:`to_bed`. (k, 2)."""
    b = np.asarray(xy, float).copy()
    if side == "back":
        b[:, 0] = 2.0 * mirror_axis_x - b[:, 0]
    return b - np.asarray(origin, float)


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


class _Emitter:
    """Accumulates G-code lines, the tool position and print statistics."""

    def __init__(self, printer: Printer, relative_e: bool):
        self.p, self.rel = printer, relative_e
        self.lines: list[str] = []
        self.e = 0.0                  # absolute E (filament mm)
        self.xy = np.zeros(2)
        self.z = 0.0
        self.retracted = False
        self.stats = dict(print_length_mm=0.0, travel_length_mm=0.0, extruded_filament_mm=0.0,
                          n_retractions=0, estimated_time_s=0.0)

    def _e_word(self, de):
        self.e += de
        return f"E{de:.5f}" if self.rel else f"E{self.e:.5f}"

    def retract(self):
        if self.retracted or self.p.retraction_mm == 0:
            return
        f = self.p.retraction_speed_mm_s
        self.lines.append(f"G1 {self._e_word(-self.p.retraction_mm)} F{f * 60:.0f}")
        self.retracted = True
        self.stats["n_retractions"] += 1
        self.stats["estimated_time_s"] += self.p.retraction_mm / f

    def unretract(self):
        if not self.retracted:
            return
        f = self.p.retraction_speed_mm_s
        self.lines.append(f"G1 {self._e_word(self.p.retraction_mm)} F{f * 60:.0f}")
        self.retracted = False
        self.stats["estimated_time_s"] += self.p.retraction_mm / f

    def move_z(self, z):
        if abs(z - self.z) > 1e-9:
            self.lines.append(f"G1 Z{z:.3f} F{self.p.z_speed_mm_s * 60:.0f}")
            self.stats["estimated_time_s"] += abs(z - self.z) / self.p.z_speed_mm_s
            self.z = z

    def travel(self, xy, z):
        """Go to (xy, z) without extruding: retract and hop when the way is long."""
        dist = float(np.hypot(*(xy - self.xy)))
        if dist > self.p.retract_min_travel_mm or abs(z - self.z) > 1e-9:
            self.retract()
            self.move_z(max(z, self.z) + self.p.z_hop_mm)
        if dist > 0:
            self.lines.append(f"G0 X{xy[0]:.3f} Y{xy[1]:.3f} F{self.p.travel_speed_mm_s * 60:.0f}")
            self.stats["travel_length_mm"] += dist
            self.stats["estimated_time_s"] += dist / self.p.travel_speed_mm_s
            self.xy = xy.copy()
        self.move_z(z)
        self.unretract()

    def extrude(self, pts, e_per_mm):
        """Print the polyline ``pts`` (k, 2), starting at the current position pts[0]."""
        seg = np.hypot(*np.diff(pts, axis=0).T)
        de = seg * e_per_mm
        e_abs = self.e + np.cumsum(de)
        words = de if self.rel else e_abs
        lines = [f"G1 X{x:.3f} Y{y:.3f} E{e:.5f}"
                 for x, y, e in zip(pts[1:, 0].tolist(), pts[1:, 1].tolist(), words.tolist())]
        lines[0] += f" F{self.p.print_speed_mm_s * 60:.0f}"
        self.lines += lines
        self.e = float(e_abs[-1])
        length = float(seg.sum())
        self.stats["print_length_mm"] += length
        self.stats["extruded_filament_mm"] += float(de.sum())
        self.stats["estimated_time_s"] += length / self.p.print_speed_mm_s
        self.xy = pts[-1].copy()


def _header(p: Printer, side, origin, axis, relative_e, n_ribbons, n_layers):
    h = p.layer_height_mm
    return [
        "; generated by selfshape (inverse.gcode.write_gcode)",
        f"; selfshape side = {side}",
        f"; selfshape origin_mm = {origin[0]:.6f}, {origin[1]:.6f}",
        f"; selfshape mirror_axis_x_mm = {axis:.6f}",
        f"; selfshape bed_offset_z_mm = {p.bed_offset_z_mm:.6f}",
        f"; selfshape ribbons = {n_ribbons}",
        f"; selfshape layers = {n_layers}",
        "; pattern (x, y) is printed at bed (x + ox, y + oy) on the front and at "
        "(2 a - x - ox, y + oy) on the back (frame flipped about bed x = a)",
        f"; bed_shape = {p.bed_size[0]:g} x {p.bed_size[1]:g}",
        f"; nozzle_diameter = {p.nozzle_mm:g}",
        f"; filament_diameter = {p.filament_diameter_mm:g}",
        f"; layer_height = {h:g}",
        f"; first_layer_height = {h:g}",
        f"; extrusion_multiplier = {p.extrusion_multiplier:g}",
        f"; print_speed = {p.print_speed_mm_s:g}",
        f"; travel_speed = {p.travel_speed_mm_s:g}",
        f"; retract_length = {p.retraction_mm:g}",
        f"; retract_speed = {p.retraction_speed_mm_s:g}",
        f"; retract_lift = {p.z_hop_mm:g}",
        f"; temperature = {p.nozzle_temperature_c:g}",
        f"; bed_temperature = {p.bed_temperature_c:g}",
        "G21 ; millimetres",
        "G90 ; absolute positions",
        "M83 ; relative extrusion" if relative_e else "M82 ; absolute extrusion",
        f"M140 S{p.bed_temperature_c:.0f}",
        f"M104 S{p.nozzle_temperature_c:.0f}",
        "G28 ; home",
        f"M190 S{p.bed_temperature_c:.0f}" if p.bed_temperature_c > 0 else "; no bed heating (fabric)",
        f"M109 S{p.nozzle_temperature_c:.0f}",
        "G92 E0",
        "M107",
    ]


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

    em = _Emitter(p, rel)
    em.lines += _header(p, side, origin, axis, rel, len(sel), n_layers)
    pos = np.zeros(2)
    starts = np.array([b[0] for b in bed_paths]).reshape(-1, 2)
    ends = np.array([b[-1] for b in bed_paths]).reshape(-1, 2)
    for layer in range(1, n_layers + 1):
        z = p.bed_offset_z_mm + layer * h
        em.lines += [";LAYER_CHANGE", f";Z:{z:.3f}", f";HEIGHT:{h:g}"]
        live = np.flatnonzero(n_layers_each >= layer)
        order, rev, pos = greedy_order(starts[live], ends[live], pos)
        for k, r in zip(live[order], rev):
            b = bed_paths[k][::-1] if r else bed_paths[k]
            em.travel(b[0], z)
            em.lines += [";TYPE:Ribbon", f";WIDTH:{widths[sel[k]]:g}",
                         f"; {_ribbon_name(int(sel[k]), ribbons[sel[k]])} layer {layer}"]
            em.extrude(b, e_per_mm[k])
    em.retract()
    em.move_z(em.z + 10.0)
    em.lines += ["M104 S0", "M140 S0", "M107", "M84", "; end of selfshape print"]

    _write_atomic(path, "\n".join(em.lines) + "\n")
    bbox = (np.concatenate(bed_paths).min(0).tolist() + np.concatenate(bed_paths).max(0).tolist()
            if bed_paths else [])
    stats = dict(em.stats)
    stats.update(
        path=str(path), side=side, n_ribbons=int(len(sel)), n_layers=n_layers, layer_height_mm=h,
        n_lines=len(em.lines), relative_e=rel, origin_mm=[float(origin[0]), float(origin[1])],
        mirror_axis_x_mm=axis, bed_bbox_mm=bbox,
        plastic_volume_mm3=stats["extruded_filament_mm"] * p.filament_area_mm2,
        ribbon_indices=sel.tolist(), thickness_printed_mm=(n_layers_each * h).tolist(),
        thickness_error_max_mm=float(np.abs(n_layers_each * h - thick[sel]).max()) if len(sel) else 0.0,
        warnings=[] if len(sel) else [f"no {side} ribbons: the file prints nothing"],
    )
    return stats


def _write_atomic(path, text):
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    try:
        fd, tmp = tempfile.mkstemp(prefix=".selfshape-", suffix=".gcode", dir=folder)
    except OSError as e:
        raise SelfshapeError(f"cannot write {path}: {e.strerror}") from None
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except OSError as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise SelfshapeError(f"cannot write {path}: {e.strerror}") from None


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
