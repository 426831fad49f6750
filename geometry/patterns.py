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

Every numeric key is checked strictly (no bools, no strings) against its physical range in
geometry.schema, unknown keys are errors suggesting the closest valid one, and a pattern read
from a file may only name [print] files inside its folder and must print something.
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
from geometry.schema import (MAX_SUPPORT_POINTS, MIN_FABRIC_WIDTH_MM, MIN_FEATURE_MM, PATTERN_NUMBERS, SOLVER_CHOICES,
                             SUPPORT_REACH, check_keys, model_parameter_spec, number)
from geometry.stars import star_elements
from geometry.tomlfile import read_toml
from shellfem.errors import SelfshapeError
from shellfem.infiles import check_input_file
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
    "contact": {"enabled", "exclusion_mm"},
    "ground": {"enabled", "height_mm"},
}
#: (key, Fabric attribute, lower bound, bound exclusive) of the numeric [fabric] entries; the
#: reader checks them against the (tighter) physical ranges of geometry.schema.PATTERN_NUMBERS
FABRIC_FIELDS = (("thickness_mm", "thickness", 0.0, True), ("young_modulus_mpa", "young_modulus", 0.0, True),
                 ("poisson", "poisson", None, False), ("bending_stiffness_nmm", "bending_stiffness", 0.0, False),
                 ("course_angle_deg", "course_angle_deg", None, False),
                 ("areal_weight_n_per_mm2", "areal_weight", 0.0, False))
#: (key, Plastic attribute) of the [plastic] entries
PLASTIC_FIELDS = (("young_modulus_mpa", "young_modulus"), ("poisson", "poisson"),
                  ("rest_curvature_per_mm", "rest_curvature"))
#: [solver] keys: the numeric ones of the schema and the model choice
SOLVER_KEYS = set(PATTERN_NUMBERS["solver"]) | set(SOLVER_CHOICES) | {"metric_predictor"}
SOLVER_MODELS = SOLVER_CHOICES["model"]
TOP_LEVEL = {"fabric", "plastic", "region", "ribbon", "stars", "support", "mesh", "solver", "print", "meta", "contact",
             "ground"}


def fabric_keys() -> set:
    """The keys [fabric] allows: shape, record fields, one table per registered membrane model."""
    return {*SHAPES, "holes", *FABRIC_RECORD_KEYS, *MEMBRANE_MODELS}


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
    coarse_levels, "auto" or an integer >= 0, 0 = none; see shellfem.multilevel). release_steps:
    continuation steps over which the release ramps the pre-stretch, the plastic's set and the
    supports' motion ([solver] release_steps, default 1). solver_model:
    [solver] model, "shell" (default: printed areas as bilayer shell regions) or "rods" (the
    seed's chapter-3 model: rods on the centre lines of stars and ribbons on a bare fabric,
    shellfem.rods). source: file path or "<dict>". raw: the parsed TOML
    (unknown [solver] and [meta] keys are kept here for the solver).
    metric_predictor: solve with the printed layers' truncated metric first ([solver]
    metric_predictor, default true; forward.simulate.simulate_sheet). contact_exclusion: the
    printed distance (mm) within which parts of the sheet are never in contact ([contact]
    exclusion_mm; None: the mesh's own, shellfem.contact.Contact).
    contact: self-contact on ([contact] enabled, default true; shellfem.contact). ground: the
    height (mm) of the ground plane under the sheet ([ground] height_mm, default 0), or None
    without a ground ([ground] enabled; default: on when a support stands the sheet on the
    table, :func:`on_the_table`).
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
    release_steps: int = 1
    solver_model: str = "shell"
    contact: bool = True
    ground: float | None = None
    metric_predictor: bool = True
    contact_exclusion: float | None = None
    source: str = "<dict>"
    raw: dict = field(default_factory=dict)


# ---------------------------------------------------------------- small validators

def _num(table: dict, key: str, where: str, default=None, section: str | None = None, spec=None):
    """table[key] strictly checked against its schema range (geometry.schema.PATTERN_NUMBERS
    [section][key], ``section`` parsed from ``where`` when not given; or ``spec``): a finite
    number, never a bool or a string. ``default`` when absent (None: the key is required)."""
    if key not in table:
        if default is None:
            raise SelfshapeError(f"{where}: missing {key}")
        return default
    if spec is None:
        spec = PATTERN_NUMBERS[section or _section(where)][key]
    return number(table[key], f"{where}: {key}", spec)


def _section(where: str) -> str:
    """The table name in a message prefix such as "file.toml: [[ribbon]] #2" -> "ribbon"."""
    inner = where.rsplit("[", 1)[-1]
    return inner.split("]", 1)[0].split(" ")[0].split(".")[0]


def solver_options(solver: dict, where: str) -> tuple[int, int, float | None]:
    """(seed, max_iterations, metric_floor) of a [solver] table, defaults 0, 300 and None (the
    solver's own default); a one-line SelfshapeError naming ``where`` for a bad value. Unknown
    keys are left to the caller."""
    seed = _num(solver, "seed", where, 0, "solver")
    cap = _num(solver, "max_iterations", where, 300, "solver")
    floor = _num(solver, "metric_floor", where, section="solver") if "metric_floor" in solver else None
    return seed, cap, floor


def coarse_levels_option(solver: dict, where: str) -> int | str:
    """[solver] coarse_levels: "auto" (default) or an integer >= 0 (one-line SelfshapeError otherwise)."""
    v = solver.get("coarse_levels", "auto")
    if v == "auto":
        return v
    if isinstance(v, str):
        raise SelfshapeError(f"{where}: coarse_levels must be \"auto\" or an integer >= 0, got {v!r:.40}")
    return _num(solver, "coarse_levels", where, section="solver")


def _flag(table: dict, key: str, where: str, default: bool) -> bool:
    """table[key] as true/false (default when absent); anything else is a one-line error."""
    v = table.get(key, default)
    if not isinstance(v, bool):
        raise SelfshapeError(f"{where}: {key} must be true or false, got {v!r:.40}")
    return v


def on_the_table(supports, gravity: bool) -> bool:
    """True when a support stands the sheet on the table, so that a ground is on by default: a
    ``fix = "z"`` support (on the plane z = 0, free to slide), or, under gravity, an "xyz"
    support at its relaxed position (z = 0: pinned to the table). "xyz" supports at a stated
    ``position`` are posts or a frame in the air (a jig, a rim held above the table): they do
    not put a table under the sheet, with or without gravity; ``[ground] enabled = true`` does."""
    return any(s.fix == "z" or (gravity and s.fix == "xyz" and s.position is None) for s in supports)


def contact_options(raw: dict, src: str, fabric, supports) -> tuple[bool, float | None, float | None]:
    """([contact] enabled, ground height or None, [contact] exclusion_mm or None) of a pattern:
    see :class:`Pattern`. The ground's default is :func:`on_the_table` (issue 20: on wherever a
    support holds the sheet on the ground, or gravity pulls it onto the table it is pinned to).
    exclusion_mm (mm) is None when absent: the mesh's own (shellfem.contact.Contact raises a
    value below the mesh's minimum to it)."""
    c = _table(raw.get("contact", {}), f"{src}: [contact]", KEYS["contact"])
    contact = _flag(c, "enabled", f"{src}: [contact]", True)
    exclusion = _num(c, "exclusion_mm", f"{src}: [contact]", section="contact") if "exclusion_mm" in c else None
    where = f"{src}: [ground]"
    g = _table(raw.get("ground", {}), where, KEYS["ground"])
    gravity = fabric.areal_weight > 0
    on = _flag(g, "enabled", where, on_the_table(supports, gravity))
    height = _num(g, "height_mm", where, 0.0, "ground")
    if on and g.get("enabled") is True and not supports:
        raise SelfshapeError(f"{src}: [ground] enabled = true needs a [[support]] that holds the sheet on it: "
                             f"without one nothing holds the sheet against the ground and the "
                             f"solve cannot converge (the rigid-motion gauge carries its push)")
    if on:
        for s in supports:
            if s.position is not None and np.any(s.position[:, 2] < height):
                k = int(np.argmin(s.position[:, 2]))
                raise SelfshapeError(f"{src}: [[support]] #{s.label.split('#')[-1]} position {k + 1} is at "
                                     f"z = {s.position[k, 2]:.4g} mm, below the [ground] at height_mm = {height:g}: "
                                     f"a post cannot hold the sheet under the ground")
    return contact, (height if on else None), exclusion


def check_rods_contact(raw: dict, src: str) -> None:
    """[solver] model = "rods" has no contact (shellfem.rods: the seed's chapter-3 model): a
    [contact] or [ground] that turns one on is a one-line error, not ignored."""
    c, g = raw.get("contact", {}), raw.get("ground", {})
    if isinstance(c, dict) and c.get("enabled", False) is True:
        raise SelfshapeError(f"{src}: [contact] enabled = true with [solver] model = \"rods\": the rods model has "
                             f"no contact; set enabled = false or use model = \"shell\"")
    if isinstance(g, dict) and g and g.get("enabled", True) is not False:
        raise SelfshapeError(f"{src}: [ground] with [solver] model = \"rods\": the rods model has no ground; "
                             f"remove [ground] (or set enabled = false) or use model = \"shell\"")


def _choice(table: dict, key: str, where: str, options: tuple, default: str):
    v = table.get(key, default)
    if v not in options:
        raise SelfshapeError(f"{where}: {key} must be one of {', '.join(repr(o) for o in options)}, got {v!r:.60}")
    return v


def _table(value, where: str, allowed: set | None) -> dict:
    if not isinstance(value, dict):
        raise SelfshapeError(f"{where} must be a table, got {type(value).__name__}")
    if allowed is not None:
        check_keys(value, allowed, where)
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
            raise SelfshapeError(f"{where}: rectangle width and height must be > 0, got {t['rectangle']!r:.60}")
        outline = outlines.rectangle(*wh)
    elif kind == "disk":
        outline = outlines.disk(_num(t, "disk", where), mesh_size)
    elif kind == "hexagon":
        outline = outlines.hexagon(_num(t, "hexagon", where))
    else:
        outline = outlines.polygon(t["outline"], f"{where} outline")
    if "holes" in t:
        outline = outlines.with_holes(outline, t["holes"], f"{where} holes")
    width = 2.0 * outline.area / outline.length
    if width < MIN_FABRIC_WIDTH_MM:
        raise SelfshapeError(f"{where}: {kind}: the fabric is {width:.3g} mm wide (2 area / perimeter); "
                             f"at least {MIN_FABRIC_WIDTH_MM:g} mm is needed")

    s = t.get("stretch", 1.35)
    if isinstance(s, list):
        if len(s) != 2:
            raise SelfshapeError(f"{where}: stretch must be a number or [sx, sy], got {s!r:.60}")
        s = tuple(_num({"stretch": v}, "stretch", where, section="fabric") for v in s)
    else:
        s = _num(t, "stretch", where, 1.35, "fabric")
    params = {}
    for name, membrane in MEMBRANE_MODELS.items():      # bounds: the model's schema, via Fabric
        if name in t:
            o = _table(t[name], f"{where} {name}", {p.name for p in membrane.parameters})
            specs = {p.name: model_parameter_spec(p) for p in membrane.parameters}
            params[name] = {k: _num(o, k, f"{where} {name}", spec=specs[k]) for k in o}
    kw = dict(stretch=s, model=t.get("model", "neo-hookean"), parameters=params)
    if "model" in t and not isinstance(t["model"], str):
        raise SelfshapeError(f"{where}: model must be a string, one of {', '.join(sorted(MEMBRANE_MODELS))}")
    for key, attr, _, _ in FABRIC_FIELDS:
        if key in t:
            kw[attr] = _num(t, key, where, section="fabric")
    return _rewrap(src, Fabric, **kw), outline


def _plastic(raw: dict, src: str) -> Plastic:
    where = f"{src}: [plastic]"
    t = _table(raw.get("plastic", {}), where, KEYS["plastic"])
    kw = {}
    for key, attr in PLASTIC_FIELDS:
        if key in t:
            kw[attr] = _num(t, key, where, section="plastic")
    return _rewrap(src, Plastic, **kw)


def _regions(raw, src, outline) -> list[PrintedElement]:
    out = []
    for i, where, t in _entries(raw, "region", src, "polygon"):
        poly = outlines.polygon(t["polygon"], where)
        h = _num(t, "thickness_mm", where, section="region")
        side = _choice(t, "side", where, ("front", "back"), "front")
        width = 2.0 * poly.area / poly.length
        if width < MIN_FEATURE_MM:
            raise SelfshapeError(f"{where}: polygon is a {width:.3g} mm sliver (2 area / perimeter); the narrowest "
                                 f"printable feature is {MIN_FEATURE_MM:g} mm")
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
        w = _num(t, "width_mm", where, 1.5, "ribbon")
        h = _num(t, "thickness_mm", where, 0.4, "ribbon")
        side = _choice(t, "side", where, ("front", "back"), "front")
        ends = _choice(t, "ends", where, ("square", "round"), "square")
        geom = ribbon_polygon(path, w, ends)
        if not geom.is_valid:
            geom = shapely.make_valid(geom)
        clipped = geom.intersection(outline)
        clipped = _polygonal(clipped)
        if clipped.is_empty or clipped.area <= 1e-12 * geom.area:
            raise SelfshapeError(f"{where}: ribbon lies entirely outside the fabric")
        out.append(PrintedElement(clipped, h, side, "ribbon", f"ribbon #{i}", centrelines=[path], width_mm=w))
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
    spacing = _num(t, "spacing_mm", where, section="stars")
    fields = {}
    for k, d in (("arm_length", 0.7), ("thickness_mm", 0.3), ("arm_width_mm", 0.8)):
        f = compile_field(t.get(k, d), f"{where} {k}")
        fields[k] = number(f, f"{where}: {k}", PATTERN_NUMBERS["stars"][k]) if isinstance(f, float) else f
    side = _choice(t, "side", where, ("front", "back"), "front")
    origin = outlines.as_points([t["origin"]], f"{where} origin")[0] if "origin" in t else None
    angle = _num(t, "angle_deg", where, 0.0, "stars")
    return star_elements(outline, spacing, fields["arm_length"], fields["thickness_mm"], fields["arm_width_mm"],
                         side, origin=origin, angle_deg=angle, where=where)


def _read_gcode(path: str, where: str, **options) -> list[PrintedElement]:
    try:
        from geometry.gcode import read_gcode
    except ImportError as e:
        raise SelfshapeError(f"{where}: G-code import is not available ({e})") from None
    check_input_file(path, "G-code file", f"{where}: G-code file {path!r:.200}")   # a folder, pipe or device too
    return list(read_gcode(path, **options))


def gcode_path(name: str, base_dir: str, where: str, confine: bool) -> str:
    """The file a [print] gcode entry names: relative to ``base_dir`` (the pattern file's
    folder). With ``confine`` (a pattern read from a file) the resolved path (symlinks
    followed) must stay inside that folder: a pattern file is data that may come from
    anyone, and must not make selfshape read /etc/passwd or ../../secrets. A file elsewhere
    is given on the command line instead (``selfshape simulate path/to/print.gcode``)."""
    if "\x00" in name:
        raise SelfshapeError(f"{where}: gcode file name contains a NUL character")
    path = name if os.path.isabs(name) else os.path.join(base_dir, name)
    if confine:
        root = os.path.realpath(base_dir)
        real = os.path.realpath(path)
        if os.path.commonpath([root, real]) != root:
            raise SelfshapeError(f"{where}: gcode {name!r:.80} is outside the pattern's folder; [print] files must be "
                                 f"in the pattern file's folder or below it (give another file on the command line)")
    return path


def _print(raw, src, outline, base_dir, confine=False) -> list[PrintedElement]:
    """[print] gcode = "file" or ["front.gcode", "back.gcode"]; optional side and origin_mm
    (bed position of pattern (0, 0)) are passed to geometry.gcode.read_gcode. Files resolve
    by :func:`gcode_path`; a file none of whose print lies on the fabric is an error (it
    would otherwise be dropped silently)."""
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
        path = gcode_path(f, base_dir, f"{where} gcode", confine)
        n0, bounds = len(out), None
        try:
            read = _read_gcode(path, f"{where} gcode {f}", **options)
        except SelfshapeError as err:          # "print.gcode: line 3: ...": say which pattern asked for it
            msg = str(err)
            raise SelfshapeError(msg if msg.startswith(where) else f"{where} gcode {msg}") from None
        for e in read:
            g = _polygonal(e.geometry.intersection(outline))
            b = e.geometry.bounds
            bounds = b if bounds is None else (min(bounds[0], b[0]), min(bounds[1], b[1]),
                                               max(bounds[2], b[2]), max(bounds[3], b[3]))
            if not g.is_empty and g.area > 0:
                out.append(PrintedElement(g, e.thickness_mm, e.side, e.kind or "gcode", e.label or f))
        if len(out) == n0:
            fx0, fy0, fx1, fy1 = outline.bounds
            raise SelfshapeError(
                f"{where} {f}: the print lies entirely outside the fabric (print x {bounds[0]:.4g}..{bounds[2]:.4g}, "
                f"y {bounds[1]:.4g}..{bounds[3]:.4g} mm; fabric x {fx0:.4g}..{fx1:.4g}, y {fy0:.4g}..{fy1:.4g} mm); "
                f"set [print] origin_mm to the bed position of pattern (0, 0)")
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
                raise SelfshapeError(f"{where}: boundary = true holds the whole outer edge; drop points/position")
            out.append(Support(points=np.zeros((0, 2)), fix=fix, label=f"support #{i + 1}", boundary=True))
            continue
        if "points" not in t:
            raise SelfshapeError(f"{where}: missing points (or boundary = true)")
        pts = outlines.as_points(t["points"], f"{where} points", 1)
        inside = shapely.contains_xy(grown, pts[:, 0], pts[:, 1])
        if not inside.all():
            k = int(np.argmin(inside))
            how = "in a hole of" if outline.interiors and shapely.contains_xy(Polygon(outline.exterior), *pts[k]) \
                else "outside"
            raise SelfshapeError(f"{where}: point {k + 1} ({pts[k, 0]:.4g}, {pts[k, 1]:.4g}) is {how} the fabric")
        pos = None
        if "position" in t:
            if fix != "xyz":
                raise SelfshapeError(f"{where}: position is only meaningful with fix = \"xyz\"")
            pos = outlines.as_points(t["position"], f"{where} position", 1, dim=3)
            if len(pos) != len(pts):
                raise SelfshapeError(f"{where}: position has {len(pos)} entries but points has {len(pts)}")
        out.append(Support(points=pts, fix=fix, position=pos, label=f"support #{i + 1}"))
        total = sum(len(s.points) for s in out)
        if total > MAX_SUPPORT_POINTS:
            raise SelfshapeError(f"{where}: points bring the supports to {total:,} points, more than the "
                                 f"{MAX_SUPPORT_POINTS:,} a pattern may hold (each is a held mesh vertex; use "
                                 f"boundary = true to hold the whole outline)")
    return out


def check_support_positions(supports, fabric, outline, src: str) -> None:
    """The stated positions of "xyz" supports within reach of the fabric (geometry.schema.
    SUPPORT_REACH): each within SUPPORT_REACH fabric diagonals of its point's relaxed position
    (x/sx, y/sy, 0), and any two held points at most SUPPORT_REACH times their printed
    distance apart (the fabric is printed pre-stretched and breaks before 3x); one-line
    SelfshapeError naming the support and the point otherwise."""
    held = [(s, k) for s in supports if s.position is not None for k in range(len(s.points))]
    if not held:
        return
    b = outline.bounds
    diag = math.hypot(b[2] - b[0], b[3] - b[1])
    sx, sy = fabric.stretch
    p = np.array([s.points[k] for s, k in held], float)
    P = np.array([s.position[k] for s, k in held], float)
    relaxed = np.column_stack([p[:, 0] / sx, p[:, 1] / sy, np.zeros(len(p))])
    off = np.linalg.norm(P - relaxed, axis=1)
    if off.max() > SUPPORT_REACH * diag:
        j = int(np.argmax(off))
        s, k = held[j]
        raise SelfshapeError(f"{src}: [[support]] #{s.label.split('#')[-1]} position {k + 1} is {off[j]:.4g} mm "
                             f"from its point's relaxed position, more than {SUPPORT_REACH:g} x the fabric's "
                             f"{diag:.4g} mm diagonal: a support holds the sheet where it deploys (move the whole "
                             f"frame instead)")
    for i0 in range(0, len(p), 1024):
        dp = np.linalg.norm(p[i0:i0 + 1024, None] - p[None], axis=2)
        dP = np.linalg.norm(P[i0:i0 + 1024, None] - P[None], axis=2)
        bad = dP > SUPPORT_REACH * dp + 1e-9 * diag
        if bad.any():
            a, c = np.argwhere(bad)[0]
            (s1, k1), (s2, k2) = held[i0 + a], held[c]
            raise SelfshapeError(f"{src}: [[support]] positions {s1.label.split('#')[-1]}.{k1 + 1} and "
                                 f"{s2.label.split('#')[-1]}.{k2 + 1} are {dP[a, c]:.4g} mm apart, more than "
                                 f"{SUPPORT_REACH:g} x their {dp[a, c]:.4g} mm on the printed fabric: the fabric "
                                 f"cannot stretch that far")


# ---------------------------------------------------------------- entry points

def parse_pattern(raw: dict, src: str = "<dict>", base_dir: str = ".", from_file: bool = False) -> Pattern:
    """Validate a parsed pattern dict; ``src`` names it in messages, ``base_dir`` resolves [print] files.

    ``from_file``: the dict is a pattern file's content (load_pattern of a path): its [print]
    files must then lie inside ``base_dir`` (:func:`gcode_path`), and a pattern that prints
    nothing is an error (:func:`check_printed`). Python callers passing a dict are trusted."""
    if not isinstance(raw, dict):
        raise SelfshapeError(f"{src}: a pattern must be a table, got {type(raw).__name__}")
    check_keys(raw, TOP_LEVEL, src)
    mesh = _table(raw.get("mesh", {}), f"{src}: [mesh]", KEYS["mesh"])
    mesh_size = _num(mesh, "size_mm", f"{src}: [mesh]", 1.0, "mesh")
    across = _num(mesh, "across", f"{src}: [mesh]", 2.0, "mesh")
    solver = _table(raw.get("solver", {}), f"{src}: [solver]", SOLVER_KEYS)
    seed, cap, floor = solver_options(solver, f"{src}: [solver]")
    levels = coarse_levels_option(solver, f"{src}: [solver]")
    release_steps = _num(solver, "release_steps", f"{src}: [solver]", 1, "solver")
    model = _choice(solver, "model", f"{src}: [solver]", SOLVER_MODELS, "shell")
    predictor = _flag(solver, "metric_predictor", f"{src}: [solver]", True)
    _table(raw.get("meta", {}), f"{src}: [meta]", None)
    fabric, outline = _fabric(raw, src, mesh_size)
    plastic = _plastic(raw, src)
    elements = (_regions(raw, src, outline) + _ribbons(raw, src, outline) + _stars(raw, src, outline)
                + _print(raw, src, outline, base_dir, confine=from_file))
    supports = _supports(raw, src, outline)
    check_support_positions(supports, fabric, outline, src)
    if model == "rods":
        check_rods_model(elements, src)
    contact, ground, exclusion = contact_options(raw, src, fabric, supports)
    if model == "rods":              # no contact in the rods model: say so, and record it
        check_rods_contact(raw, src)
        contact, ground = False, None
    if from_file:
        check_printed(elements, fabric, src)
    return Pattern(fabric=fabric, plastic=plastic, outline=outline, elements=elements, supports=supports,
                   mesh_size=mesh_size, seed=seed, mesh_across=across, max_iterations=cap,
                   metric_floor=floor, coarse_levels=levels, release_steps=release_steps, solver_model=model,
                   contact=contact, ground=ground, metric_predictor=predictor,
                   contact_exclusion=exclusion,
                   source=src,
                   raw=raw)


def check_rods_model(elements, src: str) -> None:
    """[solver] model = "rods" puts rods on centre lines: [stars] arms and [[ribbon]] paths;
    a [[region]] or [print] has none (one-line SelfshapeError naming the file and key)."""
    for el in elements:
        if not el.centrelines:
            raise SelfshapeError(f"{src}: [solver] model = \"rods\" supports [stars] and [[ribbon]] patterns only; "
                                 f"{el.label or el.kind} ({el.kind}) has no centre line (use model = \"shell\")")


def check_printed(elements, fabric, src: str) -> None:
    """A pattern file must print something: a bare sheet released from its pre-stretch only
    shrinks, flat, to (x / sx, y / sy), so simulating it is a mistake (a forgotten
    [[ribbon]], a misspelt table). The explicit opt-in is gravity: with
    ``[fabric] areal_weight_n_per_mm2 > 0`` (and a [[support]]) a bare sheet drapes, which is
    a simulation."""
    if not elements and not fabric.areal_weight > 0:
        raise SelfshapeError(f"{src}: nothing is printed (no [[region]], [[ribbon]], [stars] or [print]); a bare "
                             f"sheet only shrinks flat (set [fabric] areal_weight_n_per_mm2 > 0 to simulate a "
                             f"draping sheet)")


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
    return parse_pattern(raw, src, os.path.dirname(os.path.abspath(src)), from_file=True)


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
