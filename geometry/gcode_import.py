"""G-code -> printed elements: what an FDM print deposits on the fabric (printed-state mm).

Reads PrusaSlicer/SuperSlicer, Cura, Simplify3D and plain Marlin-style G-code: G0/G1,
arcs G2/G3 in the XY plane (linearised to 0.002 mm chord error), G20/G21 units, G90/G91
positions, M82/M83 extrusion (Marlin 2: G90/G91 also set the E mode, M82/M83 after them
override), G92, G28, retractions as negative E moves and firmware G10/G11, z-hops, travels,
comments ``;...`` and ``(...)``, line numbers and checksums.

Deposit: a positive E move first restores what earlier negative E moves retracted; only
the remainder is plastic. An extruded *segment* is an XY move that deposits; a *path* is a
run of consecutive segments with no travel, retraction or z change between them.

Bead model (Slic3r): cross-section (w - h) h + pi h^2 / 4, so a segment of length L that
deposits filament length E of diameter d has width w = A / h + h (1 - pi / 4), A = E pi d^2
/ (4 L). h is the ``;HEIGHT:`` hint when present, else the z step from the extrusion level
below (from the bed for the first). ``;WIDTH:`` hints, when present, give w directly.

Coordinates: a file written by :func:`inverse.gcode.write_gcode` carries its origin, flip
axis and fabric height in ``; selfshape ...`` header lines and reads back to pattern
coordinates; for other files bed coordinates are pattern coordinates (origin (0, 0)) and
the back side is un-mirrored about x = ``mirror_axis_x`` (default: the Ultimaker 2 bed
centre, 111.5 mm), x -> 2 a - x.
"""
from __future__ import annotations

import math
import os
import re

import numpy as np
import shapely

from geometry.elements import PrintedElement
from shellfem.errors import SelfshapeError

SEGMENT_DTYPE = np.dtype([
    ("x0", "f8"), ("y0", "f8"), ("x1", "f8"), ("y1", "f8"), ("z", "f8"),
    ("e_mm", "f8"),          # filament length deposited by the segment (after retractions)
    ("layer", "i4"),         # index of the segment's z among the distinct extrusion z, from 0
    ("width_hint", "f8"),    # ;WIDTH: in effect (nan if none)
    ("height_hint", "f8"),   # ;HEIGHT: in effect (nan if none)
    ("path", "i4"),          # extruded path index, from 0, in file order
    ("line", "i4"),          # 1-based source line
    ("type", "i2"),          # index into meta["types"] of the ;TYPE: in effect (-1 if none)
])

DEFAULT_FILAMENT_DIAMETER_MM = 1.75
DEFAULT_MIRROR_AXIS_X_MM = 111.5       # Ultimaker 2 bed centre, as inverse.printer.Printer
ARC_TOLERANCE_MM = 0.002

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)"
_PARAMS_RE = re.compile(r"\s*([A-Z])\s*(" + _NUMBER + r"|(?=\s|$))")     # a bare letter is a flag
_PARAMS_FULL_RE = re.compile(r"(?:\s*[A-Z](?:\s*" + _NUMBER + r"|(?=\s|$)))*\s*")
_CMD_RE = re.compile(r"([GMT])(\d+(?:\.\d+)?)")
_PAREN_RE = re.compile(r"\([^)]*\)")
_DIAMETER_RE = re.compile(r"(?:filament_diameter|filamentdiameters|material[._ ]diameter|filament diameter)"
                          r"\s*[:=,]\s*([0-9]*\.?[0-9]+)", re.IGNORECASE)
_LAYER_HEIGHT_RE = re.compile(r"^(?:layer_height\s*=|layerheight\s*,|layer height\s*:)\s*([0-9]*\.?[0-9]+)",
                              re.IGNORECASE)
_UNSUPPORTED_MOTION = {"G5": "cubic spline (G5)", "G5.1": "quadratic spline (G5.1)", "G6": "direct stepper move (G6)",
                       "G70": "unknown units (G70, use G20/G21)", "G71": "unknown units (G71, use G20/G21)"}


class GcodeElements(list):
    """list[PrintedElement] with a ``meta`` dict (counts, filament, warnings, ...)."""

    def __init__(self, items=(), meta=None):
        super().__init__(items)
        self.meta = meta or {}


def _fail(name, lineno, msg):
    raise SelfshapeError(f"{name}: line {lineno}: {msg}")


def _read_lines(path):
    name = os.path.basename(os.fspath(path))
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as e:
        raise SelfshapeError(f"{path}: cannot read G-code ({e.strerror})") from None
    if data[:4] == b"GCDE":
        raise SelfshapeError(f"{name}: line 1: binary G-code (.bgcode) is not supported; export plain text G-code")
    if b"\x00" in data[:65536]:
        raise SelfshapeError(f"{name}: line 1: not a text G-code file (binary data)")
    return name, data.decode("utf-8", errors="replace").splitlines()


class _State:
    """Machine state while reading: positions in mm, E in filament mm."""

    def __init__(self, name):
        self.name = name
        self.x = self.y = self.z = 0.0
        self.e = 0.0
        self.abs_xyz = True
        self.abs_e = True
        self.scale = 1.0
        self.plane = 17
        self.pending = 0.0          # filament retracted and not yet restored
        self.path = -1
        self.in_path = False
        self.width = math.nan
        self.height = math.nan
        self.type = -1
        self.types: list[str] = []
        self.units: set[str] = set()
        self.segs: list[tuple] = []
        self.meta = dict(filament_diameter_mm_file=None, layer_height_setting_mm=None, slicer=None,
                         selfshape={}, e_mode=None, n_retractions=0, n_firmware_retractions=0,
                         n_travels=0, n_arcs=0, stationary_extrusion_mm=0.0, layer_change_hints=0,
                         ignored_codes=set())

    def comment(self, c, lineno):
        c = c.strip()
        if not c:
            return
        if c.startswith("WIDTH:"):
            self.width = self._hint(c[6:], lineno, "WIDTH")
        elif c.startswith("HEIGHT:"):
            self.height = self._hint(c[7:], lineno, "HEIGHT")
        elif c.startswith("TYPE:"):
            t = c[5:].strip()
            if t not in self.types:
                self.types.append(t)
            self.type = self.types.index(t)
        elif c.startswith("LAYER_CHANGE") or c.startswith("LAYER:"):
            self.meta["layer_change_hints"] += 1
        elif c.startswith("selfshape "):
            k, _, v = c[10:].partition("=")
            self.meta["selfshape"][k.strip()] = v.strip()
        else:
            low = c.lower()
            if "diameter" in low and "nozzle" not in low[:20]:
                m = _DIAMETER_RE.search(c)
                if m and self.meta["filament_diameter_mm_file"] is None:
                    self.meta["filament_diameter_mm_file"] = float(m.group(1))
            elif "layer" in low:
                m = _LAYER_HEIGHT_RE.match(c)
                if m and self.meta["layer_height_setting_mm"] is None:
                    self.meta["layer_height_setting_mm"] = float(m.group(1))
            if self.meta["slicer"] is None and ("generated" in low or low.startswith("flavor")):
                self.meta["slicer"] = c[:80]

    def _hint(self, text, lineno, what):
        try:
            v = float(text)
        except ValueError:
            _fail(self.name, lineno, f";{what}: hint is not a number: {text.strip()!r}")
        if not (math.isfinite(v) and v > 0):
            _fail(self.name, lineno, f";{what}: hint must be > 0, got {v:g}")
        return v

    def move(self, nx, ny, nz, de, lineno):
        """Account one straight move to (nx, ny, nz) with E change de (mm)."""
        deposit = 0.0
        if de < 0:
            self.pending -= de
        elif de > 0:
            used = de if de < self.pending else self.pending
            self.pending -= used
            deposit = de - used
        moved = nx != self.x or ny != self.y
        if moved and deposit > 1e-12:
            if abs(nz - self.z) > 1e-6:
                _fail(self.name, lineno, "extruding move changes Z (spiral/non-planar printing is not supported)")
            if not self.in_path:
                self.path += 1
                self.in_path = True
            self.segs.append((self.x, self.y, nx, ny, nz, deposit, 0, self.width, self.height,
                              self.path, lineno, self.type))
        else:
            if moved or nz != self.z or de < 0:
                self.in_path = False
            if moved:
                self.meta["n_travels"] += 1
            if de < 0:
                self.meta["n_retractions"] += 1
            if deposit > 0:
                self.meta["stationary_extrusion_mm"] += deposit
        self.x, self.y, self.z = nx, ny, nz

    def target(self, p):
        """New (x, y, z) and E change from G0/G1/G2/G3 parameters."""
        s = self.scale
        if self.abs_xyz:
            nx = p["X"] * s if "X" in p else self.x
            ny = p["Y"] * s if "Y" in p else self.y
            nz = p["Z"] * s if "Z" in p else self.z
        else:
            nx = self.x + p.get("X", 0.0) * s
            ny = self.y + p.get("Y", 0.0) * s
            nz = self.z + p.get("Z", 0.0) * s
        de = 0.0
        if "E" in p:
            ev = p["E"] * s
            de = ev - self.e if self.abs_e else ev
            self.e += de
        return nx, ny, nz, de

    def arc(self, p, clockwise, lineno):
        if self.plane != 17:
            _fail(self.name, lineno, f"arc in plane G{self.plane} is not supported (XY plane G17 only)")
        x0, y0, z0 = self.x, self.y, self.z
        nx, ny, nz, de = self.target(p)
        s = self.scale
        if "R" in p:
            r = p["R"] * s
            dx, dy = nx - x0, ny - y0
            d = math.hypot(dx, dy)
            if d == 0 or abs(r) < d / 2 * (1 - 1e-9):
                _fail(self.name, lineno, f"arc radius R{p['R']:g} cannot join its end points")
            hh = math.sqrt(max(r * r - d * d / 4, 0.0))
            sgn = (1.0 if not clockwise else -1.0) * (1.0 if r > 0 else -1.0)
            cx = (x0 + nx) / 2 - sgn * hh * dy / d
            cy = (y0 + ny) / 2 + sgn * hh * dx / d
        elif "I" in p or "J" in p:
            cx, cy = x0 + p.get("I", 0.0) * s, y0 + p.get("J", 0.0) * s
        else:
            _fail(self.name, lineno, "arc needs I/J or R")
        rad = math.hypot(x0 - cx, y0 - cy)
        if rad == 0:
            _fail(self.name, lineno, "arc has zero radius")
        a0 = math.atan2(y0 - cy, x0 - cx)
        a1 = math.atan2(ny - cy, nx - cx)
        sweep = (a0 - a1) if clockwise else (a1 - a0)
        sweep %= 2 * math.pi
        if sweep < 1e-9:
            sweep = 2 * math.pi
        step = 2 * math.acos(max(1 - ARC_TOLERANCE_MM / rad, -1.0))
        n = max(1, math.ceil(sweep / step))
        sign = -1.0 if clockwise else 1.0
        self.meta["n_arcs"] += 1
        r1 = math.hypot(nx - cx, ny - cy)
        for k in range(1, n + 1):
            f = k / n
            if k == n:
                px, py = nx, ny
            else:
                a = a0 + sign * sweep * f
                rr = rad + (r1 - rad) * f
                px, py = cx + rr * math.cos(a), cy + rr * math.sin(a)
            self.move(px, py, z0 + (nz - z0) * f, de / n, lineno)


def _params(rest, name, lineno, flags_ok=False):
    """Parameters {letter: value}; a bare letter (a flag, e.g. G28 X) maps to nan."""
    out = {}
    for tok in rest.split():                    # fast path: "X1.5 Y2 E.03"
        c = tok[0]
        if len(tok) == 1 or not "A" <= c <= "Z":
            break
        try:
            out[c] = float(tok[1:])
        except ValueError:
            break
    else:
        return out
    if not _PARAMS_FULL_RE.fullmatch(rest):
        _fail(name, lineno, f"malformed parameters {rest.strip()!r}")
    out = {k: (float(v) if v else math.nan) for k, v in _PARAMS_RE.findall(rest)}
    if not flags_ok:
        for k, v in out.items():
            if v != v:
                _fail(name, lineno, f"parameter {k} has no value in {rest.strip()!r}")
    return out


def _parse(path):
    """Parse a G-code file. Returns (segments structured array SEGMENT_DTYPE, meta dict)."""
    name, lines = _read_lines(path)
    st = _State(name)
    for lineno, raw in enumerate(lines, 1):
        i = raw.find(";")
        if i >= 0:
            st.comment(raw[i + 1:], lineno)
            code = raw[:i]
        else:
            code = raw
        if "(" in code:
            code = _PAREN_RE.sub(" ", code)
        code = code.strip().upper()
        if not code:
            continue
        if code[0] == "N":                      # line number and checksum
            j = 1
            while j < len(code) and code[j].isdigit():
                j += 1
            code = code[j:].strip()
            if not code:
                continue
        if "*" in code:
            code = code[:code.index("*")].strip()
        head, _, rest = code.partition(" ")
        if head != "G1" and head != "G0":
            m = _CMD_RE.match(code)
            if m is None:
                if code[0] in "XYZEF":
                    _fail(name, lineno, f"move without a command word: {raw.strip()[:40]!r}")
                _fail(name, lineno, f"not a G-code command: {raw.strip()[:40]!r}")
            letter, num = m.group(1), m.group(2)
            head = letter + (num.lstrip("0") or "0") if "." not in num else letter + num
            rest = code[m.end():]
        cmd = head
        letter = cmd[0]
        if cmd == "G1" or cmd == "G0":
            p = _params(rest, name, lineno)
            nx, ny, nz, de = st.target(p)
            st.move(nx, ny, nz, de, lineno)
        elif letter == "T":
            continue
        elif cmd in ("G2", "G3"):
            st.arc(_params(rest, name, lineno), cmd == "G2", lineno)
        elif cmd == "G92":
            p = _params(rest, name, lineno)
            if not p:
                p = dict(X=0.0, Y=0.0, Z=0.0, E=0.0)
            s = st.scale
            st.x = p["X"] * s if "X" in p else st.x
            st.y = p["Y"] * s if "Y" in p else st.y
            st.z = p["Z"] * s if "Z" in p else st.z
            st.e = p["E"] * s if "E" in p else st.e
            if "X" in p or "Y" in p or "Z" in p:
                st.in_path = False
        elif cmd == "G90":
            st.abs_xyz = st.abs_e = True
        elif cmd == "G91":
            st.abs_xyz = st.abs_e = False
        elif cmd == "M82":
            st.abs_e = True
            st.meta["e_mode"] = "absolute"
        elif cmd == "M83":
            st.abs_e = False
            st.meta["e_mode"] = "relative"
        elif cmd == "G21":
            st.scale = 1.0
            st.units.add("mm")
        elif cmd == "G20":
            st.scale = 25.4
            st.units.add("inch")
        elif cmd == "G10":
            p = _params(rest, name, lineno, flags_ok=True)
            if "L" not in p and "P" not in p:     # firmware retraction (not tool offsets)
                st.meta["n_firmware_retractions"] += 1
                st.in_path = False
        elif cmd == "G11":
            st.in_path = False
        elif cmd == "G28":
            p = _params(rest, name, lineno, flags_ok=True)
            axes = [a for a in "XYZ" if a in p] or ["X", "Y", "Z"]
            for a in axes:
                setattr(st, a.lower(), 0.0)
            st.in_path = False
        elif cmd in ("G17", "G18", "G19"):
            st.plane = int(cmd[1:])
        elif cmd in _UNSUPPORTED_MOTION:
            _fail(name, lineno, f"{_UNSUPPORTED_MOTION[cmd]} is not supported")
        elif letter == "G":
            st.meta["ignored_codes"].add(cmd)
    seg = np.array(st.segs, dtype=SEGMENT_DTYPE) if st.segs else np.zeros(0, SEGMENT_DTYPE)
    if len(seg):
        zr = np.round(seg["z"], 4)
        levels, seg["layer"] = np.unique(zr, return_inverse=True)
    else:
        levels = np.zeros(0)
    meta = st.meta
    meta.update(file=os.fspath(path), name=name, n_lines=len(lines), n_segments=int(len(seg)),
                n_paths=int(st.path + 1), n_layers=int(len(levels)), layer_z_mm=levels.tolist(),
                types=st.types, ignored_codes=sorted(meta["ignored_codes"]),
                units="+".join(sorted(st.units)) or "mm (default)", e_mode=meta["e_mode"] or "absolute (default)")
    return seg, meta


def parse_gcode(path) -> np.ndarray:
    """Extruded segments of a G-code file: structured array with fields x0, y0, x1, y1, z,
    e_mm (deposited filament mm), layer, width_hint, height_hint (nan when absent), path,
    line, type (bed mm). Raises SelfshapeError (file and line) on unreadable input."""
    return _parse(path)[0]


def _header_float(meta, key, lineno_name):
    v = meta["selfshape"].get(key)
    if v is None:
        return None
    try:
        return [float(t) for t in v.split(",")]
    except ValueError:
        raise SelfshapeError(f"{lineno_name}: selfshape header {key} = {v!r} is not a number") from None


def _finite(what, v):
    try:
        v = float(v)
    except (TypeError, ValueError):
        v = math.nan
    if not math.isfinite(v):
        raise SelfshapeError(f"read_gcode: {what} must be a finite number")
    return v


def segment_widths(seg, heights, filament_diameter_mm):
    """Bead width (mm) per segment: the ;WIDTH: hint or the bead model inverted from the
    deposited volume. heights: (n,) layer heights (mm). Vectorised."""
    length = np.hypot(seg["x1"] - seg["x0"], seg["y1"] - seg["y0"])
    area = seg["e_mm"] * (math.pi * filament_diameter_mm ** 2 / 4.0) / length
    w_volume = area / heights + heights * (1.0 - math.pi / 4.0)
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


def read_gcode(path, *, side=None, mirror_axis_x=None, filament_diameter_mm=None, min_width_mm=0.1,
               cap="square", origin_mm=None, bed_z_mm=None, exclude_types=()) -> GcodeElements:
    """What a G-code print deposits: one PrintedElement per connected printed shape of
    constant stacked thickness (kind "gcode"), in printed-state mm, in print order.

    side: "front"/"back" (default: the selfshape header's, else "front"); the back is
    un-mirrored x -> 2 a - x with a = mirror_axis_x (default header, else 111.5 mm).
    filament_diameter_mm: used when the file does not state it (default 1.75, with a
    warning in ``.meta["warnings"]``). Paths thinner than min_width_mm are dropped. cap:
    "square", "round" or "flat" path ends. origin_mm: bed position of pattern (0, 0)
    (default header, else (0, 0)). bed_z_mm: z of the fabric top (default header, else 0).
    exclude_types: ;TYPE: names whose extrusion is ignored (e.g. "Custom" for PrusaSlicer's
    intro line, "SKIRT").
    Thickness = sum of the layer heights stacked at the shape. Returns a list with ``.meta``.
    """
    if cap not in ("square", "round", "flat"):
        raise SelfshapeError(f"read_gcode: cap must be \"square\", \"round\" or \"flat\", got {cap!r}")
    seg, meta = _parse(path)
    name = meta["name"]
    warnings = []
    hdr_side = meta["selfshape"].get("side")
    if side is None:
        side = hdr_side or "front"
    if side not in ("front", "back"):
        raise SelfshapeError(f"read_gcode: side must be \"front\" or \"back\", got {side!r}")
    if hdr_side and hdr_side != side:
        warnings.append(f"reading as side {side} a file written for side {hdr_side}")
    excluded = [i for i, t in enumerate(meta["types"]) if t in set(exclude_types)]
    if excluded:
        n0 = len(seg)
        seg = seg[~np.isin(seg["type"], excluded)]
        meta["excluded_segments"] = n0 - len(seg)
    if len(seg) == 0:
        raise SelfshapeError(f"{name}: line {meta['n_lines']}: no extruding move in the file "
                             f"({meta['n_lines']} lines{', after exclude_types' if excluded else ''})")
    # settings: explicit argument > file header > default
    if meta["filament_diameter_mm_file"] is not None:
        d_f, d_src = meta["filament_diameter_mm_file"], "file comment"
        if filament_diameter_mm is not None and abs(_finite("filament_diameter_mm", filament_diameter_mm) - d_f) > 1e-9:
            warnings.append(f"filament diameter {filament_diameter_mm:g} mm given, the file says {d_f:g} mm: "
                            f"using the file's")
    elif filament_diameter_mm is not None:
        d_f, d_src = _finite("filament_diameter_mm", filament_diameter_mm), "argument"
    else:
        d_f, d_src = DEFAULT_FILAMENT_DIAMETER_MM, "default"
        warnings.append(f"{name}: filament diameter not stated in the file, assuming {d_f:g} mm")
    if not (math.isfinite(d_f) and d_f > 0):
        raise SelfshapeError(f"{name}: filament diameter must be > 0, got {d_f:g}")
    hdr_origin = _header_float(meta, "origin_mm", name)
    origin = np.asarray(origin_mm if origin_mm is not None else (hdr_origin or (0.0, 0.0)), float)
    if origin.shape != (2,) or not np.isfinite(origin).all():
        raise SelfshapeError(f"read_gcode: origin_mm must be (x, y), got {origin_mm!r}")
    hdr_axis = _header_float(meta, "mirror_axis_x_mm", name)
    axis = _finite("mirror_axis_x", mirror_axis_x if mirror_axis_x is not None else
                   (hdr_axis[0] if hdr_axis else DEFAULT_MIRROR_AXIS_X_MM))
    hdr_bed = _header_float(meta, "bed_offset_z_mm", name)
    bed_z = _finite("bed_z_mm", bed_z_mm if bed_z_mm is not None else (hdr_bed[0] if hdr_bed else 0.0))
    min_width_mm = _finite("min_width_mm", min_width_mm)

    # layer heights: hint, else the step from the extrusion level below
    levels = np.asarray(meta["layer_z_mm"])
    steps = np.diff(np.r_[bed_z, levels])
    heights = np.where(np.isfinite(seg["height_hint"]), seg["height_hint"], steps[seg["layer"]])
    bad = np.flatnonzero(heights <= 1e-6)
    if len(bad):
        k = bad[0]
        raise SelfshapeError(f"{name}: line {seg['line'][k]}: extrusion at z = {seg['z'][k]:g} mm is not above "
                             f"the fabric at z = {bed_z:g} mm")
    widths, w_volume, length = segment_widths(seg, heights, d_f)
    run, first = _runs(seg, widths, heights)
    n_runs = int(run[-1]) + 1
    run_len = np.bincount(run, length, n_runs)
    run_w = np.bincount(run, widths * length, n_runs) / run_len
    run_h = heights[first]
    run_layer = seg["layer"][first]
    run_line = seg["line"][first]
    run_path = seg["path"][first]

    # polylines per run, in pattern coordinates
    p0 = np.column_stack([seg["x0"], seg["y0"]])
    p1 = np.column_stack([seg["x1"], seg["y1"]])
    start_idx = np.flatnonzero(first)
    pos1 = np.arange(len(seg)) + run + 1
    coords = np.empty((len(seg) + n_runs, 2))
    coords[pos1] = p1
    coords[start_idx + np.arange(n_runs)] = p0[start_idx]
    if side == "back":
        coords[:, 0] = 2.0 * axis - coords[:, 0]
    coords -= origin
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
    meta["dropped_thin_paths"] = int((~keep).sum())
    if not keep.any():
        raise SelfshapeError(f"{name}: line {seg['line'][0]}: every extruded path is thinner than "
                             f"min_width_mm = {min_width_mm:g} mm")
    beads = shapely.buffer(lines[keep], run_w[keep] / 2.0, cap_style=cap, join_style="round", quad_segs=8)
    r_layer, r_h, r_line, r_path = run_layer[keep], run_h[keep], run_line[keep], run_path[keep]

    pieces = stack_beads(beads, r_layer, r_h, sliver=0.2 * min_width_mm)
    elements = _elements(pieces, beads, r_line, r_path, side, name)

    hint = np.isfinite(seg["width_hint"])
    meta.update(
        side=side, origin_mm=origin.tolist(), mirror_axis_x_mm=axis, bed_z_mm=bed_z,
        filament_diameter_mm=d_f, filament_diameter_source=d_src,
        layer_heights_mm=steps.tolist(), n_runs=n_runs, n_elements=len(elements),
        extruded_filament_mm=float(seg["e_mm"].sum()),
        plastic_volume_mm3=float(seg["e_mm"].sum() * math.pi * d_f ** 2 / 4),
        width_source="hint" if hint.all() else ("volume" if not hint.any() else "mixed"),
        width_hint_vs_volume_max_rel=(float(np.max(np.abs(w_volume[hint] / widths[hint] - 1)))
                                      if hint.any() else None),
        path_widths_mm=run_w.tolist(), warnings=warnings)
    return GcodeElements(elements, meta)


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
