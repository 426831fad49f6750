"""G-code, the format of a print: read into printed elements, written from planned moves (mm).

Reader: PrusaSlicer/SuperSlicer, Cura, Simplify3D and plain Marlin-style G-code: G0/G1,
arcs G2/G3 in the XY plane (linearised to 0.002 mm chord error), G20/G21 units, G90/G91
positions, M82/M83 extrusion (Marlin 2: G90/G91 also set the E mode, M82/M83 after them
override), G92, G28, retractions as negative E moves and firmware G10/G11, z-hops, travels,
comments ``;...`` and ``(...)``, line numbers and checksums.

Deposit: a positive E move first restores what earlier negative E moves retracted; only
the remainder is plastic. An extruded *segment* is an XY move that deposits; a *path* is a
run of consecutive segments with no travel, retraction or z change between them. Layer
height h is the ``;HEIGHT:`` hint when present, else the z step from the extrusion level
below (from the fabric for the first); what the segments deposit is geometry.beads.

Writer (:class:`GcodeWriter`): the header, travels with retraction and z-hop, extrusions
with E from the bead volume, ``;LAYER_CHANGE`` / ``;Z:`` / ``;HEIGHT:`` / ``;TYPE:`` /
``;WIDTH:`` hints, and the end sequence; what to print (ribbons -> layered, ordered paths)
is planned by inverse.gcode.

Header (:class:`GcodeHeader`): every setting the writer states, as ``; selfshape key =
value`` lines (side, frame origin and flip axis, fabric height, counts) and slicer-style
``; key = value`` lines (printer settings), each read back by :func:`read_header`.

Frame (seed section 5.5): a pattern point (x, y) is printed on the front at bed
(x + ox, y + oy), (ox, oy) = origin. To print the back, the frame is flipped about the bed
line x = a (the mirror axis), which sends the fabric point at bed x to bed 2a - x, y
unchanged: the back is printed at bed (2a - (x + ox), y + oy), the same fabric point as the
front (:func:`to_bed`, :func:`from_bed`). A file with a selfshape header reads back to
pattern coordinates; for other files bed coordinates are pattern coordinates (origin
(0, 0)) and the back side is un-mirrored about x = ``mirror_axis_x`` (default: the
Ultimaker 2 bed centre, 111.5 mm).
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass

import numpy as np

from geometry.beads import MAX_BEAD_MM, printed_elements
from geometry.schema import COORD_MAX_MM, PRINTER_NUMBERS
from shellfem.errors import SelfshapeError
from shellfem.infiles import read_input_bytes

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
DEFAULT_MIRROR_AXIS_X_MM = 111.5       # centre of the Ultimaker 2 bed (223 mm)
ARC_TOLERANCE_MM = 0.002
#: Most extruded segments one file may hold (arcs linearised): the bound on the work a
#: G-code input can ask for (about 40x a dense 200 x 200 mm print at 0.8 mm beads).
MAX_SEGMENTS = 2_000_000
#: Most distinct extrusion heights: stacking layers of different footprints costs an overlay
#: per layer and thickness class (quadratic in the layers); a print on fabric has a few
#: layers (2 mm of plastic is 10 at 0.2 mm), 500 is a 100 mm tall object.
MAX_LAYERS = 500

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)"
_PARAMS_RE = re.compile(r"\s*([A-Z])\s*(" + _NUMBER + r"|(?=\s|$))")     # a bare letter is a flag
_PARAMS_FULL_RE = re.compile(r"(?:\s*[A-Z](?:\s*" + _NUMBER + r"|(?=\s|$)))*\s*")
_CMD_RE = re.compile(r"([GMT])(\d+(?:\.\d+)?)")
_PAREN_RE = re.compile(r"\([^)]*\)")
_DIAMETER_RE = re.compile(r"(?:filament_diameter|filamentdiameters|material[._ ]diameter|filament diameter)"
                          r"\s*[:=,]\s*([0-9]*\.?[0-9]+)", re.IGNORECASE)
_LAYER_HEIGHT_RE = re.compile(r"^(?:layer_height\s*=|layerheight\s*,|layer height\s*:)\s*([0-9]*\.?[0-9]+)",
                              re.IGNORECASE)
_SETTING_RE = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)\s*=\s*(.*)")               # slicer-style "key = value"
_UNSUPPORTED_MOTION = {"G5": "cubic spline (G5)", "G5.1": "quadratic spline (G5.1)", "G6": "direct stepper move (G6)",
                       "G70": "unknown units (G70, use G20/G21)", "G71": "unknown units (G71, use G20/G21)"}


class GcodeElements(list):
    """list[PrintedElement] with a ``meta`` dict (counts, filament, warnings, ...)."""

    def __init__(self, items=(), meta=None):
        super().__init__(items)
        self.meta = meta or {}


# ---------------------------------------------------------------- frame

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


# ---------------------------------------------------------------- header

@dataclass
class GcodeHeader:
    """Every setting a selfshape G-code file states (mm, mm/s, deg C).

    side: "front" or "back"; origin_mm: bed position of pattern (0, 0); mirror_axis_x_mm:
    bed x of the frame's flip line; bed_offset_z_mm: fabric top above the bed; ribbons,
    layers: what the file prints; the rest are the printer settings the moves were made
    with; relative_e: M83 (True) or M82 extrusion.
    """
    side: str
    origin_mm: tuple
    mirror_axis_x_mm: float
    bed_offset_z_mm: float
    ribbons: int
    layers: int
    bed_shape_mm: tuple
    nozzle_diameter_mm: float
    filament_diameter_mm: float
    layer_height_mm: float
    first_layer_height_mm: float
    extrusion_multiplier: float
    print_speed_mm_s: float
    travel_speed_mm_s: float
    retract_length_mm: float
    retract_speed_mm_s: float
    retract_lift_mm: float
    temperature_c: float
    bed_temperature_c: float
    relative_e: bool


# field -> key in the file, its format (value -> text) and parser (text -> value)
_SELFSHAPE_KEYS = (
    ("side", "side", str, lambda t: _choice(t, ("front", "back"))),
    ("origin_mm", "origin_mm", lambda v: f"{v[0]:.6f}, {v[1]:.6f}", lambda t: _numbers(t, ",", 2)),
    ("mirror_axis_x_mm", "mirror_axis_x_mm", lambda v: f"{v:.6f}", float),
    ("bed_offset_z_mm", "bed_offset_z_mm", lambda v: f"{v:.6f}", float),
    ("ribbons", "ribbons", str, int),
    ("layers", "layers", str, int),
)
_SETTING_KEYS = (
    ("bed_shape_mm", "bed_shape", lambda v: f"{v[0]:g} x {v[1]:g}", lambda t: _numbers(t, "x", 2)),
) + tuple((f, k, lambda v: f"{v:g}", float) for f, k in (
    ("nozzle_diameter_mm", "nozzle_diameter"), ("filament_diameter_mm", "filament_diameter"),
    ("layer_height_mm", "layer_height"), ("first_layer_height_mm", "first_layer_height"),
    ("extrusion_multiplier", "extrusion_multiplier"), ("print_speed_mm_s", "print_speed"),
    ("travel_speed_mm_s", "travel_speed"), ("retract_length_mm", "retract_length"),
    ("retract_speed_mm_s", "retract_speed"), ("retract_lift_mm", "retract_lift"),
    ("temperature_c", "temperature"), ("bed_temperature_c", "bed_temperature")))
FRAME_NOTE = ("; pattern (x, y) is printed at bed (x + ox, y + oy) on the front and at "
              "(2 a - x - ox, y + oy) on the back (frame flipped about bed x = a)")


def _choice(text, allowed):
    if text not in allowed:
        raise ValueError(text)
    return text


def _numbers(text, sep, n):
    vals = tuple(float(t) for t in text.split(sep))
    if len(vals) != n:
        raise ValueError(text)
    return vals


def header_lines(h: GcodeHeader) -> list[str]:
    """The header of a selfshape G-code file: its settings as comments, then the start
    sequence (units, positioning, E mode, temperatures, homing)."""
    return (["; generated by selfshape (inverse.gcode.write_gcode)"]
            + [f"; selfshape {key} = {fmt(getattr(h, f))}" for f, key, fmt, _ in _SELFSHAPE_KEYS]
            + [FRAME_NOTE]
            + [f"; {key} = {fmt(getattr(h, f))}" for f, key, fmt, _ in _SETTING_KEYS]
            + ["G21 ; millimetres",
               "G90 ; absolute positions",
               "M83 ; relative extrusion" if h.relative_e else "M82 ; absolute extrusion",
               f"M140 S{h.bed_temperature_c:.0f}",
               f"M104 S{h.temperature_c:.0f}",
               "G28 ; home",
               f"M190 S{h.bed_temperature_c:.0f}" if h.bed_temperature_c > 0 else "; no bed heating (fabric)",
               f"M109 S{h.temperature_c:.0f}",
               "G92 E0",
               "M107"])


def _header_from_meta(meta) -> GcodeHeader:
    """The GcodeHeader of a parsed file (meta of _parse); raises if a setting is missing or malformed."""
    name = meta["name"]
    if not meta["selfshape"]:
        raise SelfshapeError(f"{name}: no selfshape header (the file was not written by selfshape)")
    values = {}
    for table, keys, what, kind in ((meta["selfshape"], _SELFSHAPE_KEYS, "selfshape header", "selfshape"),
                                    (meta["settings"], _SETTING_KEYS, "header setting", "setting")):
        for f, key, _, parse in keys:
            if key not in table:
                raise SelfshapeError(f"{name}: {what} {key} is missing")
            try:
                values[f] = parse(table[key])
            except ValueError:
                line = meta["header_lines"].get((kind, key), "?")
                raise SelfshapeError(f"{name}: line {line}: {what} {key} is not valid") from None
    return GcodeHeader(**values, relative_e=meta["e_mode"] == "relative")


def read_header(path) -> GcodeHeader:
    """The settings stated by a G-code file written by selfshape (:class:`GcodeHeader`).
    Raises SelfshapeError when the file has no selfshape header or a setting is missing."""
    return _header_from_meta(_parse(path)[1])


# ---------------------------------------------------------------- reader

def _fail(name, lineno, msg):
    raise SelfshapeError(f"{name}: line {lineno}: {msg}")


def _read_lines(path):
    name = os.path.basename(os.fspath(path))
    data = read_input_bytes(path, "G-code file", name)
    if data[:4] == b"GCDE":
        raise SelfshapeError(f"{name}: line 1: binary G-code (.bgcode) is not supported; export plain text G-code")
    if b"\x00" in data[:65536]:
        raise SelfshapeError(f"{name}: line 1: not a text G-code file (binary data)")
    # utf-8-sig: a byte-order mark (Windows editors) is not a command
    return name, data.decode("utf-8-sig", errors="replace").splitlines()


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
                         ignored_codes=set(), settings={}, header_lines={})

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
            self.meta["header_lines"][("selfshape", k.strip())] = lineno
        else:
            if "=" in c:
                m = _SETTING_RE.fullmatch(c)
                if m:
                    self.meta["settings"][m.group(1)] = m.group(2).strip()
                    self.meta["header_lines"][("setting", m.group(1))] = lineno
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
            _fail(self.name, lineno, f";{what}: hint is not a number")
        if not (math.isfinite(v) and 0 < v <= MAX_BEAD_MM):
            _fail(self.name, lineno, f";{what}: hint must be in (0, {MAX_BEAD_MM:g}] mm, got {v:.4g}")
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
        if max(abs(nx), abs(ny), abs(nz)) > COORD_MAX_MM:
            _fail(self.name, lineno, f"a move beyond +-{COORD_MAX_MM:g} mm (10 m) from the bed origin")
        if moved and deposit > 1e-12:
            if abs(nz - self.z) > 1e-6:
                _fail(self.name, lineno, "extruding move changes Z (spiral/non-planar printing is not supported)")
            if not self.in_path:
                self.path += 1
                self.in_path = True
            if len(self.segs) >= MAX_SEGMENTS:
                _fail(self.name, lineno, f"more than {MAX_SEGMENTS:,} extruded segments (arcs linearised); "
                                         f"selfshape reads prints of at most that many")
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
        if not rad <= COORD_MAX_MM:          # also nan: the linearisation would never end
            _fail(self.name, lineno, f"arc radius beyond {COORD_MAX_MM:g} mm (10 m)")
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
        if not math.isfinite(out[c]):       # "Xinf", "Ynan", "X1e999"
            _fail(name, lineno, f"parameter {c} is not a finite number")
    else:
        return out
    if not _PARAMS_FULL_RE.fullmatch(rest):
        _fail(name, lineno, "malformed parameters")
    out = {k: (float(v) if v else math.nan) for k, v in _PARAMS_RE.findall(rest)}
    for k, v in out.items():
        if math.isinf(v):                   # a few hundred digits
            _fail(name, lineno, f"parameter {k} is not a finite number")
        if v != v and not flags_ok:
            _fail(name, lineno, f"parameter {k} has no value")
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
                    _fail(name, lineno, "move without a command word (G0/G1)")
                _fail(name, lineno, "not a G-code command (the file is not G-code, or not plain G-code)")
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
        if len(levels) > MAX_LAYERS:
            first = int(seg["line"][np.flatnonzero(seg["layer"] == MAX_LAYERS)[0]])
            _fail(name, first, f"more than {MAX_LAYERS} extrusion heights (layers); selfshape reads prints of at "
                               f"most that many (a print on fabric has a few)")
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
        vals = [float(t) for t in v.split(",")]
    except ValueError:
        raise SelfshapeError(f"{lineno_name}: selfshape header {key} is not a number") from None
    if not all(abs(x) <= COORD_MAX_MM for x in vals):     # also inf and nan
        raise SelfshapeError(f"{lineno_name}: selfshape header {key} is not a finite length within "
                             f"+-{COORD_MAX_MM:g} mm")
    return vals


def _finite(what, v):
    try:
        v = float(v)
    except (TypeError, ValueError):
        v = math.nan
    if not math.isfinite(v):
        raise SelfshapeError(f"read_gcode: {what} must be a finite number")
    return v


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
    spec = PRINTER_NUMBERS["filament_diameter_mm"]
    if not (spec.lo <= d_f <= spec.hi):
        raise SelfshapeError(f"{name}: filament diameter ({d_src}) must be in {spec.describe()}, got {d_f:.4g}")
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
    # the nozzle must be above the fabric whatever the ;HEIGHT: hint says (Z-5 with a hint was
    # read as a 0.4 mm bead printed 5 mm under the bed, issue 19)
    bad = np.flatnonzero((heights <= 1e-6) | (seg["z"] <= bed_z + 1e-6))
    if len(bad):
        k = bad[0]
        raise SelfshapeError(f"{name}: line {seg['line'][k]}: extrusion at z = {seg['z'][k]:g} mm is not above "
                             f"the fabric at z = {bed_z:g} mm")
    p0 = from_bed(np.column_stack([seg["x0"], seg["y0"]]), origin, side, axis)
    p1 = from_bed(np.column_stack([seg["x1"], seg["y1"]]), origin, side, axis)
    elements, dep = printed_elements(seg, p0, p1, heights, d_f, min_width_mm, cap, side, name)
    meta["dropped_thin_paths"] = dep["dropped_thin_paths"]
    widths, w_volume = dep["widths"], dep["w_volume"]

    hint = np.isfinite(seg["width_hint"])
    meta.update(
        side=side, origin_mm=origin.tolist(), mirror_axis_x_mm=axis, bed_z_mm=bed_z,
        filament_diameter_mm=d_f, filament_diameter_source=d_src,
        layer_heights_mm=steps.tolist(), n_runs=dep["n_runs"], n_elements=len(elements),
        extruded_filament_mm=float(seg["e_mm"].sum()),
        plastic_volume_mm3=float(seg["e_mm"].sum() * math.pi * d_f ** 2 / 4),
        width_source="hint" if hint.all() else ("volume" if not hint.any() else "mixed"),
        width_hint_vs_volume_max_rel=(float(np.max(np.abs(w_volume[hint] / widths[hint] - 1)))
                                      if hint.any() else None),
        path_widths_mm=dep["path_widths_mm"].tolist(), warnings=warnings)
    return GcodeElements(elements, meta)


# ---------------------------------------------------------------- writer

#: a G-code word whose number is not finite (what Python formats for inf/nan)
_NON_FINITE_WORD = re.compile(r"(?:^|\s)[A-Za-z][+-]?(?:inf|nan)(?![A-Za-z])", re.I)


class GcodeWriter:
    """The text of one print, line by line, with the tool position and print statistics.

    Starts with the header of ``header`` (whose speeds, retraction and E mode the moves use);
    z_speed_mm_s: speed of z moves; travels longer than retract_min_travel_mm retract and hop.
    Statistics (``stats``): print and travel length (mm), extruded filament (mm),
    retractions, estimated time (s).
    """

    def __init__(self, header: GcodeHeader, z_speed_mm_s: float, retract_min_travel_mm: float):
        self.h = header
        self.rel = header.relative_e
        self.z_speed_mm_s = z_speed_mm_s
        self.retract_min_travel_mm = retract_min_travel_mm
        self.lines: list[str] = header_lines(header)
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
        if self.retracted or self.h.retract_length_mm == 0:
            return
        f = self.h.retract_speed_mm_s
        self.lines.append(f"G1 {self._e_word(-self.h.retract_length_mm)} F{f * 60:.0f}")
        self.retracted = True
        self.stats["n_retractions"] += 1
        self.stats["estimated_time_s"] += self.h.retract_length_mm / f

    def unretract(self):
        if not self.retracted:
            return
        f = self.h.retract_speed_mm_s
        self.lines.append(f"G1 {self._e_word(self.h.retract_length_mm)} F{f * 60:.0f}")
        self.retracted = False
        self.stats["estimated_time_s"] += self.h.retract_length_mm / f

    def move_z(self, z):
        if abs(z - self.z) > 1e-9:
            self.lines.append(f"G1 Z{z:.3f} F{self.z_speed_mm_s * 60:.0f}")
            self.stats["estimated_time_s"] += abs(z - self.z) / self.z_speed_mm_s
            self.z = z

    def travel(self, xy, z):
        """Go to (xy, z) without extruding: retract and hop when the way is long."""
        dist = float(np.hypot(*(xy - self.xy)))
        if dist > self.retract_min_travel_mm or abs(z - self.z) > 1e-9:
            self.retract()
            self.move_z(max(z, self.z) + self.h.retract_lift_mm)
        if dist > 0:
            self.lines.append(f"G0 X{xy[0]:.3f} Y{xy[1]:.3f} F{self.h.travel_speed_mm_s * 60:.0f}")
            self.stats["travel_length_mm"] += dist
            self.stats["estimated_time_s"] += dist / self.h.travel_speed_mm_s
            self.xy = xy.copy()
        self.move_z(z)
        self.unretract()

    def extrude(self, pts, e_per_mm):
        """Print the polyline ``pts`` (k, 2), starting at the current position pts[0], with
        ``e_per_mm`` filament mm per mm of path."""
        seg = np.hypot(*np.diff(pts, axis=0).T)
        de = seg * e_per_mm
        e_abs = self.e + np.cumsum(de)
        words = de if self.rel else e_abs
        lines = [f"G1 X{x:.3f} Y{y:.3f} E{e:.5f}"
                 for x, y, e in zip(pts[1:, 0].tolist(), pts[1:, 1].tolist(), words.tolist())]
        lines[0] += f" F{self.h.print_speed_mm_s * 60:.0f}"
        self.lines += lines
        self.e = float(e_abs[-1])
        length = float(seg.sum())
        self.stats["print_length_mm"] += length
        self.stats["extruded_filament_mm"] += float(de.sum())
        self.stats["estimated_time_s"] += length / self.h.print_speed_mm_s
        self.xy = pts[-1].copy()

    def layer_change(self, z, height):
        """Hints that a layer of ``height`` mm at ``z`` mm starts."""
        self.lines += [";LAYER_CHANGE", f";Z:{z:.3f}", f";HEIGHT:{height:g}"]

    def feature(self, kind, width, comment):
        """Hints for the next extrusion: its ;TYPE: ``kind``, ;WIDTH: (mm) and a comment."""
        self.lines += [f";TYPE:{kind}", f";WIDTH:{width:g}", f"; {comment}"]

    def finish(self):
        """Retract, lift 10 mm, heaters and fan off, motors off."""
        self.retract()
        self.move_z(self.z + 10.0)
        self.lines += ["M104 S0", "M140 S0", "M107", "M84", "; end of selfshape print"]

    def write(self, path):
        """Write the lines to ``path`` atomically (a temporary file in the same folder, renamed;
        removed on any failure, Ctrl-C included: shellfem.outfiles.write_text_file)."""
        from shellfem.outfiles import NonFiniteOutput, write_text_file
        for k, line in enumerate(self.lines, 1):     # G-code drives hardware: never "Einf" or "Xnan"
            word = _NON_FINITE_WORD.search(line.split(";", 1)[0])
            if word:
                raise NonFiniteOutput(f"{os.path.basename(os.fspath(path))}: line {k}: {word.group().strip()} "
                                      f"is not a finite number; nothing is written")
        write_text_file(path, "\n".join(self.lines) + "\n")
