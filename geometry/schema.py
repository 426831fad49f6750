"""The input schema: every numeric key of a pattern and of a printer file, with its type,
unit and physical range, and the strict checks that enforce them (one-line SelfshapeErrors).

Why a schema: an input can be syntactically fine and physically absurd (a 1e-300 mm
filament writes ``Einf`` into G-code that goes to a real printer; a stretch of 135 simulates
to a blob; ``nozzle_mm = true`` would be read as 1 mm). Each value is therefore checked
against a range with a stated reason, and the same tables drive the reader
(geometry.patterns, inverse.printer), the documentation (docs/pattern-format.md, "Ranges")
and the generated bad-input tests (tests/test_contract_inputs.py), so a key added here is
validated and tested without further lists.

Strictness: a number is a TOML integer or float (Python int/float/numpy number), never a
bool, never a string ("0.8" is an error, not 0.8); it must be finite and inside its range.
An integer key also refuses floats. Unknown keys are errors that suggest the closest valid
key (difflib), see :func:`check_keys`.
"""
from __future__ import annotations

import difflib
import math
import numbers
from dataclasses import dataclass

from shellfem.errors import SelfshapeError

#: Largest |coordinate| of any point in a pattern (mm): 10 m, beyond any printer bed or fabric.
COORD_MAX_MM = 1.0e4
#: Narrowest printable feature (mm): below a 0.1 mm nozzle's bead no FDM print exists.
MIN_FEATURE_MM = 0.1
#: Finest geometric detail kept (mm): polygon vertices that deviate less than this from the
#: line through their neighbours are dropped (Douglas-Peucker, topology kept) from fabric
#: outlines, regions and every printed piece. 0.1 um is 1/1000 of the narrowest printable
#: feature; detail below it only costs: a 100,000-point circle of 1.9 mm meshed into 0.0 deg
#: slivers and hung in Gmsh (its boundary setup grows with the square of a loop's vertices).
DETAIL_MM = 1.0e-4
#: Most vertices one polygon (outline, region, printed piece) may keep after DETAIL_MM:
#: Gmsh needs ~10 s to set up a boundary loop of 50,000 vertices (quadratic beyond).
MAX_POLYGON_VERTICES = 50_000
#: Most support points one pattern may hold ([[support]] points, all tables): each becomes a
#: held mesh vertex; 200,000 points took 100 s to mesh and say nothing a few hundred do not.
MAX_SUPPORT_POINTS = 10_000
#: A support's stated position lies within this many fabric diagonals (its bounding box) of the
#: held point's relaxed position (x/sx, y/sy, 0), and two held points are at most this many
#: times their printed distance apart: a post 9 m above a 40 mm strip ran past 2 min (a rigid
#: move the solver carries step by step), two posts 1 m apart tore it to non-finite numbers.
SUPPORT_REACH = 3.0
#: Most stars one [stars] table may place: each printed star needs at least ~10 triangles of
#: the MAX_TRIANGLES mesh budget; 1.15 million stars (a 1 m sheet at 1 mm spacing) took minutes
#: and 2.5 GB before any budget was checked.
MAX_STARS = 200_000
#: Smallest fabric "width" 2 area / perimeter (mm) (a disk's radius, ~ a strip's width).
MIN_FABRIC_WIDTH_MM = 0.5
#: Cap of the estimated triangle count of a mesh (geometry.meshing.estimate_triangles):
#: about 8 GB of Gmsh and solver memory; 40k-vertex sheets already take minutes to solve.
MAX_TRIANGLES = 2_000_000
#: Deepest nesting of a field expression (geometry.expressions): deeper trees are refused
#: with one line before any recursive walk.
MAX_EXPRESSION_DEPTH = 100


@dataclass(frozen=True)
class Num:
    """A number (or, with ``integer``, an integer) in [lo, hi] (open ends with lo_open /
    hi_open), its unit, and the reason for the range (docs and tests read it)."""
    lo: float | None = None
    hi: float | None = None
    unit: str = ""
    reason: str = ""
    lo_open: bool = False
    hi_open: bool = False
    integer: bool = False

    def describe(self) -> str:
        """The range as text, e.g. "[0.1, 2] mm" or "(0, 1e+04] MPa"."""
        fmt = (lambda v: f"{int(v)}") if self.integer else (lambda v: f"{v:g}")
        lo = "-inf" if self.lo is None else fmt(self.lo)
        hi = "inf" if self.hi is None else fmt(self.hi)
        br = ("(" if self.lo_open or self.lo is None else "[") + f"{lo}, {hi}" + (
            ")" if self.hi_open or self.hi is None else "]")
        return br + (f" {self.unit}" if self.unit not in ("", "1") else "")

    def check(self, value, name: str):
        """``value`` as float (int for integer keys) inside the range, else a one-line
        SelfshapeError naming ``name`` (bools and strings are never numbers)."""
        return number(value, name, self)


def is_number(value) -> bool:
    """True for real numbers that are not bools (Python or numpy)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and type(value).__name__ != "bool_"


def number(value, name: str, spec: Num):
    """Strictly checked number: see :class:`Num`. The message says what was given and the range."""
    if not is_number(value):
        what = "true/false" if isinstance(value, bool) or type(value).__name__ == "bool_" else (
            f"the string {value!r:.40}" if isinstance(value, str) else type(value).__name__)
        kind = "an integer" if spec.integer else "a number"
        raise SelfshapeError(f"{name} must be {kind} in {spec.describe()}, got {what}")
    if spec.integer:
        if not isinstance(value, numbers.Integral):
            raise SelfshapeError(f"{name} must be an integer in {spec.describe()}, got {value!r:.40}")
        v = int(value)
        lo_bad = spec.lo is not None and (v <= spec.lo if spec.lo_open else v < spec.lo)
        hi_bad = spec.hi is not None and (v >= spec.hi if spec.hi_open else v > spec.hi)
        if lo_bad or hi_bad:
            shown = f"{v}" if abs(v) < 10 ** 15 else f"{v:.3e}"
            raise SelfshapeError(f"{name} must be an integer in {spec.describe()}, got {shown}")
        return v
    try:
        v = float(value)
    except OverflowError:                     # an integer beyond the float range
        raise SelfshapeError(f"{name} must be in {spec.describe()}, got an integer of {len(str(value))} digits") \
            from None
    if not math.isfinite(v):
        raise SelfshapeError(f"{name} must be a finite number in {spec.describe()}, got {v}")
    lo_bad = spec.lo is not None and (v <= spec.lo if spec.lo_open else v < spec.lo)
    hi_bad = spec.hi is not None and (v >= spec.hi if spec.hi_open else v > spec.hi)
    if lo_bad or hi_bad:       # the reasons explain the upper ends (lower ones are mostly "positive")
        raise SelfshapeError(f"{name} must be in {spec.describe()}, got {v:.6g}"
                             + (f" ({spec.reason})" if spec.reason and hi_bad else ""))
    return v


def check_keys(table: dict, allowed, where: str) -> None:
    """One-line SelfshapeError for the first key of ``table`` not in ``allowed``, with the
    closest allowed key when one is close ("did you mean ...?", difflib) else the list."""
    allowed = sorted(allowed)
    for k in table:
        if k in allowed:
            continue
        close = difflib.get_close_matches(str(k), allowed, n=1, cutoff=0.6)
        hint = f"did you mean {close[0]!r}?" if close else f"allowed: {', '.join(allowed)}"
        raise SelfshapeError(f"{where}: unknown key {str(k)!r:.60} ({hint})")


# ---------------------------------------------------------------- the pattern

_LEN = "mm"
COORD = Num(-COORD_MAX_MM, COORD_MAX_MM, _LEN, "10 m: beyond any printer bed or fabric")
THICKNESS_PLASTIC = Num(0.01, 10.0, _LEN, "printed plastic: one 0.01 mm layer to a 10 mm slab")
WIDTH = Num(MIN_FEATURE_MM, 500.0, _LEN, "a bead is at least 0.1 mm wide; wider than 0.5 m is a region")

#: table -> key -> Num for every numeric key of a pattern (points, lists and strings are
#: checked by the reader; ``stretch`` applies to the number and to each of [sx, sy]).
PATTERN_NUMBERS: dict[str, dict[str, Num]] = {
    "fabric": {
        "disk": Num(MIN_FABRIC_WIDTH_MM, 5000.0, _LEN, "radius: a fabric at least 1 mm across, at most 10 m"),
        "hexagon": Num(MIN_FABRIC_WIDTH_MM, 5000.0, _LEN, "side: a fabric at least 1 mm across, at most 10 m"),
        "stretch": Num(1.0, 3.0, "", "knitted fabric breaks before a 3x pre-stretch; the seed uses 1.1-1.6"),
        "thickness_mm": Num(0.01, 10.0, _LEN, "a fabric is 0.01-10 mm thick"),
        "young_modulus_mpa": Num(1e-3, 1e4, "MPa", "textiles: 0.01-1000 MPa"),
        "poisson": Num(-0.99, 0.499, "", "an isotropic solid, short of incompressible"),
        "bending_stiffness_nmm": Num(0.0, 1e3, "N mm", "spandex is 0.02 N mm; 1000 is a steel sheet"),
        "course_angle_deg": Num(-360.0, 360.0, "deg", "an angle"),
        "areal_weight_n_per_mm2": Num(0.0, 1e-4, "N/mm^2", "1e-4 N/mm^2 = 10 kg/m^2, 30x a heavy canvas"),
    },
    "plastic": {
        "young_modulus_mpa": Num(0.1, 1e5, "MPa", "soft TPU (10 MPa) to carbon-filled filaments (< 100 GPa)"),
        "poisson": Num(-0.99, 0.5, "", "an isotropic solid, incompressible at most"),
        "rest_curvature_per_mm": Num(-10.0, 10.0, "1/mm", "a set radius below 0.1 mm is not a plastic set"),
    },
    "region": {"thickness_mm": THICKNESS_PLASTIC},
    "ribbon": {"width_mm": WIDTH, "thickness_mm": THICKNESS_PLASTIC},
    "stars": {
        "spacing_mm": Num(1.0, 1000.0, _LEN, "a lattice of 1 mm to 1 m"),
        "arm_length": Num(0.0, 1.0, "", "fraction of spacing_mm; 0 omits the star, 1 reaches the next centre"),
        "thickness_mm": THICKNESS_PLASTIC,
        "arm_width_mm": WIDTH,
        "angle_deg": Num(-360.0, 360.0, "deg", "an angle"),
    },
    "mesh": {
        "size_mm": Num(0.01, 1000.0, _LEN, "and at most 2 million triangles (estimated before meshing)"),
        "across": Num(0.5, 10.0, "", "triangle rows across the narrowest printed feature"),
    },
    "solver": {
        "seed": Num(0, 2 ** 32 - 1, "", "a numpy seed", integer=True),
        "max_iterations": Num(1, 100_000, "", "Newton iterations per mesh level", integer=True),
        "metric_floor": Num(0.0, 1e6, "", "multiples of the median Hessian diagonal"),
        "coarse_levels": Num(0, 20, "", "or \"auto\"", integer=True),
        "release_steps": Num(1, 100, "", "continuation steps of the release", integer=True),
    },
    "ground": {
        "height_mm": Num(-COORD_MAX_MM, COORD_MAX_MM, _LEN, "the plane z = height under the sheet's mid-surface"),
    },
    "contact": {
        "exclusion_mm": Num(0.0, COORD_MAX_MM, _LEN, "printed distance within which parts never touch; "
                            "raised to the mesh's minimum (0: the minimum)"),
    },
}
#: [solver] keys that are choices, not numbers: key -> allowed values (first = default).
#: model: "shell" (printed areas as bilayer shell regions) or "rods" (the seed's chapter-3
#: model: rods on the centre lines of [stars] arms and [[ribbon]] paths, shellfem.rods).
SOLVER_CHOICES: dict[str, tuple] = {"model": ("shell", "rods")}
#: Arm length of a star that is printed (fraction > 0): at least this, mm.
MIN_ARM_MM = MIN_FEATURE_MM

#: Numbers of `selfshape design` that are not pattern keys (inverse.design.DesignOptions
#: field -> Num), checked by design() before it runs, by the CLI's options and by design
#: sweeps (validation.sweep) before any case runs. The diagonal scales the target before
#: anything else runs, so its range is checked first: a 1e300 mm target overflowed to "zero
#: total area", 1e5 mm flattened for minutes before the bed check. The lengths below had no
#: range before sweeps could set them: a NaN gap or edge reached the layout unchecked.
DESIGN_NUMBERS: dict[str, Num] = {
    "diagonal_mm": Num(10.0, 5000.0, _LEN, "no 15 mm ribbon fits a smaller target; a larger one flattens to more "
                       "than the largest (2 m) printer bed"),
    # the designed pattern's [fabric] stretch, and a pre-stretch (> 1: the seed's contraction)
    "stretch": Num(1.0, PATTERN_NUMBERS["fabric"]["stretch"].hi, "", PATTERN_NUMBERS["fabric"]["stretch"].reason,
                   lo_open=True),
    "lam": Num(None, 0.0, "1/mm^2", "the seed's line-field lambda is <= 0"),
    "edge_mm": Num(0.0, COORD_MAX_MM, _LEN, "the target's mean edge after refinement: a length on a target of at "
                   "most 10 m", lo_open=True),
    "gap_mm": Num(0.0, COORD_MAX_MM, _LEN, "a distance between ribbons on a target of at most 10 m"),
    "layout_edge_mm": Num(0.0, COORD_MAX_MM, _LEN, "the layout mesh's mean edge: a length on a target of at most "
                          "10 m", lo_open=True),
    # the rest are Python-only (and sweep) options: -1 reached numpy's generator after the
    # flattening (a raw ValueError, exit 3), 0 faces or iterations ran to nonsense
    "seed": PATTERN_NUMBERS["solver"]["seed"],
    "max_faces": Num(1, MAX_TRIANGLES, "", "the refined target's face cap: at most the mesh budget", integer=True),
    "flatten_max_iter": Num(1, 100_000, "", "flattening iterations on the fine mesh", integer=True),
    "ribbon_length": Num(1.0, 1000.0, _LEN, "a printed dash of 1 mm to 1 m"),
    "ribbon_width": WIDTH,
    "proxy_smooth_mm": Num(0.0, COORD_MAX_MM, _LEN, "the proxy surface's shortest wavelength: a length on a target "
                           "of at most 10 m", lo_open=True),
    "stretch_candidates": Num(1, 10, "", "designs verified per surface with --stretch auto (1: the stretch "
                              "choice's score alone; the shipped laws are at 5 stretches)", integer=True),
}
#: The flattening's stretch bounds (s1min, s1max, s2min, s2max) of a design: each in this range
#: and each minimum at most its maximum (DesignOptions.bounds; None: the contraction model's).
DESIGN_BOUND = Num(0.0, 10.0, "", "a principal stretch of the flattening", lo_open=True)
#: The flattening's stop rules (DesignOptions.stop).
DESIGN_STOPS = ("mean", "norm")


# ---------------------------------------------------------------- the printer

#: Printer field -> Num (pairs: each component). Ranges of desktop and large-format FDM printers.
PRINTER_NUMBERS: dict[str, Num] = {
    "bed_size": Num(10.0, 2000.0, _LEN, "each side: a 10 mm to 2 m bed"),
    "nozzle_mm": Num(0.1, 2.0, _LEN, "FDM nozzles are 0.1-2 mm"),
    "filament_diameter_mm": Num(1.0, 3.5, _LEN, "filament is 1.75, 2.85 or 3 mm"),
    "layer_height_mm": Num(0.02, 2.0, _LEN, "and at most the nozzle diameter (the bead model needs h <= w)"),
    "print_speed_mm_s": Num(1.0, 500.0, "mm/s", "FDM extrusion speeds"),
    "travel_speed_mm_s": Num(1.0, 1000.0, "mm/s", "FDM travel speeds"),
    "z_speed_mm_s": Num(0.5, 100.0, "mm/s", "lead-screw z axes"),
    "retraction_mm": Num(0.0, 20.0, _LEN, "Bowden retractions are at most ~10 mm"),
    "retraction_speed_mm_s": Num(1.0, 200.0, "mm/s", "extruder speeds"),
    "retract_min_travel_mm": Num(0.0, 1000.0, _LEN, "a travel length on the bed"),
    "z_hop_mm": Num(0.0, 20.0, _LEN, "a lift over the print"),
    "extrusion_multiplier": Num(0.5, 2.0, "", "a flow correction, not a different bead"),
    "nozzle_temperature_c": Num(150.0, 350.0, "deg C", "no filament flows below 150 C; 350 C is the hotend limit"),
    "bed_temperature_c": Num(0.0, 150.0, "deg C", "0 = off (fabric); 150 C is the heater limit"),
    "bed_offset_z_mm": Num(0.0, 100.0, _LEN, "the frame's height above the bed"),
    "origin": Num(-2000.0, 2000.0, _LEN, "each coordinate: on or near a bed of at most 2 m"),
    "mirror_axis_x": Num(0.0, 2000.0, _LEN, "a line on the bed: 0 <= a <= bed_size[0]"),
}

#: Physical caps on the parameters of the registered fabric membrane models
#: ([fabric.<model>] tables), by unit, on top of each model's own bounds: no textile is
#: stiffer than 1e4 MPa in-plane, and a dimensionless parameter (a Green strain, a
#: Poisson's ratio) beyond 10 is no fabric.
MODEL_UNIT_CAPS: dict[str, Num] = {
    "MPa": Num(0.0, 1e4, "MPa", "no textile is stiffer than 1e4 MPa in-plane"),
    "1": Num(-10.0, 10.0, "", "a Green strain or ratio beyond 10 is no fabric"),
}


def model_parameter_spec(parameter) -> Num:
    """The range of a membrane-model Parameter: its own bounds intersected with the unit's cap."""
    cap = MODEL_UNIT_CAPS.get(parameter.unit, Num(-1e6, 1e6, parameter.unit, "a bounded model parameter"))
    lo, hi, lo_open = parameter.lo, parameter.hi, parameter.lo_open
    capped = False
    if lo is None or lo < cap.lo:
        lo, lo_open, capped = cap.lo, cap.lo_open, True
    if hi is None or hi > cap.hi:
        hi, capped = cap.hi, True
    return Num(lo, hi, parameter.unit, cap.reason if capped else "the model's own bounds", lo_open=lo_open)


def ranges_markdown() -> str:
    """The "Ranges" tables of docs/pattern-format.md, generated from this module (a test
    checks that the document holds exactly this text)."""
    from shellfem.materials import MEMBRANE_MODELS

    rows = ["| table | key | range | why |", "|---|---|---|---|"]
    for table, keys in PATTERN_NUMBERS.items():
        for key, spec in keys.items():
            rows.append(f"| `[{table}]` | `{key}` | {spec.describe()} | {spec.reason} |")
    for name, model in MEMBRANE_MODELS.items():
        for p in model.parameters:
            spec = model_parameter_spec(p)
            rows.append(f"| `[fabric.{name}]` | `{p.name}` | {spec.describe()} | {spec.reason} |")
    rows += ["", "| printer field | range | why |", "|---|---|---|"]
    for key, spec in PRINTER_NUMBERS.items():
        rows.append(f"| `{key}` | {spec.describe()} | {spec.reason} |")
    return "\n".join(rows) + "\n"
