"""Pattern files (TOML, see INTERFACE.md and the README): read into a validated Pattern, and written.

``load_pattern(source)`` takes a path to a .toml pattern (or a .gcode print, see below)
or an already-parsed dict. Every problem raises SelfshapeError with one line naming the
file, the entry (1-based, e.g. ``[[region]] #3``) and the problem. Printed geometry is
resolved here: [[region]] polygons must lie inside the fabric; [[ribbon]], [stars] and
[print] G-code elements are clipped to it. All lengths are printed-state mm.

A bare ``.gcode`` file is a pattern too: its printed paths (geometry.gcode) on a
rectangle of fabric = the print's bounding box plus a 10 mm margin on every side, with
the default fabric and plastic (seed Table 4.1) and the default mesh size.

This module owns the format both ways: :func:`fabric_table` and :func:`plastic_table` are
the inverses of the [fabric] and [plastic] parse (every field), :func:`write_pattern`
writes a pattern dict as TOML. [fabric.<model>] tables are those of the membrane models
registered in shellfem.materials, validated against each model's parameter schema.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np
import shapely
import tomli_w
from shapely.geometry import LineString, Polygon

from geometry import outlines
from geometry.elements import PrintedElement, Support
from geometry.expressions import compile_field
from geometry.stars import star_elements
from shellfem.errors import SelfshapeError, check_number
from geometry.tomlfile import read_toml
from shellfem.materials import MEMBRANE_MODELS, Fabric, Plastic

GCODE_MARGIN_MM = 10.0

SHAPES = ("rectangle", "outline", "disk", "hexagon")
#: [fabric] keys besides the shape and the [fabric.<model>] tables of the registered models
FABRIC_RECORD_KEYS = ("stretch", "thickness_mm", "model", "young_modulus_mpa", "poisson", "bending_stiffness_nmm",
                      "course_angle_deg", "areal_weight_n_per_mm2")
KEYS = {
    "plastic": {"young_modulus_mpa", "poisson", "rest_curvature_per_mm"},
    "region": {"polygon", "thickness_mm", "side"},
    "ribbon": {"path", "width_mm", "thickness_mm", "side", "ends"},
    "stars": {"spacing_mm", "arm_length", "thickness_mm", "arm_width_mm", "side", "origin", "angle_deg"},
    "support": {"points", "fix", "position", "boundary"},
    "mesh": {"size_mm", "across"},
    "print": {"gcode", "side", "origin_mm"},
}
#: (key, Fabric attribute, lower bound, bound exclusive) of the numeric [fabric] entries
FABRIC_FIELDS = (("thickness_mm", "thickness", 0.0, True), ("young_modulus_mpa", "young_modulus", 0.0, True),
                 ("poisson", "poisson", None, False), ("bending_stiffness_nmm", "bending_stiffness", 0.0, False),
                 ("course_angle_deg", "course_angle_deg", None, False),
                 ("areal_weight_n_per_mm2", "areal_weight", 0.0, False))
#: (key, Plastic attribute) of the [plastic] entries
PLASTIC_FIELDS = (("young_modulus_mpa", "young_modulus"), ("poisson", "poisson"),
                  ("rest_curvature_per_mm", "rest_curvature"))
TOP_LEVEL = {"fabric", "plastic", "region", "ribbon", "stars", "support", "mesh", "solver", "print", "meta"}


def fabric_keys() -> set:
    """The keys [fabric] allows: shape, record fields, one table per registered membrane model."""
    return {*SHAPES, *FABRIC_RECORD_KEYS, *MEMBRANE_MODELS}


@dataclass
class Pattern:
    """A validated pattern, printed-state mm.

    outline: the fabric (shapely Polygon). elements: printed geometry, already clipped to
    the outline, in file order ([[region]], [[ribbon]], [stars], [print]). supports:
    boundary conditions. mesh_size: target edge length in bare fabric, mm. mesh_across:
    triangle rows across the narrowest printed feature ([mesh] across, default 2). seed: the
    solver's symmetry-breaking seed. max_iterations: the Newton cap ([solver] max_iterations,
    default 300). metric_floor: the solver's trust-region metric floor ([solver] metric_floor;
    None when absent, meaning the solver's default, shellfem.newton.lm_metric). coarse_levels: coarser meshes solved first ([solver]
    coarse_levels, "auto" or an integer >= 0, 0 = none; see shellfem.multilevel). source: file path or "<dict>". raw: the parsed TOML
    (unknown [solver] and [meta] keys are kept here for the solver).
    """
    fabric: Fabric
    plastic: Plastic
    outline: Polygon
    elements: list = field(default_factory=list)
    supports: list = field(default_factory=list)
    mesh_size: float = 1.0
    seed: int = 0
    mesh_across: float = 2.0
    max_iterations: int = 300
    metric_floor: float | None = None
    coarse_levels: int | str = "auto"
    source: str = "<dict>"
    raw: dict = field(default_factory=dict)


# ---------------------------------------------------------------- small validators

def _num(table: dict, key: str, where: str, default=None, lo=None, lo_open=False, hi=None):
    """table[key] as a finite float (bools and strings rejected), with optional bounds."""
    if key not in table:
        if default is None:
            raise SelfshapeError(f"{where}: missing {key}")
        return default
    v = table[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SelfshapeError(f"{where}: {key} must be a number, got {v!r:.60}")
    return check_number(f"{where}: {key}", v, lo=lo, hi=hi, lo_open=lo_open)


def solver_options(solver: dict, where: str) -> tuple[int, int, float | None]:
    """(seed, max_iterations, metric_floor) of a [solver] table, defaults 0, 300 and None (the
    solver's own default); a one-line SelfshapeError naming ``where`` for a bad value. Unknown
    keys are left to the caller."""
    seed = solver.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise SelfshapeError(f"{where}: seed must be an integer, got {seed!r:.40}")
    cap = solver.get("max_iterations", 300)
    if isinstance(cap, bool) or not isinstance(cap, int) or cap < 1:
        raise SelfshapeError(f"{where}: max_iterations must be a positive integer, got {cap!r:.40}")
    floor = _num(solver, "metric_floor", where, lo=0.0) if "metric_floor" in solver else None
    return seed, cap, floor


def coarse_levels_option(solver: dict, where: str) -> int | str:
    """[solver] coarse_levels: "auto" (default) or an integer >= 0 (one-line SelfshapeError otherwise)."""
    v = solver.get("coarse_levels", "auto")
    if v == "auto":
        return v
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise SelfshapeError(f"{where}: coarse_levels must be \"auto\" or an integer >= 0, got {v!r:.40}")
    return v


def _choice(table: dict, key: str, where: str, options: tuple, default: str):
    v = table.get(key, default)
    if v not in options:
        raise SelfshapeError(f"{where}: {key} must be one of {', '.join(repr(o) for o in options)}, got {v!r:.60}")
    return v


def _table(value, where: str, allowed: set | None) -> dict:
    if not isinstance(value, dict):
        raise SelfshapeError(f"{where} must be a table, got {type(value).__name__}")
    if allowed is not None:
        unknown = [k for k in value if k not in allowed]
        if unknown:
            raise SelfshapeError(f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(allowed))})")
    return value


def _array_of_tables(raw: dict, name: str, src: str) -> list:
    v = raw.get(name, [])
    if isinstance(v, dict):
        v = [v]
    if not isinstance(v, list):
        raise SelfshapeError(f"{src}: [[{name}]] must be an array of tables")
    return [_table(t, f"{src}: [[{name}]] #{i + 1}", KEYS[name]) for i, t in enumerate(v)]


def _entries(raw: dict, name: str, src: str, required: str):
    """(1-based index, where, table) of each [[name]] entry, each holding ``required``."""
    for i, t in enumerate(_array_of_tables(raw, name, src)):
        where = f"{src}: [[{name}]] #{i + 1}"
        if required not in t:
            raise SelfshapeError(f"{where}: missing {required}")
        yield i + 1, where, t


def _rewrap(where: str, fn, *args, **kw):
    """Call a record constructor, prefixing its SelfshapeError with the file."""
    try:
        return fn(*args, **kw)
    except SelfshapeError as e:
        raise SelfshapeError(f"{where}: {e}") from None


# ---------------------------------------------------------------- sections

def _fabric(raw: dict, src: str, mesh_size: float):
    where = f"{src}: [fabric]"
    t = _table(raw.get("fabric"), where, fabric_keys()) if "fabric" in raw else None
    if t is None:
        raise SelfshapeError(f"{src}: missing [fabric] table")
    shapes = [k for k in SHAPES if k in t]
    if len(shapes) != 1:
        raise SelfshapeError(f"{where}: give exactly one of {', '.join(SHAPES)} (got {', '.join(shapes) or 'none'})")
    kind = shapes[0]
    if kind == "rectangle":
        wh = outlines.as_points([t["rectangle"]], f"{where} rectangle", 1)[0]
        if not (wh > 0).all():
            raise SelfshapeError(f"{where}: rectangle width and height must be > 0, got {t['rectangle']!r}")
        outline = outlines.rectangle(*wh)
    elif kind == "disk":
        outline = outlines.disk(_num(t, "disk", where, lo=0.0, lo_open=True), mesh_size)
    elif kind == "hexagon":
        outline = outlines.hexagon(_num(t, "hexagon", where, lo=0.0, lo_open=True))
    else:
        outline = outlines.polygon(t["outline"], f"{where} outline")

    s = t.get("stretch", 1.35)
    if isinstance(s, list):
        if len(s) != 2:
            raise SelfshapeError(f"{where}: stretch must be a number or [sx, sy], got {s!r:.60}")
        s = tuple(_num({"stretch": v}, "stretch", where, lo=1.0) for v in s)
    else:
        s = _num(t, "stretch", where, 1.35, lo=1.0)
    params = {}
    for name, membrane in MEMBRANE_MODELS.items():      # bounds: the model's schema, via Fabric
        if name in t:
            o = _table(t[name], f"{where} {name}", {p.name for p in membrane.parameters})
            params[name] = {k: _num(o, k, f"{where} {name}") for k in o}
    kw = dict(stretch=s, model=t.get("model", "neo-hookean"), parameters=params)
    for key, attr, lo, lo_open in FABRIC_FIELDS:
        if key in t:
            kw[attr] = _num(t, key, where, lo=lo, lo_open=lo_open)
    return _rewrap(src, Fabric, **kw), outline


def _plastic(raw: dict, src: str) -> Plastic:
    where = f"{src}: [plastic]"
    t = _table(raw.get("plastic", {}), where, KEYS["plastic"])
    kw = {}
    for key, attr in PLASTIC_FIELDS:
        if key in t:
            kw[attr] = _num(t, key, where)
    return _rewrap(src, Plastic, **kw)


def _regions(raw, src, outline) -> list[PrintedElement]:
    out = []
    for i, where, t in _entries(raw, "region", src, "polygon"):
        poly = outlines.polygon(t["polygon"], where)
        h = _num(t, "thickness_mm", where, lo=0.0, lo_open=True)
        side = _choice(t, "side", where, ("front", "back"), "front")
        outlines.check_inside(outline, poly, where)
        out.append(PrintedElement(poly, h, side, "region", f"region #{i}"))
    return out


def ribbon_polygon(path: np.ndarray, width: float, ends: str = "square", segment_mm: float | None = None):
    """The printed area of a path of given width (mm): mitred joins (bevelled beyond 2 w),
    square ends (cut at the path's end points) or round ends (half discs).

    Round ends use arcs of about ``segment_mm`` chords (default width / 2), so the
    geometry does not force a finer mesh than the bead needs.
    """
    seg = width / 2.0 if segment_mm is None else segment_mm
    quad = max(1, int(math.ceil(0.25 * math.pi * width / 2.0 / seg)))
    return LineString(path).buffer(width / 2.0, quad_segs=quad, cap_style="round" if ends == "round" else "flat",
                                   join_style="mitre", mitre_limit=2.0)


def _ribbons(raw, src, outline) -> list[PrintedElement]:
    out = []
    for i, where, t in _entries(raw, "ribbon", src, "path"):
        path = outlines.as_points(t["path"], f"{where} path", 2)
        keep = np.ones(len(path), bool)
        keep[1:] = np.any(path[1:] != path[:-1], axis=1)
        path = path[keep]
        if len(path) < 2:
            raise SelfshapeError(f"{where}: path needs at least 2 distinct points")
        w = _num(t, "width_mm", where, 1.5, lo=0.0, lo_open=True)
        h = _num(t, "thickness_mm", where, 0.4, lo=0.0, lo_open=True)
        side = _choice(t, "side", where, ("front", "back"), "front")
        ends = _choice(t, "ends", where, ("square", "round"), "square")
        geom = ribbon_polygon(path, w, ends)
        if not geom.is_valid:
            geom = shapely.make_valid(geom)
        clipped = geom.intersection(outline)
        clipped = _polygonal(clipped)
        if clipped.is_empty or clipped.area <= 1e-12 * geom.area:
            raise SelfshapeError(f"{where}: ribbon lies entirely outside the fabric")
        out.append(PrintedElement(clipped, h, side, "ribbon", f"ribbon #{i}"))
    return out


def _polygonal(geom):
    """Keep only the areal part of a clipping result (drop touching lines and points)."""
    if geom.geom_type in ("Polygon", "MultiPolygon") or geom.is_empty:
        return geom
    polys = [g for g in shapely.get_parts(geom) if g.geom_type in ("Polygon", "MultiPolygon")]
    return shapely.union_all(polys) if polys else Polygon()


def _stars(raw, src, outline) -> list[PrintedElement]:
    if "stars" not in raw:
        return []
    where = f"{src}: [stars]"
    t = _table(raw["stars"], where, KEYS["stars"])
    spacing = _num(t, "spacing_mm", where, lo=0.0, lo_open=True)
    fields = {k: compile_field(t.get(k, d), f"{where} {k}")
              for k, d in (("arm_length", 0.7), ("thickness_mm", 0.3), ("arm_width_mm", 0.8))}
    side = _choice(t, "side", where, ("front", "back"), "front")
    origin = outlines.as_points([t["origin"]], f"{where} origin")[0] if "origin" in t else None
    angle = _num(t, "angle_deg", where, 0.0)
    return star_elements(outline, spacing, fields["arm_length"], fields["thickness_mm"], fields["arm_width_mm"],
                         side, origin=origin, angle_deg=angle, where=where)


def _read_gcode(path: str, where: str, **options) -> list[PrintedElement]:
    try:
        from geometry.gcode import read_gcode
    except ImportError as e:
        raise SelfshapeError(f"{where}: G-code import is not available ({e})") from None
    if not os.path.isfile(path):
        raise SelfshapeError(f"{where}: G-code file {path!r} not found")
    return list(read_gcode(path, **options))


def _print(raw, src, outline, base_dir) -> list[PrintedElement]:
    """[print] gcode = "file" or ["front.gcode", "back.gcode"]; optional side and origin_mm
    (bed position of pattern (0, 0)) are passed to geometry.gcode.read_gcode."""
    if "print" not in raw:
        return []
    where = f"{src}: [print]"
    t = _table(raw["print"], where, KEYS["print"])
    files = t.get("gcode", [])
    files = [files] if isinstance(files, str) else files
    if not isinstance(files, list) or not files or not all(isinstance(f, str) for f in files):
        raise SelfshapeError(f"{where}: gcode must be a file name or a list of file names")
    options = {}
    if "side" in t:
        options["side"] = _choice(t, "side", where, ("front", "back"), "front")
    if "origin_mm" in t:
        options["origin_mm"] = tuple(outlines.as_points([t["origin_mm"]], f"{where} origin_mm")[0])
    out = []
    for f in files:
        path = f if os.path.isabs(f) else os.path.join(base_dir, f)
        for e in _read_gcode(path, f"{where} {f}", **options):
            g = _polygonal(e.geometry.intersection(outline))
            if not g.is_empty and g.area > 0:
                out.append(PrintedElement(g, e.thickness_mm, e.side, e.kind or "gcode", e.label or f))
    return out


def _supports(raw, src, outline) -> list[Support]:
    out = []
    tol = 1e-9 * max(1.0, math.sqrt(outline.area))
    grown = outline.buffer(tol)
    for i, t in enumerate(_array_of_tables(raw, "support", src)):
        where = f"{src}: [[support]] #{i + 1}"
        boundary = t.get("boundary", False)
        if not isinstance(boundary, bool):
            raise SelfshapeError(f"{where}: boundary must be true or false, got {boundary!r:.40}")
        fix = _choice(t, "fix", where, ("z", "xyz"), "z")
        if boundary:
            if "points" in t or "position" in t:
                raise SelfshapeError(f"{where}: boundary = true holds the whole outline; drop points/position")
            out.append(Support(points=np.zeros((0, 2)), fix=fix, label=f"support #{i + 1}", boundary=True))
            continue
        if "points" not in t:
            raise SelfshapeError(f"{where}: missing points (or boundary = true)")
        pts = outlines.as_points(t["points"], f"{where} points", 1)
        inside = shapely.contains_xy(grown, pts[:, 0], pts[:, 1])
        if not inside.all():
            k = int(np.argmin(inside))
            raise SelfshapeError(f"{where}: point {k + 1} ({pts[k, 0]:.4g}, {pts[k, 1]:.4g}) is outside the fabric")
        pos = None
        if "position" in t:
            if fix != "xyz":
                raise SelfshapeError(f"{where}: position is only meaningful with fix = \"xyz\"")
            pos = outlines.as_points(t["position"], f"{where} position", 1, dim=3)
            if len(pos) != len(pts):
                raise SelfshapeError(f"{where}: position has {len(pos)} entries but points has {len(pts)}")
        out.append(Support(points=pts, fix=fix, position=pos, label=f"support #{i + 1}"))
    return out


# ---------------------------------------------------------------- entry points

def parse_pattern(raw: dict, src: str = "<dict>", base_dir: str = ".") -> Pattern:
    """Validate a parsed pattern dict; ``src`` names it in messages, ``base_dir`` resolves [print] files."""
    if not isinstance(raw, dict):
        raise SelfshapeError(f"{src}: a pattern must be a table, got {type(raw).__name__}")
    unknown = [k for k in raw if k not in TOP_LEVEL]
    if unknown:
        raise SelfshapeError(f"{src}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(TOP_LEVEL))})")
    mesh = _table(raw.get("mesh", {}), f"{src}: [mesh]", KEYS["mesh"])
    mesh_size = _num(mesh, "size_mm", f"{src}: [mesh]", 1.0, lo=0.0, lo_open=True)
    across = _num(mesh, "across", f"{src}: [mesh]", 2.0, lo=0.5, hi=10.0)
    solver = _table(raw.get("solver", {}), f"{src}: [solver]", None)
    seed, cap, floor = solver_options(solver, f"{src}: [solver]")
    levels = coarse_levels_option(solver, f"{src}: [solver]")
    _table(raw.get("meta", {}), f"{src}: [meta]", None)
    fabric, outline = _fabric(raw, src, mesh_size)
    plastic = _plastic(raw, src)
    elements = (_regions(raw, src, outline) + _ribbons(raw, src, outline) + _stars(raw, src, outline)
                + _print(raw, src, outline, base_dir))
    supports = _supports(raw, src, outline)
    return Pattern(fabric=fabric, plastic=plastic, outline=outline, elements=elements, supports=supports,
                   mesh_size=mesh_size, seed=seed, mesh_across=across, max_iterations=cap,
                   metric_floor=floor, coarse_levels=levels, source=src,
                   raw=raw)


def pattern_from_gcode(path: str) -> Pattern:
    """A bare G-code print on a rectangle = its bounding box + 10 mm margin, default materials."""
    src = str(path)
    elements = _read_gcode(src, src)
    if not elements:
        raise SelfshapeError(f"{src}: no printed paths found")
    xmin, ymin, xmax, ymax = shapely.union_all([e.geometry for e in elements]).bounds
    m = GCODE_MARGIN_MM
    outline = Polygon([(xmin - m, ymin - m), (xmax + m, ymin - m), (xmax + m, ymax + m), (xmin - m, ymax + m)])
    raw = {"fabric": {"outline": [list(map(float, p)) for p in outline.exterior.coords[:-1]]},
           "print": {"gcode": os.path.abspath(src)}}
    return Pattern(fabric=Fabric(), plastic=Plastic(), outline=outline, elements=elements, supports=[],
                   source=src, raw=raw)


def load_pattern(source) -> Pattern:
    """Load a pattern from a .toml path, a .gcode path or a parsed dict (see module doc)."""
    if isinstance(source, dict):
        return parse_pattern(source)
    src = os.fspath(source)
    if src.lower().endswith((".gcode", ".gco", ".g")):
        return pattern_from_gcode(src)
    raw = read_toml(src)
    return parse_pattern(raw, src, os.path.dirname(os.path.abspath(src)))


# ---------------------------------------------------------------- writing

def fabric_table(fabric: Fabric) -> dict:
    """The [fabric] entries of a Fabric record, every field (the inverse of the parse; the
    outline's shape key is the caller's): stretch (a number when sx = sy), model, the numeric
    fields and the [fabric.<model>] table of the model in use, plus any other model's table
    whose parameters differ from its defaults."""
    sx, sy = fabric.stretch
    t = {"stretch": float(sx) if sx == sy else [float(sx), float(sy)], "model": fabric.model}
    for key, attr, _, _ in FABRIC_FIELDS:
        t[key] = float(getattr(fabric, attr))
    for name, params in fabric.parameters.items():
        if params and (name == fabric.model or params != MEMBRANE_MODELS[name].defaults()):
            t[name] = {k: float(v) for k, v in params.items()}
    return t


def plastic_table(plastic: Plastic) -> dict:
    """The [plastic] entries of a Plastic record, every field (the inverse of the parse)."""
    return {key: float(getattr(plastic, attr)) for key, attr in PLASTIC_FIELDS}


def _plain(v):
    """TOML-ready values: numpy scalars and arrays, tuples -> Python numbers and lists."""
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_plain(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    return v


def write_pattern(path, raw: dict) -> None:
    """Write a pattern dict (as :func:`parse_pattern` reads it) to ``path`` as TOML."""
    with open(path, "wb") as f:
        tomli_w.dump(_plain(raw), f)
