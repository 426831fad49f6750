"""Calibration prints: G-code, a specimen map and a measurement template, so that a lab can
measure its own material law (issue 23; seed section 3.3 and Fig. 5.6-5.7).

Two print sets, each laid out on one or more fabric frames (one pre-stretch per frame):

* **strips** (``selfshape calibration-print strips``): rectangular bilayer strips for the
  plastic / fabric modulus ratio (seed section 3.3: 4 thicknesses 0.3-0.45 mm x 10 strips,
  stretch 1.35, fabric 0.8 mm; front and back as in the project's strips data). Each strip is
  one serpentine path of beads filling its width x length rectangle, printed in
  round(thickness / layer height) layers. The template ``strips.csv`` is the strips schema
  (validation.strips, /work/shared/data/README.md) with every column filled but the measured
  ones (curvature_per_mm, rest_curvature_per_mm), plus where each specimen is (frame, x_mm,
  y_mm): what ``selfshape calibrate strips`` reads once the lab has measured.
* **law** (``selfshape calibration-print law``): the parallel-ribbon patches of the curvature
  law kappa(thickness, transverse spacing mu2, side) (seed Fig. 5.7, an 8 x 6 grid per side).
  Each patch is exactly the patch the project simulates for its own law
  (validation.law_tables.patch_pattern: staggered l_r x w_r dashes, period mu1 along x, rows
  mu2 apart, cut along the patch rectangle), so that a measured and a simulated law are made of
  the same specimens. The template ``law_measurements.csv`` (docs/calibration-prints.md) is
  read by ``selfshape law build`` (validation.law_build). With ``--simulate`` (or
  ``--from-rows``) its measured columns are filled by the project's patch simulations
  (validation.law_tables.simulate_row), so an in-silico law and a measured one are built by the
  same command.

Both sides are printed with the flipped-frame convention of the back G-code
(geometry.gcode.to_bed, inverse.gcode.write_gcode): the front and back files of a frame share
the origin and the flip axis, and the front and back specimens of a frame occupy different
places of the fabric (a strip printed on both faces at once would be a trilayer). Every
printed thickness must be a whole number of layers: the layer height is the printer's, or the
largest printer height / k that divides every thickness (0.05 mm for the seed's 0.3-0.45 mm),
said in the print's summary JSON and on the command line. One folder may hold a strips and a law
print (their file names differ; a rerun removes its own kind's files only).

Units: mm, 1/mm, dimensionless stretch; positions are pattern (printed-state) coordinates of
the fabric seen from the front, the ones geometry.gcode.read_gcode reads the files back to.
"""
from __future__ import annotations

import csv
import dataclasses
import io
import math
import os
from dataclasses import dataclass, field

import numpy as np

from geometry.elements import Ribbon
from geometry.schema import PRINTER_NUMBERS
from inverse.printer import Printer
from shellfem.errors import SelfshapeError, check_number
from shellfem.outfiles import OutputDir

SIDES = ("front", "back")
#: seed section 3.3 (thicknesses, stretch, fabric thickness); strip size and both sides as the
#: project's strips data (strips_S1.csv: 10 x 40 mm, front and back)
STRIP_DEFAULTS = {"thickness_mm": (0.3, 0.35, 0.4, 0.45), "repetitions": 10, "stretch": (1.35,),
                  "sides": ("front", "back"), "orientation_deg": (0.0,), "width_mm": 10.0, "length_mm": 40.0,
                  "fabric_thickness_mm": 0.8}
#: seed Fig. 5.7: 8 thicknesses x 6 transverse spacings per side (the spacings of
#: validation.law_tables, thicknesses 0.2-0.55 mm around the shipped laws' 0.2-0.4 mm)
LAW_DEFAULTS = {"thickness_mm": (0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.55),
                "spacing_mm": (3.9, 5.0, 6.5, 8.5, 11.0, 15.0), "stretch": 1.6, "sides": ("front", "back"),
                "rows": 6, "motifs": 3, "aspect": 2.0, "repetitions": 1}
GAP_MM = 8.0          # fabric between neighbouring specimens (to cut them apart)
MARGIN_MM = 8.0       # free border of the bed around the layout
STRIPS_MEASURED = ("curvature_per_mm", "rest_curvature_per_mm")
STRIPS_COLUMNS = ("specimen", "side", "stretch", "orientation_deg", "plastic_thickness_mm", "fabric_thickness_mm",
                  "width_mm", "length_mm") + STRIPS_MEASURED + ("frame", "x_mm", "y_mm")
#: law_measurements.csv: identification and geometry (filled by the print), then the measured columns
LAW_GEOMETRY = ("patch", "frame", "side", "stretch", "thickness_mm", "spacing_mm", "ribbon_length_mm",
                "ribbon_width_mm", "ribbon_gap_mm", "rows", "motifs", "patch_length_mm", "patch_width_mm",
                "x_mm", "y_mm")
LAW_MEASURED = ("kappa_per_mm", "kappa_across_per_mm", "contraction_along", "contraction_across")
LAW_COLUMNS = LAW_GEOMETRY + LAW_MEASURED + ("note",)
#: the per-frame files of a print set (``kind`` strips or law): a rerun removes its own kind's only
FRAME_FILE = r"{kind}_frame\d+_(front|back)\.gcode|{kind}_frame\d+_map\.png"


# ----------------------------------------------------------------------------- specimens
@dataclass
class Specimen:
    """One specimen: its ribbons in local coordinates (centred on (0, 0)), the rectangle the lab
    cuts it out along (local, (4, 2) corners), its size on the frame (axis-aligned, mm) and,
    after layout, its id, frame and centre (pattern mm)."""
    kind: str
    side: str
    stretch: float
    thickness_mm: float
    ribbons: list
    outline: np.ndarray
    fields: dict = field(default_factory=dict)
    id: str = ""
    frame: int = 0
    centre: tuple = (0.0, 0.0)

    @property
    def size(self):
        return tuple(np.ptp(self.outline, axis=0))

    def placed_ribbons(self):
        """The ribbons moved to the specimen's centre, labelled with its id."""
        c = np.asarray(self.centre, float)
        return [dataclasses.replace(r, path=np.asarray(r.path, float) + c, label=self.id) for r in self.ribbons]


def serpentine(length_mm, width_mm, bead_mm):
    """Centre line (k, 2) of one bead path filling a length x width rectangle centred on (0, 0)
    with n = max(1, round(width / bead)) passes along x of bead width width / n (returned too);
    passes turn at the ends, so the beads' outline is the rectangle (square path ends, round turns)."""
    n = max(1, int(round(width_mm / bead_mm)))
    w = width_mm / n
    if length_mm < 2 * w:
        raise SelfshapeError(f"strip length {length_mm:g} mm must be at least two bead widths ({2 * w:g} mm)")
    y = -width_mm / 2 + (np.arange(n) + 0.5) * w
    x0, x1 = -length_mm / 2 + w / 2, length_mm / 2 - w / 2
    xs = np.where(np.arange(n) % 2 == 0, x0, x1)
    pts = np.empty((2 * n, 2))
    pts[0::2, 0], pts[1::2, 0] = xs, x0 + x1 - xs
    pts[0::2, 1] = pts[1::2, 1] = y
    return pts, w


def _rot(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


def strip_specimens(thickness_mm=STRIP_DEFAULTS["thickness_mm"], repetitions=STRIP_DEFAULTS["repetitions"],
                    stretch=STRIP_DEFAULTS["stretch"], sides=STRIP_DEFAULTS["sides"],
                    orientation_deg=STRIP_DEFAULTS["orientation_deg"], width_mm=STRIP_DEFAULTS["width_mm"],
                    length_mm=STRIP_DEFAULTS["length_mm"], fabric_thickness_mm=STRIP_DEFAULTS["fabric_thickness_mm"],
                    bead_mm=0.8):
    """The strip set: every stretch x side x orientation x thickness, ``repetitions`` times
    (lengths mm, orientation degrees from the fabric's course x direction, counter-clockwise
    seen from the front)."""
    path, w = serpentine(length_mm, width_mm, bead_mm)
    out = []
    for s in stretch:
        for side in sides:
            for ang in orientation_deg:
                R = _rot(ang)
                corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * [length_mm / 2, width_mm / 2]
                for t in thickness_mm:
                    for _ in range(int(repetitions)):
                        rib = Ribbon(path=path @ R.T, width_mm=w, thickness_mm=float(t), side=side)
                        out.append(Specimen("strip", side, float(s), float(t), [rib], corners @ R.T, {
                            "orientation_deg": float(ang), "width_mm": float(width_mm), "length_mm": float(length_mm),
                            "fabric_thickness_mm": float(fabric_thickness_mm), "bead_width_mm": w}))
    return out


def patch_specimens(thickness_mm=LAW_DEFAULTS["thickness_mm"], spacing_mm=LAW_DEFAULTS["spacing_mm"],
                    stretch=LAW_DEFAULTS["stretch"], sides=LAW_DEFAULTS["sides"], rows=LAW_DEFAULTS["rows"],
                    motifs=LAW_DEFAULTS["motifs"], aspect=LAW_DEFAULTS["aspect"],
                    repetitions=LAW_DEFAULTS["repetitions"]):
    """The law's parallel-ribbon patches: every side x thickness x spacing, ``repetitions`` times
    (replicates, averaged by `law build`), each the patch of validation.law_tables.patch_pattern
    (the simulated one), centred on (0, 0)."""
    from validation.law_tables import MU1, RIBBON_LENGTH, RIBBON_WIDTH, patch_motifs, patch_pattern
    out = []
    for side in sides:
        for t in thickness_mm:
            for mu in spacing_mm:
                raw = patch_pattern(float(t), float(mu), side, float(stretch), n_rows=int(rows), n_motifs=int(motifs),
                                    aspect=float(aspect))
                W, H = raw["fabric"]["rectangle"]
                c = np.array([W / 2, H / 2])
                ribs = [Ribbon(path=np.asarray(r["path"], float) - c, width_mm=r["width_mm"],
                               thickness_mm=r["thickness_mm"], side=side) for r in raw["ribbon"]]
                corners = np.array([[0, 0], [W, 0], [W, H], [0, H]], float) - c
                for _ in range(int(repetitions)):
                    out.append(Specimen("patch", side, float(stretch), float(t), ribs, corners, {
                        "spacing_mm": float(mu), "ribbon_length_mm": RIBBON_LENGTH, "ribbon_width_mm": RIBBON_WIDTH,
                        "ribbon_gap_mm": MU1 - RIBBON_LENGTH, "mu1_mm": MU1, "rows": int(rows),
                        "motifs": int(patch_motifs(motifs, rows, mu, MU1, aspect)), "patch_length_mm": float(W),
                        "patch_width_mm": float(H)}))
    return out


# ----------------------------------------------------------------------------- layout
def layout(specimens, bed_size, prefix, gap_mm=GAP_MM, margin_mm=MARGIN_MM, shuffle=None):
    """Place the specimens on frames: one stretch per frame, first-fit decreasing-height shelf
    packing into the bed less ``margin_mm``, with ``gap_mm`` of fabric between specimens (each
    specimen, tallest first, goes on the first shelf of any open frame with room, else on a new
    shelf of the first frame with room, else on a new frame; shelves run left to right, bottom to
    top). Sets each specimen's frame (from 1), centre (pattern mm, the frame's layout centred on
    (0, 0)) and id (``prefix``-nnn in frame and row order). ``shuffle``: a seed; specimens of
    one size are then placed in a seeded random order instead of the given one, so that a place
    on the frame (uneven tension, the print's first or last layers) is not confounded with a
    thickness or a side. Returns the frames as [(frame, stretch, [specimens])]. A specimen larger
    than the bed is a SelfshapeError."""
    W, H = bed_size[0] - 2 * margin_mm, bed_size[1] - 2 * margin_mm
    frames = []
    for s in sorted({sp.stretch for sp in specimens}):
        group = [sp for sp in specimens if sp.stretch == s]
        rank = np.arange(len(group)) if shuffle is None else np.random.default_rng(shuffle).permutation(len(group))
        order = sorted(range(len(group)), key=lambda i: (-round(group[i].size[1], 6), -round(group[i].size[0], 6),
                                                         rank[i]))
        sheets = []                    # per frame: {"shelves": [[y, height, x_next]], "top": y_next, "placed": []}
        for i in order:
            sp = group[i]
            w, h = sp.size
            if w > W or h > H:
                raise SelfshapeError(f"a {sp.kind} of {w:.1f} x {h:.1f} mm does not fit the {bed_size[0]:g} x "
                                     f"{bed_size[1]:g} mm bed less {margin_mm:g} mm margins (--printer bed_size; "
                                     f"fewer rows or motifs)")
            spot = next(((sh, shelf) for sh in sheets for shelf in sh["shelves"]
                         if h <= shelf[1] + 1e-9 and shelf[2] + w <= W + 1e-9), None)
            if spot is None:
                sh = next((sh for sh in sheets if sh["top"] + h <= H + 1e-9), None)
                if sh is None:
                    sh = {"shelves": [], "top": 0.0, "placed": []}
                    sheets.append(sh)
                shelf = [sh["top"], h, 0.0]
                sh["shelves"].append(shelf)
                sh["top"] += h + gap_mm
                spot = (sh, shelf)
            sh, shelf = spot
            sh["placed"].append((sp, shelf[2] + w / 2, shelf[0] + h / 2))
            shelf[2] += w + gap_mm
        for sh in sheets:
            placed = sh["placed"]
            pts = np.array([[cx, cy] for _, cx, cy in placed])
            half = np.array([sp.size for sp, _, _ in placed]) / 2
            mid = ((pts - half).min(0) + (pts + half).max(0)) / 2
            frame = len(frames) + 1
            for sp, cx, cy in placed:
                sp.frame, sp.centre = frame, (float(cx - mid[0]), float(cy - mid[1]))
            frames.append((frame, s, [sp for sp, _, _ in placed]))
    k = 0
    for _, _, sps in frames:
        sps.sort(key=lambda sp: (round(sp.centre[1] - sp.size[1] / 2, 6), sp.centre[0]))
        for sp in sps:
            k += 1
            sp.id = f"{prefix}-{k:03d}"
    return frames


# ----------------------------------------------------------------------------- printer
def layer_height_for(thicknesses, printer: Printer, layer_height_mm=None) -> float:
    """The layer height every thickness is a whole number of layers of (mm): ``layer_height_mm``
    if given (checked), else the printer's, else the largest printer height / k (k = 2..40)
    that divides all, within geometry.schema's range. A SelfshapeError names a thickness that
    no such height prints exactly."""
    spec = PRINTER_NUMBERS["layer_height_mm"]
    t = np.asarray(sorted(set(float(v) for v in thicknesses)))

    def divides(h):
        n = t / h
        return bool(np.all(np.abs(n - np.round(n)) < 1e-6) and np.all(np.round(n) >= 1))
    if layer_height_mm is not None:
        h = float(layer_height_mm)
        if not divides(h):
            n = t / h
            bad = t[np.abs(n - np.round(n)) >= 1e-6]
            bad = t[np.round(n) < 1] if bad.size == 0 else bad
            raise SelfshapeError(f"thickness {bad[0]:g} mm is not a whole number of {h:g} mm layers "
                                 f"(--layer-height); choose thicknesses on that layer grid")
        return h
    for k in range(1, 41):
        h = printer.layer_height_mm / k
        if h < spec.lo:
            break
        if divides(h):
            return float(round(h, 9))
    raise SelfshapeError(f"the thicknesses {', '.join(f'{v:g}' for v in t)} mm are not whole numbers of layers of "
                         f"any height printer.layer_height_mm / k >= {spec.lo:g} mm; choose thicknesses on a common "
                         f"layer grid or give --layer-height")


def print_printer(printer, thicknesses, layer_height_mm=None) -> Printer:
    """The printer with the layer height of :func:`layer_height_for` (validated again by Printer)."""
    p = printer if printer is not None else Printer()
    h = layer_height_for(thicknesses, p, layer_height_mm)
    try:
        return dataclasses.replace(p, layer_height_mm=h)
    except SelfshapeError as e:
        raise SelfshapeError(f"layer height {h:g} mm: {e}") from None


# ----------------------------------------------------------------------------- writing
def _fmt(v):
    if isinstance(v, (float, np.floating)):
        return "" if not np.isfinite(v) else f"{float(v):.10g}"
    return str(v)


def csv_text(columns, rows, comments=()):
    """CSV text: ``# `` comment lines, the header, then one line per row dict (missing = empty)."""
    buf = io.StringIO()
    for c in comments:
        buf.write(f"# {c}\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([_fmt(r.get(c, "")) for c in columns])
    return buf.getvalue()


def _plot_map(frame, stretch, specimens, printer, path, title, origin=None):
    """PNG of one frame: every specimen's cut outline and ribbons in pattern coordinates seen
    from the front (front specimens solid blue, back ones dashed orange), its id at its centre,
    and the front's bed (bed position of pattern (0, 0): ``origin``, default the bed centre)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    bx, by = printer.bed_size
    ox, oy = (bx / 2, by / 2) if origin is None else origin
    fig, ax = plt.subplots(figsize=(8.0, 8.0 * by / bx + 0.6))
    ax.add_patch(plt.Rectangle((-ox, -oy), bx, by, fill=False, ec="0.6", lw=0.8, ls=":"))
    segs, colors = [], []
    for sp in specimens:
        col = "C0" if sp.side == "front" else "C1"
        o = sp.outline + np.asarray(sp.centre)
        ax.add_patch(plt.Polygon(o, closed=True, fill=False, ec=col, lw=0.9, ls="-" if sp.side == "front" else "--"))
        if sp.kind == "patch":             # the dashes (a strip's beads fill its outline)
            for r in sp.placed_ribbons():
                segs.append(np.asarray(r.path)[[0, -1]])
                colors.append(col)
            label = f"{sp.id}\nt {sp.thickness_mm:g} / mu2 {sp.fields['spacing_mm']:g}"
        else:
            label = f"{sp.id}  t {sp.thickness_mm:g}"
        fs = 6 if sp.kind == "strip" else 7
        rot = 90 if sp.size[1] > 1.5 * sp.size[0] else 0
        ax.text(sp.centre[0], sp.centre[1], label, ha="center", va="center", fontsize=fs, rotation=rot,
                bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8))
    if segs:
        ax.add_collection(LineCollection(segs, colors=colors, linewidths=0.6, alpha=0.5))
    ax.set_xlim(-ox, bx - ox)
    ax.set_ylim(-oy, by - oy)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm, fabric course direction)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"{title}, frame {frame}, stretch {stretch:g}: seen from the front\n"
                 f"blue solid = front, orange dashed = back (printed after flipping the frame); cut along the "
                 f"outlines", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def _write_frames(outs, frames, printer, kind, title):
    """G-code (front, and back when the frame has back specimens) and map of every frame;
    returns the per-frame summary."""
    from inverse.gcode import write_gcode
    out = []
    for frame, s, sps in frames:
        ribbons = [r for sp in sps for r in sp.placed_ribbons()]
        info = {"frame": frame, "stretch": s, "specimens": [sp.id for sp in sps], "files": {}}
        for side in SIDES:
            if not any(sp.side == side for sp in sps):
                continue
            name = f"{kind}_frame{frame:02d}_{side}.gcode"
            holder = {}
            outs.write(name, lambda tmp, side=side: holder.update(write_gcode(ribbons, tmp, printer, side=side)))
            st = holder
            info["files"][side] = name
            info[side] = {"ribbons": st["n_ribbons"], "layers": st["n_layers"],
                          "filament_mm": round(st["extruded_filament_mm"], 1),
                          "estimated_time_min": round(st["estimated_time_s"] / 60, 1),
                          "origin_mm": st["origin_mm"], "mirror_axis_x_mm": st["mirror_axis_x_mm"]}
        name = f"{kind}_frame{frame:02d}_map.png"
        origin = next((info[sd]["origin_mm"] for sd in SIDES if sd in info), None)
        outs.write(name, lambda tmp, frame=frame, s=s, sps=sps, origin=origin: _plot_map(frame, s, sps, printer, tmp,
                                                                                         title, origin))
        info["files"]["map"] = name
        out.append(info)
    return out


def _printer_summary(p: Printer) -> dict:
    return {f.name: getattr(p, f.name) for f in dataclasses.fields(p)}


# ----------------------------------------------------------------------------- strips
STRIPS_OUTPUTS = ("strips.csv", "strips_summary.json")


def calibration_strips(out_dir, printer: Printer | None = None, *, layer_height_mm=None, gap_mm=GAP_MM,
                       inputs=(), shuffle=None, **options) -> dict:
    """Write the strip calibration print to ``out_dir``: per frame G-code (front, back) and a
    map PNG, ``strips.csv`` (the strips schema, measured columns empty) and
    ``strips_summary.json`` (last). ``options``: those of :func:`strip_specimens` (default:
    :data:`STRIP_DEFAULTS`). Returns the summary."""
    p0 = printer if printer is not None else Printer()
    opts = dict(STRIP_DEFAULTS)
    opts.update({k: v for k, v in options.items() if v is not None})
    _check_options(opts)
    outs = OutputDir(out_dir, STRIPS_OUTPUTS, patterns=(FRAME_FILE.format(kind="strips"),),
                     inputs=inputs)                   # checked before the work
    p = print_printer(p0, opts["thickness_mm"], layer_height_mm)
    bead = max(p.nozzle_mm, p.layer_height_mm)
    sps = strip_specimens(bead_mm=bead, **{k: opts[k] for k in STRIP_DEFAULTS})
    frames = layout(sps, p.bed_size, "ST", gap_mm=gap_mm, shuffle=shuffle)
    rows = [dict(specimen=sp.id, side=sp.side, stretch=sp.stretch, orientation_deg=sp.fields["orientation_deg"],
                 plastic_thickness_mm=sp.thickness_mm, fabric_thickness_mm=sp.fields["fabric_thickness_mm"],
                 width_mm=sp.fields["width_mm"], length_mm=sp.fields["length_mm"], frame=sp.frame,
                 x_mm=round(sp.centre[0], 3), y_mm=round(sp.centre[1], 3))
            for _, _, fs in frames for sp in fs]
    summary = {"kind": "strips", "specimens": len(rows), "layer_height_mm": p.layer_height_mm,
               "bead_width_mm": sps[0].fields["bead_width_mm"], "options": {k: opts[k] for k in STRIP_DEFAULTS},
               "gap_mm": gap_mm, "shuffle_seed": shuffle,
               "measure": "fill curvature_per_mm (and rest_curvature_per_mm) in strips.csv, then "
               "selfshape calibrate strips strips.csv -o DIR", "printer": _printer_summary(p)}
    with outs.begin():
        summary["frames"] = _write_frames(outs, frames, p, "strips", "strip calibration")
        outs.write_text("strips.csv", csv_text(STRIPS_COLUMNS, rows))
        outs.write_json("strips_summary.json", summary)
    return summary


def _check_options(opts):
    """Physical ranges of the specimen options (validation.strips.RANGES for the strips schema)."""
    from validation.strips import RANGES
    for key, col in (("thickness_mm", "plastic_thickness_mm"), ("stretch", "stretch"),
                     ("orientation_deg", "orientation_deg"), ("spacing_mm", None)):
        for v in opts.get(key, ()):
            lo, hi = RANGES[col] if col else (0.5, 1e3)
            check_number(f"--{key.split('_')[0]}", v, lo=lo, hi=hi)
        if key in opts and len(set(opts[key])) != len(opts[key]):
            raise SelfshapeError(f"--{key.split('_')[0]}: a value is given twice")
    for key in ("width_mm", "length_mm", "fabric_thickness_mm"):
        if key in opts:
            lo, hi = RANGES[key]
            check_number(f"--{key.rsplit('_', 1)[0].replace('_', '-')}", opts[key], lo=max(lo, 0.1), hi=min(hi, 1e3))
    if "repetitions" in opts and not (isinstance(opts["repetitions"], int) and 1 <= opts["repetitions"] <= 1000):
        raise SelfshapeError(f"--repetitions must be an integer in [1, 1000], got {opts['repetitions']!r}")
    sides = opts.get("sides", ())
    if not sides or any(s not in SIDES for s in sides) or len(set(sides)) != len(sides):
        raise SelfshapeError(f"--sides must be front and/or back (each once), got {' '.join(map(str, sides))}")


def fill_strips_from_model(template, out_path, modulus_ratio, noise=0.015, seed=0) -> np.ndarray:
    """Fill a strips.csv template's curvature_per_mm with the project's bilayer strip model
    (validation.strips.strip_model, plastic flat at rest) at ``modulus_ratio`` times
    (1 + ``noise`` N(0, 1)) (seeded): a synthetic measurement for round-trip checks of
    `calibrate strips`. Other columns are kept; returns the curvatures written (1/mm)."""
    from validation.strips import MEASURED, read_strips, strip_model
    rows = read_strips(template, require_measured=False)
    k = strip_model(rows["plastic_thickness_mm"], rows["fabric_thickness_mm"], rows["stretch"], modulus_ratio)
    k = k * (1 + noise * np.random.default_rng(seed).standard_normal(k.size))
    header, body = rows["_raw"]
    j = header.index(MEASURED)
    for r, v in zip(body, k):
        r[j] = f"{v:.6g}"
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(body)
    from shellfem.outfiles import write_text_file
    write_text_file(out_path, buf.getvalue())
    return k


# ----------------------------------------------------------------------------- law
LAW_OUTPUTS = ("law_measurements.csv", "law_sim_rows.json", "law_summary.json")
LAW_COMMENTS = (
    "selfshape law_measurements template (selfshape calibration-print law); columns: docs/calibration-prints.md",
    "measure each released patch: kappa_per_mm = 1 / radius (1/mm) of the cylinder it rolls into, along the "
    "ribbons (printed x), a magnitude;",
    "  optional: kappa_across_per_mm (across the ribbons), contraction_along / contraction_across = printed / "
    "deployed length of a line drawn on the fabric (>= 1 when it contracts)",
    "then: selfshape law build law_measurements.csv -o LAW.csv",
)


def calibration_law(out_dir, printer: Printer | None = None, *, layer_height_mm=None, gap_mm=GAP_MM, inputs=(),
                    shuffle=None, simulate=False, from_rows=None, mirror_back=False, sim_options=None, calibration=None,
                    **options) -> dict:
    """Write the curvature-law calibration print to ``out_dir``: per frame G-code and map,
    ``law_measurements.csv`` and ``law_summary.json`` (last). ``options``: those of
    :func:`patch_specimens` (default :data:`LAW_DEFAULTS`). ``simulate``: fill the measured
    columns by simulating every patch (validation.law_tables.simulate_row with
    ``sim_options``: mesh_size, across, max_iterations, start_curvature, start_direction, seed;
    plastic = the modulus ratio of ``calibration`` (a `calibrate strips` parameters.json) x the
    fabric's E, default the shipped inverse/data/strips_S1_calibration.json); ``from_rows``:
    fill them from a rows JSON of studies/thickness_law_sim.py (--rows-json) instead, matching
    (thickness, spacing, side; one row per cell). ``mirror_back``: back cells take their front cell's values
    (the model is mirror-symmetric without gravity; so were the shipped laws made) instead of
    being simulated or looked up. Cells that do not converge or are absent stay empty, with a
    note. Returns the summary."""
    p0 = printer if printer is not None else Printer()
    opts = dict(LAW_DEFAULTS)
    opts.update({k: v for k, v in options.items() if v is not None})
    _check_options({k: opts[k] for k in ("thickness_mm", "spacing_mm", "sides")} | {"stretch": (opts["stretch"],)})
    for key, lo, hi in (("rows", 1, 100), ("motifs", 1, 100), ("repetitions", 1, 100)):
        if not (isinstance(opts[key], int) and lo <= opts[key] <= hi):
            raise SelfshapeError(f"--{key} must be an integer in [{lo}, {hi}], got {opts[key]!r}")
    check_number("--aspect", opts["aspect"], lo=0.0, hi=20.0)
    from validation.law_tables import RIBBON_WIDTH
    for mu in opts["spacing_mm"]:      # rows closer than a ribbon's width overlap: a plate, not ribbons
        if mu <= RIBBON_WIDTH:
            raise SelfshapeError(f"--spacing {mu:g} mm: rows of {RIBBON_WIDTH:g} mm wide ribbons must be more than "
                                 f"their width apart (mu2 > {RIBBON_WIDTH:g} mm), else they overlap")
    if simulate and from_rows:
        raise SelfshapeError("--simulate and --from-rows are exclusive: fill by simulating or from a rows JSON")
    rows_index = _read_rows_json(from_rows) if from_rows else None
    plastic_info = (plastic_from_calibration(calibration) if simulate or (rows_index is not None and calibration)
                    else None)
    outs = OutputDir(out_dir, LAW_OUTPUTS, patterns=(FRAME_FILE.format(kind="law"),),
                     inputs=list(inputs) + [from_rows, calibration])
    p = print_printer(p0, opts["thickness_mm"], layer_height_mm)
    sps = patch_specimens(**{k: opts[k] for k in LAW_DEFAULTS})
    frames = layout(sps, p.bed_size, "LP", gap_mm=gap_mm, shuffle=shuffle)
    placed = [sp for _, _, fs in frames for sp in fs]
    rows = [dict(patch=sp.id, frame=sp.frame, side=sp.side, stretch=sp.stretch, thickness_mm=sp.thickness_mm,
                 x_mm=round(sp.centre[0], 3), y_mm=round(sp.centre[1], 3),
                 **{k: sp.fields[k] for k in LAW_GEOMETRY if k in sp.fields}) for sp in placed]
    comments = list(LAW_COMMENTS)
    summary = {"kind": "law", "patches": len(rows), "layer_height_mm": p.layer_height_mm,
               "options": {k: opts[k] for k in LAW_DEFAULTS}, "gap_mm": gap_mm, "shuffle_seed": shuffle,
               "printer": _printer_summary(p)}
    if simulate or rows_index is not None:
        fill = _fill_law_rows(rows, simulate, rows_index, mirror_back, sim_options or {}, plastic_info, opts)
        comments += fill["comments"]
        summary["fill"] = {k: v for k, v in fill.items() if k not in ("comments", "sim_rows")}
    with outs.begin():
        summary["frames"] = _write_frames(outs, frames, p, "law", "curvature-law calibration")
        outs.write_text("law_measurements.csv", csv_text(LAW_COLUMNS, rows, comments))
        if simulate:            # the simulated rows, for --from-rows (a refill without simulating)
            outs.write_json("law_sim_rows.json", {"rows": fill["sim_rows"], "provenance": {
                "command": "selfshape calibration-print law --simulate", "comments": fill["comments"]}})
        outs.write_json("law_summary.json", summary)
    return summary


def plastic_from_calibration(calibration):
    """(Fabric, Plastic, text) of a `calibrate strips` parameters.json (default the shipped
    strips_S1_calibration.json): the plastic's E (MPa) = its modulus_ratio x the fabric's E, the
    plastic that `calibration-print law --simulate` simulates and that `law build --calibration`
    states in the law; text says where it came from (for provenance lines)."""
    from shellfem.materials import Fabric, Plastic
    from validation.textfiles import read_json
    path = calibration or os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "inverse",
                                       "data", "strips_S1_calibration.json")
    name = os.path.basename(path)
    p = read_json(path, "calibrate strips parameters.json")
    try:
        ratio, se = (float(v) for v in p["modulus_ratio"])
    except (KeyError, TypeError, ValueError):
        raise SelfshapeError(f"{name}: not a `selfshape calibrate strips` parameters.json (needs modulus_ratio "
                             f"[value, standard error])") from None
    check_number(f"{name}: modulus_ratio", ratio, lo=1.0, hi=1e7)
    fabric = Fabric()
    plastic = dataclasses.replace(Plastic(), young_modulus=ratio * fabric.young_modulus)
    data = p.get("fit", {}).get("data", "?") if isinstance(p.get("fit"), dict) else "?"
    return fabric, plastic, (f"plastic E {plastic.young_modulus:.6g} MPa = modulus_ratio {ratio:.1f} +- {se:.1f} x "
                             f"fabric E {fabric.young_modulus:g} MPa, from {name} (calibrate strips on {data})")


#: the keys of a rows JSON row that --from-rows copies into the template (validation.law_tables
#: ROW_KEYS / EXTRA_ROW_KEYS): (lo, hi) of a finite number, None for any finite number; null is
#: allowed (not simulated). Curvatures are magnitudes (1/mm), contractions printed / deployed.
ROWS_JSON_NUMBERS = {"kappa_per_mm": (0.0, 10.0), "kappa_across_per_mm": (0.0, 10.0), "sigma_along": (0.1, 10.0),
                     "sigma_across": (0.1, 10.0), "k1_angle_deg": (-180.0, 180.0)}


def _check_rows_json_row(r, where):
    """The (thickness, spacing, side) key of one rows JSON row, after checking every field
    --from-rows reads from it: thickness and spacing finite > 0 mm, side front/back, the
    ROWS_JSON_NUMBERS null or a number in range, rows/motifs null or an integer >= 1,
    converged absent or true/false. A bad field is a one-line SelfshapeError naming ``where``
    and the key, so a hand-edited or foreign file never reaches the template as a wrong value
    (or as an internal error)."""
    if not isinstance(r, dict):
        raise SelfshapeError(f"{where}: not an object with thickness_mm, spacing_mm, side and kappa_per_mm")

    def number(key, lo=None, hi=None, lo_open=False, null=False):
        v = r.get(key)
        if v is None and null:
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise SelfshapeError(f"{where}, {key}: must be a number{' (or null)' if null else ''}, got {v!r}")
        return check_number(f"{where}, {key}:", v, lo=lo, hi=hi, lo_open=lo_open)
    t = number("thickness_mm", 0.0, 10.0, lo_open=True)
    mu = number("spacing_mm", 0.0, 1e3, lo_open=True)
    if r.get("side") not in SIDES:
        raise SelfshapeError(f"{where}, side: must be \"front\" or \"back\", got {r.get('side')!r}")
    if "kappa_per_mm" not in r:
        raise SelfshapeError(f"{where}: needs kappa_per_mm (a number in 1/mm, or null when not simulated)")
    for key, (lo, hi) in ROWS_JSON_NUMBERS.items():
        number(key, lo, hi, null=True)
    for key in ("rows", "motifs"):
        v = r.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise SelfshapeError(f"{where}, {key}: must be an integer >= 1 (or null), got {v!r}")
    if "converged" in r and not isinstance(r["converged"], bool):
        raise SelfshapeError(f"{where}, converged: must be true or false, got {r['converged']!r}")
    return round(t, 9), round(mu, 9), r["side"]


def _read_rows_json(path):
    """{(thickness, spacing, side): row} of a rows JSON (studies/thickness_law_sim.py --rows-json:
    {"rows": [{thickness_mm, spacing_mm, side, kappa_per_mm, converged, ...}]}), every row
    checked by _check_rows_json_row; a second row for one cell is refused (which one the
    template should hold is the user's choice)."""
    from validation.textfiles import read_json
    name = os.path.basename(str(path))
    d = read_json(path, "rows JSON")
    rows = d.get("rows") if isinstance(d, dict) else None
    if not isinstance(rows, list):
        raise SelfshapeError(f"{name}: not a rows JSON of studies/thickness_law_sim.py (needs \"rows\": [...])")
    out = {}
    for i, r in enumerate(rows):
        key = _check_rows_json_row(r, f"{name}: rows[{i}]")
        if key in out:
            raise SelfshapeError(f"{name}: rows[{i}]: a second row for thickness {key[0]:g} mm, spacing {key[1]:g} mm, "
                                 f"side {key[2]}: which one the template should hold is the user's choice (keep one)")
        out[key] = r
    out["_name"] = name
    return out


def _sim_values(r):
    """The template's measured columns from a simulated row (law_tables.simulate_row keys)."""
    out = {"kappa_per_mm": float(r["kappa_per_mm"])}
    for col, key in (("kappa_across_per_mm", "kappa_across_per_mm"), ("contraction_along", "sigma_along"),
                     ("contraction_across", "sigma_across")):
        if r.get(key) is not None:
            out[col] = float(r[key])
    ang = r.get("k1_angle_deg")
    if ang is not None and float(ang) > 20:
        out["note"] = f"simulated: bends obliquely, k1 at {float(ang):g} deg from the ribbons"
    return out


def _fill_law_rows(rows, simulate, rows_index, mirror_back, sim_options, plastic_info, opts):
    """Fill the measured columns of the template rows in place (see calibration_law)."""
    import time
    key = lambda r, side=None: (round(r["thickness_mm"], 9), round(r["spacing_mm"], 9), side or r["side"])  # noqa: E731
    front = {key(r): r for r in rows if r["side"] == "front"}
    n_sim = n_drop = n_mirror = n_missing = 0
    t0 = time.perf_counter()
    comments, sim_rows = [], []
    if simulate:
        from validation.law_tables import EXTRA_ROW_KEYS, ROW_KEYS, simulate_row
        fabric, plastic, text = plastic_info
        so = {"mesh_size": 3.0, "across": 2.0, "max_iterations": 800, "start_curvature": 0.0,
              "start_direction": "along", "seed": 0}
        so.update({k: v for k, v in sim_options.items() if v is not None})
        comments += [f"filled by simulation (validation.law_tables.simulate_row, forward.simulate.simulate_sheet): "
                     f"mesh size {so['mesh_size']:g} mm, {so['across']:g} triangle rows across a ribbon, at most "
                     f"{so['max_iterations']} Newton iterations, start "
                     + ("flat (perturbed)" if not so["start_curvature"] else
                        f"rolled {so['start_direction']} the ribbons to {so['start_curvature']:g} /mm"),
                     f"  fabric E {fabric.young_modulus:g} MPa, nu {fabric.poisson:g}, "
                     f"thickness {fabric.thickness:g} mm; "
                     f"{text}",
                     f"plastic_young_modulus_mpa = {plastic.young_modulus:.6g}"]
    else:
        comments.append(f"filled from the simulated rows of {rows_index['_name']} (studies/thickness_law_sim.py "
                        f"--rows-json), matched by thickness, spacing and side; a row simulated on another patch "
                        f"than the printed one says so in its note")
        if plastic_info is not None:
            comments += [f"  the rows' plastic (as stated with --calibration): {plastic_info[2]}",
                         f"plastic_young_modulus_mpa = {plastic_info[1].young_modulus:.6g}"]
    if mirror_back:
        comments.append("back cells = their front cell (mirror symmetry through the fabric mid-surface, no gravity)")
    done = {}                 # replicates of a cell: the (deterministic) simulation once
    for r in rows:
        if mirror_back and r["side"] == "back":
            continue
        if simulate:
            if key(r) in done:
                sim = done[key(r)]
            else:
                sim = simulate_row(r["thickness_mm"], r["spacing_mm"], r["side"], r["stretch"],
                                   mesh_size=so["mesh_size"], across=so["across"],
                                   max_iterations=int(so["max_iterations"]), n_rows=opts["rows"],
                                   n_motifs=opts["motifs"], aspect=opts["aspect"], seed=int(so["seed"]), fabric=fabric,
                                   plastic=plastic, start_curvature=so["start_curvature"],
                                   start_direction=so["start_direction"])
                done[key(r)] = sim
                n_sim += 1
                sim_rows.append({k: (None if isinstance(sim[k], float) and not math.isfinite(sim[k]) else sim[k])
                                 for k in ROW_KEYS + EXTRA_ROW_KEYS if k in sim})
            if sim["converged"] and np.isfinite(sim["kappa_per_mm"]):
                r.update(_sim_values(sim))
            else:
                n_drop += 1
                r["note"] = f"simulation not converged ({sim['reason']}, {sim['newton_iterations']} iterations)"
        else:
            src = rows_index.get(key(r))
            if src is None:
                n_missing += 1
                r["note"] = f"no row in {rows_index['_name']}"
            elif src.get("converged", True) is False or src["kappa_per_mm"] is None:
                n_missing += 1
                r["note"] = f"the row in {rows_index['_name']} did not converge (no value)"
            else:
                r.update(_sim_values(src))
                if src.get("rows") is not None and (src["rows"], src.get("motifs")) != (r["rows"], r["motifs"]):
                    r["note"] = "; ".join(filter(None, [r.get("note"), f"simulated on a {src['rows']} rows"
                                                        + (f" x {src['motifs']} motifs" if src.get("motifs") else "")
                                                        + " patch"]))
    if mirror_back:
        for r in rows:
            if r["side"] == "back":
                f = front.get(key(r, "front"))
                if f is None:
                    r["note"] = "no front patch to mirror"
                    continue
                r.update({c: f[c] for c in LAW_MEASURED + ("note",) if c in f})
                r["note"] = (f"mirrored from {f['patch']}" + (f"; {f['note']}" if f.get("note") else ""))
                n_mirror += 1
    return {"source": "simulation" if simulate else rows_index["_name"], "simulated": n_sim,
            "not_converged": n_drop, "mirrored": n_mirror, "missing": n_missing,
            "time_s": round(time.perf_counter() - t0, 2), "comments": comments, "sim_rows": sim_rows}
