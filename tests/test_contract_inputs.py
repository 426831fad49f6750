"""The contract under bad input (issue 19), generated from the schema.

Every numeric key of a pattern (geometry.schema.PATTERN_NUMBERS and the parameters of every
registered membrane model) and every printer field (geometry.schema.PRINTER_NUMBERS, checked
against dataclasses.fields(Printer)) is set, by hypothesis, to values outside its range, to
non-finite numbers, to booleans and to strings; every table gets misspelt keys. Each case runs
the real verb (`selfshape mesh`, `selfshape design --printer`) in-process and must exit 2 with
exactly one stderr line naming the file and the key, print nothing on stdout and leave no
output. A key added to the schema is covered here without editing this file. Then the parser
limits (nesting, expressions, int64 faces), the resource bounds (triangle budget, a retraced
G-code) and the file rules ([print] paths, content never echoed, prints off the fabric, bare
sheets, flat targets).

Parse-level only: no simulation runs here (about 30 s in all).
"""
from __future__ import annotations

import contextlib
import dataclasses
import difflib
import io
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np
import pytest
import tomli_w
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from geometry import patterns
from geometry.schema import MAX_TRIANGLES, PATTERN_NUMBERS, PRINTER_NUMBERS, model_parameter_spec, ranges_markdown
from inverse.printer import Printer
from selfshape.cli import main
from shellfem.materials import MEMBRANE_MODELS

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
GCODE = os.path.join(ROOT, "tests", "data", "patterns", "two_lines.gcode")
TARGET = os.path.join(ROOT, "meshes", "targets", "saddle.obj")
#: [stars] keys that are fields: a string there is an expression, checked at every star
STAR_FIELDS = ("arm_length", "thickness_mm", "arm_width_mm")
SETTINGS = settings(max_examples=8, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def base_pattern() -> dict:
    """A valid pattern that uses every table (the [print] file sits beside the pattern)."""
    return {
        "fabric": {"rectangle": [40.0, 30.0], "stretch": 1.35, "thickness_mm": 0.8, "young_modulus_mpa": 1.05,
                   "poisson": 0.3, "bending_stiffness_nmm": 0.0192, "course_angle_deg": 0.0,
                   "areal_weight_n_per_mm2": 0.0},
        "plastic": {"young_modulus_mpa": 72.3, "poisson": 0.5, "rest_curvature_per_mm": 0.0},
        "region": [{"polygon": [[2.0, 2.0], [8.0, 2.0], [8.0, 8.0], [2.0, 8.0]], "thickness_mm": 0.4}],
        "ribbon": [{"path": [[2.0, 25.0], [38.0, 25.0]], "width_mm": 1.5, "thickness_mm": 0.4}],
        "stars": {"spacing_mm": 12.0, "arm_length": 0.5, "thickness_mm": 0.3, "arm_width_mm": 0.8, "angle_deg": 0.0},
        "print": {"gcode": "two_lines.gcode"},
        "support": [{"points": [[20.0, 15.0]], "fix": "z"}],
        "mesh": {"size_mm": 3.0, "across": 2.0},
        "solver": {"seed": 0, "max_iterations": 300, "metric_floor": 10.0, "coarse_levels": "auto"},
        "meta": {"note": "tests/test_contract_inputs.py"},
    }


def run(argv) -> tuple[int, str, str]:
    """The selfshape CLI in-process: (exit status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main(argv)
        except SystemExit as e:            # argparse
            rc = e.code
    return rc, out.getvalue(), err.getvalue()


@contextlib.contextmanager
def folder():
    """A fresh folder holding the [print] file of base_pattern()."""
    d = tempfile.mkdtemp(prefix="contract-")
    try:
        shutil.copy(GCODE, os.path.join(d, "two_lines.gcode"))
        yield d
    finally:
        shutil.rmtree(d, ignore_errors=True)


def mesh_error(raw: dict, d: str, name: str = "pattern.toml") -> str:
    """Write ``raw`` to d/name, run `selfshape mesh`; assert the contract; return the line."""
    path = os.path.join(d, name)
    with open(path, "wb") as f:
        tomli_w.dump(raw, f)
    out = os.path.join(d, "out.msh")
    rc, stdout, stderr = run(["mesh", path, "-o", out])
    assert rc == 2, (rc, stderr)
    lines = stderr.splitlines()
    assert len(lines) == 1 and stdout == "", stderr
    assert name in lines[0], lines[0]
    assert not os.path.exists(out) and not [f for f in os.listdir(d) if "partial" in f]
    return lines[0]


def test_base_pattern_is_valid():
    """The mutations below break a pattern that is otherwise fine (and meshes)."""
    with folder() as d:
        path = os.path.join(d, "pattern.toml")
        with open(path, "wb") as f:
            tomli_w.dump(base_pattern(), f)
        rc, stdout, stderr = run(["mesh", path, "-o", os.path.join(d, "out.msh")])
        assert rc == 0 and stderr == "" and os.path.isfile(os.path.join(d, "out.msh")), stderr
        assert {e.kind for e in patterns.load_pattern(path).elements} == {"region", "ribbon", "star", "gcode"}


# ---------------------------------------------------------------- values out of range, from the schema

def bad_values(spec, as_string_ok: bool = True):
    """Values a key with range ``spec`` must refuse: beyond each end, non-finite, booleans,
    strings (numbers in quotes), and for integer keys floats; TOML-representable."""
    out = [st.sampled_from([True, False, math.nan, math.inf, -math.inf])]
    if spec.integer:
        if spec.lo is not None:
            out.append(st.integers(min_value=-2 ** 63, max_value=int(spec.lo) - 1))
        if spec.hi is not None:
            out.append(st.integers(min_value=int(spec.hi) + 1, max_value=2 ** 63 - 1))
        out.append(st.floats(allow_nan=False, allow_infinity=False).filter(lambda v: v != int(v)))
    else:
        if spec.lo is not None:
            out.append(st.floats(max_value=spec.lo, exclude_max=not spec.lo_open, allow_nan=False,
                                 allow_infinity=False))
        if spec.hi is not None:
            out.append(st.floats(min_value=spec.hi, exclude_min=not spec.hi_open, allow_nan=False,
                                 allow_infinity=False))
    if as_string_ok:
        mid = spec.lo if spec.lo is not None else 0
        out.append(st.sampled_from([str(mid), "0.8", "", "x"]))
    return st.one_of(out)


def pattern_keys():
    """(table, key, spec) of every numeric pattern key: the schema's tables and every
    membrane model's parameters."""
    rows = [(t, k, s) for t, keys in PATTERN_NUMBERS.items() for k, s in keys.items()]
    rows += [(f"fabric.{name}", p.name, model_parameter_spec(p))
             for name, m in MEMBRANE_MODELS.items() for p in m.parameters]
    return rows


def set_key(raw: dict, table: str, key: str, value) -> None:
    if table.startswith("fabric."):
        raw["fabric"][table[7:]] = {key: value}
    elif table in ("region", "ribbon"):
        raw[table][0][key] = value
    elif table == "fabric" and key in patterns.SHAPES:
        raw["fabric"].pop("rectangle")
        raw["fabric"][key] = value
    else:
        raw.setdefault(table, {})[key] = value


def test_every_key_of_the_readers_is_in_the_schema():
    """The schema covers what the reader accepts: no numeric key escapes the generated tests."""
    numeric = {k for t, keys in PATTERN_NUMBERS.items() for k in keys}
    for table in ("region", "ribbon", "stars", "mesh", "plastic"):
        for key in patterns.KEYS[table]:
            if key not in ("polygon", "path", "side", "ends", "origin"):
                assert key in PATTERN_NUMBERS[table], (table, key)
    for key in patterns.FABRIC_RECORD_KEYS:
        assert key in PATTERN_NUMBERS["fabric"] or key == "model", key
    assert {"disk", "hexagon"} <= numeric
    assert set(PRINTER_NUMBERS) | {"relative_e"} == {f.name for f in dataclasses.fields(Printer)}


@pytest.mark.parametrize("table,key,spec", pattern_keys(), ids=lambda v: v if isinstance(v, str) else "")
@SETTINGS
@given(data=st.data())
def test_pattern_value_out_of_range_is_one_line_naming_file_and_key(table, key, spec, data):
    field = table == "stars" and key in STAR_FIELDS
    value = data.draw(bad_values(spec, as_string_ok=not field), label="value")
    if field and data.draw(st.booleans(), label="as expression"):
        if isinstance(value, bool) or not math.isfinite(value) or abs(value) > 1e300:
            value = 1e9
        value = f"{value!r} + 0 * x"          # an expression: out of range at every star
    raw = base_pattern()
    if key == "stretch" and data.draw(st.booleans(), label="pair"):
        value = [1.2, value]
    set_key(raw, table, key, value)
    with folder() as d:
        line = mesh_error(raw, d)
    assert key in line, line


PRINTER_VALID = {"bed_size": [223.0, 223.0], "origin": [10.0, 10.0]}


@pytest.mark.parametrize("key,spec", list(PRINTER_NUMBERS.items()), ids=list(PRINTER_NUMBERS))
@SETTINGS
@given(data=st.data())
def test_printer_value_out_of_range_is_one_line_naming_file_and_key(key, spec, data):
    value = data.draw(bad_values(spec), label="value")
    if key in PRINTER_VALID:                  # a pair: one bad component
        value = [PRINTER_VALID[key][0], value]
    with folder() as d:
        p = os.path.join(d, "printer.toml")
        with open(p, "wb") as f:
            tomli_w.dump({"printer": {key: value}}, f)
        out = os.path.join(d, "design")
        rc, stdout, stderr = run(["design", TARGET, "-o", out, "--printer", p])
        assert rc == 2 and stdout == "" and len(stderr.splitlines()) == 1, (rc, stderr)
        assert "printer.toml" in stderr and key in stderr, stderr
        assert not os.path.exists(out)


@pytest.mark.parametrize("text, word", [
    ("nozzle_mm = true", "nozzle_mm must be a number in [0.1, 2] mm, got true/false"),
    ('nozzle_mm = "0.8"', "nozzle_mm must be a number in [0.1, 2] mm, got the string '0.8'"),
    ("filament_diameter_mm = 1e-300", "filament_diameter_mm must be in [1, 3.5] mm"),
    ("print_speed_mm_s = 1e300", "print_speed_mm_s must be in [1, 500] mm/s"),
    ("nozzle_mm = 0.4\nlayer_height_mm = 0.6", "layer_height_mm (0.6) must not exceed the nozzle diameter"),
    ("mirror_axis_x = 300", "mirror_axis_x (300) must lie on the bed"),
    ("relative_e = 1", "relative_e must be true or false"),
    ("nozle_mm = 0.4", "unknown key 'nozle_mm' (did you mean 'nozzle_mm'?)"),
])
def test_printer_cases_of_the_issue(tmp_path, text, word):
    p = tmp_path / "printer.toml"
    p.write_text("[printer]\n" + text + "\n")
    rc, _, stderr = run(["design", TARGET, "-o", str(tmp_path / "out"), "--printer", str(p)])
    assert rc == 2 and word in stderr and len(stderr.splitlines()) == 1, stderr
    assert not (tmp_path / "out").exists()


def test_keys_beside_printer_table_are_errors(tmp_path):
    p = tmp_path / "printer.toml"
    p.write_text("nozzle_mm = 0.4\n[printer]\nprint_speed_mm_s = 20\n")
    rc, _, stderr = run(["design", TARGET, "-o", str(tmp_path / "out"), "--printer", str(p)])
    assert rc == 2 and "unknown key 'nozzle_mm'" in stderr and "printer.toml" in stderr, stderr


@SETTINGS
@given(fields=st.fixed_dictionaries({}, optional={
    k: st.floats(s.lo, s.hi if k != "layer_height_mm" else 0.1) for k, s in PRINTER_NUMBERS.items()
    if k not in ("bed_size", "origin", "mirror_axis_x", "nozzle_mm")}))
def test_any_printer_in_range_writes_finite_bounded_gcode(fields):
    """Inside the ranges the G-code is sane: every number finite, feed rates at most 1000 mm/s."""
    from geometry.elements import Ribbon
    from inverse.gcode import write_gcode
    printer = Printer(**fields)
    rib = [Ribbon(path=np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 5.0]]), width_mm=1.0, thickness_mm=0.4)]
    with tempfile.TemporaryDirectory() as d:
        write_gcode(rib, os.path.join(d, "f.gcode"), printer)
        text = open(os.path.join(d, "f.gcode")).read()
    assert not re.search(r"inf|nan", text, re.IGNORECASE)
    feeds = [float(v) for v in re.findall(r"^G[01] .*F([0-9.]+)", text, re.MULTILINE)]
    words = [float(v) for v in re.findall(r"(?<=[XYZEFS])(-?[0-9.]+)", text)]
    assert feeds and max(feeds) <= 60 * 1000 and all(math.isfinite(v) and len(repr(v)) < 20 for v in words)


def other_keys():
    """(table, key) of every non-numeric key the reader accepts (choices, points, files, flags):
    patterns.KEYS and the [fabric] shape and model keys, minus the schema's numeric ones."""
    rows = [("fabric", k) for k in ("rectangle", "outline", "model")]
    rows += [(t, k) for t, keys in patterns.KEYS.items() for k in sorted(keys)
             if k not in PATTERN_NUMBERS.get(t, {})]
    return rows


#: values of the wrong kind for any non-numeric key: none is a valid choice, point list or file
WRONG_KIND = st.sampled_from([True, {"a": 1}, "zz-not-valid", 12345, [[True, 1.0]], [["x", "y"]], -7.5,
                              [[1.0, 2.0, 3.0, 4.0]], [[1e300, 1e300], [2e300, 1e300], [1e300, 3e300]]])


@pytest.mark.parametrize("table,key", other_keys(), ids=lambda v: v)
@SETTINGS
@given(value=WRONG_KIND)
def test_other_keys_of_the_wrong_kind_name_the_key(table, key, value):
    assume(not (key in ("boundary", "enabled") and value is True))      # the one valid value among them
    raw = base_pattern()
    if table == "support":
        raw["support"][0].update({"fix": "xyz"} if key == "position" else {})
        if key == "boundary":
            raw["support"][0].pop("points")
    set_key(raw, table, key, value) if table not in ("support", "print") else \
        (raw["support"][0].__setitem__(key, value) if table == "support" else raw["print"].__setitem__(key, value))
    with folder() as d:
        line = mesh_error(raw, d)
    assert key in line, line


# ---------------------------------------------------------------- unknown keys, from the schema

def tables_and_keys():
    """(table, allowed keys) of every checked table of a pattern."""
    rows = [("", patterns.TOP_LEVEL), ("fabric", patterns.fabric_keys()), ("solver", patterns.SOLVER_KEYS)]
    rows += [(t, keys) for t, keys in patterns.KEYS.items()]
    rows += [(f"fabric.{n}", {p.name for p in m.parameters}) for n, m in MEMBRANE_MODELS.items() if m.parameters]
    return rows


@pytest.mark.parametrize("table,allowed", tables_and_keys(), ids=lambda v: v if isinstance(v, str) else "")
@SETTINGS
@given(data=st.data())
def test_misspelt_key_names_file_key_and_closest(table, allowed, data):
    key = data.draw(st.sampled_from(sorted(allowed)), label="key")
    i = data.draw(st.integers(0, len(key) - 1), label="position")
    typo = data.draw(st.sampled_from([key[:i] + key[i + 1:], key + "s", key[:i] + "_" + key[i:]]), label="typo")
    if typo in allowed or not typo:
        return
    raw = base_pattern()
    target = raw if table == "" else (raw["fabric"].setdefault(table[7:], {}) if table.startswith("fabric.") else
                                      (raw[table][0] if isinstance(raw.get(table), list) else
                                       raw.setdefault(table, {})))
    target[typo] = 1.0
    with folder() as d:
        line = mesh_error(raw, d)
    assert f"unknown key {typo!r}" in line, line
    close = difflib.get_close_matches(typo, sorted(allowed), n=1, cutoff=0.6)
    assert (f"did you mean {close[0]!r}?" in line) if close else ("allowed:" in line), line


@pytest.mark.parametrize("text, word", [
    ("[solver]\nsed = 3", "[solver]: unknown key 'sed' (did you mean 'seed'?)"),
    ("[solver]\nmax_iteration = 1", "[solver]: unknown key 'max_iteration' (did you mean 'max_iterations'?)"),
    ("[fabric]\nstretch = 135", "[fabric]: stretch must be in [1, 3], got 135"),
    ("[fabric]\nyoung_modulus_mpa = 1e300", "[fabric]: young_modulus_mpa must be in"),
    ("[plastic]\nyoung_modulus_mpa = 1e300", "[plastic]: young_modulus_mpa must be in"),
    ("[fabric]\nthickness_mm = 1e300", "[fabric]: thickness_mm must be in"),
    ("[solver]\nseed = -1", "[solver]: seed must be an integer in [0, 4294967295], got -1"),
    ("[[region]]\npolygon = [[10, 10], [12, 10], [12, 10.00001]]\nthickness_mm = 0.4",
     "[[region]] #2: polygon is a"),
    ("[stars]\nspacing_mm = 10\narm_length = 1e-9", "[stars] arm_length gives a 1e-08 mm arm"),
    ("[stars]\nspacing_mm = 500\norigin = [300, 300]", "[stars] no lattice node lies inside the fabric"),
])
def test_cases_of_the_issue(text, word):
    """Appended to a valid pattern (its own tables replaced where the text repeats them)."""
    raw = base_pattern()
    import tomllib
    extra = tomllib.loads(text)
    for k, v in extra.items():
        if isinstance(raw.get(k), list):
            raw[k] = raw[k] + v
        elif isinstance(raw.get(k), dict) and k != "stars":
            raw[k] = {**raw[k], **v}
        else:
            raw[k] = v
    with folder() as d:
        line = mesh_error(raw, d)
    assert word in line, line


@pytest.mark.parametrize("shape", [{"disk": 1e-6}, {"rectangle": [1e300, 4.0]}, {"hexagon": 0.1},
                                   {"rectangle": [0.2, 40.0]}])
def test_tiny_and_huge_fabrics(shape):
    raw = base_pattern()
    raw["fabric"].pop("rectangle")
    raw["fabric"].update(shape)
    with folder() as d:
        line = mesh_error(raw, d)
    assert "[fabric]" in line and next(iter(shape)) in line, line


# ---------------------------------------------------------------- parser limits

@pytest.mark.parametrize("expr", ["-" * 999 + "x", "+".join(["0"] * 999), "9" * 400, "x" + "**x" * 500])
def test_expressions_deep_or_overflowing_are_one_line(expr):
    raw = base_pattern()
    raw["stars"]["thickness_mm"] = expr
    with folder() as d:
        line = mesh_error(raw, d)
    assert "[stars] thickness_mm" in line and ("nested" in line or "float range" in line), line


@pytest.mark.parametrize("text", ["a = " + "[" * 3000 + "]" * 3000, "a = " + "{b = " * 2000 + "1" + "}" * 2000,
                                  "[meta]\na = " + "[" * 40 + "]" * 40])
def test_deeply_nested_toml_is_one_line(tmp_path, text):
    p = tmp_path / "deep.toml"
    p.write_text(text + "\n")
    rc, _, stderr = run(["mesh", str(p), "-o", str(tmp_path / "o.msh")])
    assert rc == 2 and "deep.toml" in stderr and "nested deeper than 32" in stderr, stderr
    assert len(stderr.splitlines()) == 1


@pytest.mark.parametrize("faces, word", [
    ("f 1 2 99999999999999999999999", "line 4: a face index is beyond the int64 range"),
    ("f 1 2 -99999999999999999999999", "line 4: a face index is beyond the int64 range"),
    ("f 1 2 4", "references a vertex index outside"),
])
def test_target_face_indices_beyond_int64(tmp_path, faces, word):
    t = tmp_path / "t.obj"
    t.write_text(f"v 0 0 0\nv 1 0 0\nv 0 1 1\n{faces}\n")
    rc, _, stderr = run(["design", str(t), "-o", str(tmp_path / "out")])
    assert rc == 2 and "t.obj" in stderr and word in stderr and len(stderr.splitlines()) == 1, stderr
    assert not (tmp_path / "out").exists()


def test_target_huge_coordinates_and_uint64_faces():
    from geometry.target import check_disk
    from shellfem.errors import SelfshapeError
    V = np.array([[0, 0, 0], [1e300, 0, 0], [0, 1e300, 0]], float)
    with pytest.raises(SelfshapeError, match="vertex 1 has a coordinate beyond"):
        check_disk(V, np.array([[0, 1, 2]]), "t")
    with pytest.raises(SelfshapeError, match="beyond the int64 range"):
        check_disk(V / 1e300, np.array([[0, 1, 2 ** 64 - 1]], dtype=np.uint64), "t")


@pytest.mark.parametrize("obj, word", [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "the target is flat (3 vertices"),
    ("v 0 0 0\nv 10 0 0\nv 10 10 0.001\nv 0 10 0\nf 1 2 3\nf 1 3 4\n", "the target is flat"),
])
def test_flat_target_has_nothing_to_design(tmp_path, obj, word):
    t = tmp_path / "flat.obj"
    t.write_text(obj)
    rc, _, stderr = run(["design", str(t), "-o", str(tmp_path / "out")])
    assert rc == 2 and "flat.obj" in stderr and word in stderr and len(stderr.splitlines()) == 1, stderr
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- resource bounds

def test_mesh_budget_refuses_before_meshing():
    """size_mm = 0.002 on a 20 x 4 mm sheet is below the range; through --size (no range) and
    0.05 mm on a 200 x 100 mm sheet (in range) the triangle budget refuses it, in well under a
    second, with the count it would need."""
    raw = {"fabric": {"rectangle": [20.0, 4.0]}, "ribbon": [{"path": [[1.0, 2.0], [19.0, 2.0]]}],
           "mesh": {"size_mm": 0.002}}
    with folder() as d:
        assert "[mesh]: size_mm must be in [0.01, 1000] mm, got 0.002" in mesh_error(raw, d)
        raw["mesh"]["size_mm"] = 1.0
        path = os.path.join(d, "ok.toml")
        with open(path, "wb") as f:
            tomli_w.dump(raw, f)
        t0 = time.perf_counter()
        rc, _, stderr = run(["mesh", path, "-o", os.path.join(d, "o.msh"), "--size", "0.002"])
        assert time.perf_counter() - t0 < 5.0
        assert rc == 2 and re.search(r"mesh size 0.002 mm would need about [0-9.]+e\+07 triangles", stderr), stderr
        assert f"{MAX_TRIANGLES:,}" in stderr and not os.path.exists(os.path.join(d, "o.msh"))
        big = {"fabric": {"rectangle": [200.0, 100.0]}, "ribbon": [{"path": [[1.0, 2.0], [19.0, 2.0]]}],
               "mesh": {"size_mm": 0.05}}
        assert "mesh size 0.05 mm would need about 1.85e+07 triangles" in mesh_error(big, d)


@pytest.mark.parametrize("size", [2.0, 0.8])
def test_triangle_estimate_is_within_the_documented_factor(size):
    """The estimate the budget uses is 0.5-2x the real count (docs/pattern-format.md)."""
    import shapely

    from geometry.arrangement import feature_width, printed_pieces
    from geometry.meshing import estimate_triangles, mesh_pattern
    p = patterns.load_pattern(base_pattern() | {"print": {"gcode": GCODE}})
    g, _, _, _ = printed_pieces(p.elements)
    est = estimate_triangles(p.outline.area, shapely.area(g), shapely.length(g),
                             np.maximum(feature_width(g) / p.mesh_across, size * 1e-3), size)
    n = mesh_pattern(p, size_mm=size).n_triangles
    assert 0.5 <= n / est <= 2.0, (n, est)


def test_retraced_gcode_is_bounded(tmp_path):
    """One 2 mm segment printed back and forth 1,000 times (16 KB): read in a subprocess
    capped at 2 GB of address space (GEOS needed > 4 GB before), to one bead."""
    lines = ["M83", "G1 Z0.2 F600", "G0 X10 Y10"] + ["G1 X12 Y10 E0.1" if i % 2 == 0 else "G1 X10 Y10 E0.1"
                                                      for i in range(1000)]
    (tmp_path / "retrace.gcode").write_text("\n".join(lines) + "\n")
    code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30));"
            "from geometry.gcode import read_gcode; e = read_gcode(sys.argv[1]);"
            "print(len(e), round(e[0].geometry.area, 3), round(e[0].thickness_mm, 3))")
    env = dict(os.environ, PYTHONPATH=ROOT, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "retrace.gcode")], capture_output=True, text=True,
                       timeout=120, env=env)
    assert r.returncode == 0, r.stderr[-500:]
    n, area, h = r.stdout.split()
    # the bead of the segment: width from the volume of one pass, square ends
    assert int(n) == 1 and float(h) == 0.2 and 1.0 < float(area) < 3.0


def test_gcode_segment_cap_names_the_line(tmp_path, monkeypatch):
    import geometry.gcode as gc
    from shellfem.errors import SelfshapeError
    monkeypatch.setattr(gc, "MAX_SEGMENTS", 50)
    lines = ["M83", "G1 Z0.2"] + [f"G1 X{i + 1} Y0 E0.05" for i in range(60)]
    (tmp_path / "long.gcode").write_text("\n".join(lines) + "\n")
    with pytest.raises(SelfshapeError, match=r"long.gcode: line 53: more than 50 extruded segments"):
        gc.read_gcode(tmp_path / "long.gcode")


def test_gcode_layer_cap_names_the_line(tmp_path, monkeypatch):
    import geometry.gcode as gc
    from shellfem.errors import SelfshapeError
    monkeypatch.setattr(gc, "MAX_LAYERS", 5)
    lines = ["M83"] + [f"G1 Z{0.2 * (k + 1):.1f}\nG0 X0 Y{k}\nG1 X10 Y{k} E0.5" for k in range(8)]
    (tmp_path / "tall.gcode").write_text("\n".join(lines) + "\n")
    with pytest.raises(SelfshapeError, match=r"tall.gcode: line 19: more than 5 extrusion heights"):
        gc.read_gcode(tmp_path / "tall.gcode")


@pytest.mark.parametrize("line, word", [
    ("G1 X1e999 Y0 E1", "line 4: parameter X is not a finite number"),
    ("G1 Xinf Y0 E1", "line 4: parameter X is not a finite number"),
    ("G1 X20000 Y0 E1", "line 4: a move beyond"),
    ("G2 X10 Y0 I1e300 J0 E1", "line 4: arc radius beyond"),
])
def test_gcode_numbers_are_bounded(tmp_path, line, word):
    from geometry.gcode import read_gcode
    from shellfem.errors import SelfshapeError
    (tmp_path / "n.gcode").write_text(f"M83\nG1 Z0.2\nG0 X1 Y1\n{line}\n")
    with pytest.raises(SelfshapeError, match=re.escape(word)):
        read_gcode(tmp_path / "n.gcode")


# ---------------------------------------------------------------- files

SECRET = "SECRET-TOKEN-7f3a: root:x:0:0"


@pytest.mark.parametrize("where", ["parent", "absolute", "symlink"])
def test_print_gcode_may_not_leave_the_pattern_folder(tmp_path, where):
    outside = tmp_path / "secret.gcode"
    outside.write_text(SECRET + "\n")
    d = tmp_path / "patterns"
    d.mkdir()
    name = {"parent": "../secret.gcode", "absolute": str(outside), "symlink": "link.gcode"}[where]
    if where == "symlink":
        (d / "link.gcode").symlink_to(outside)
    raw = base_pattern()
    raw["print"] = {"gcode": name}
    line = mesh_error(raw, str(d))
    assert "[print] gcode" in line and "outside the pattern's folder" in line and "SECRET" not in line, line


def test_print_gcode_below_the_folder_and_on_the_command_line_are_fine(tmp_path):
    (tmp_path / "prints").mkdir()
    shutil.copy(GCODE, tmp_path / "prints" / "p.gcode")
    raw = base_pattern()
    raw["print"] = {"gcode": "prints/p.gcode"}
    (tmp_path / "pattern.toml").write_text(tomli_w.dumps(raw))
    assert any(e.kind == "gcode" for e in patterns.load_pattern(tmp_path / "pattern.toml").elements)
    elsewhere = tempfile.mkdtemp(prefix="contract-cli-")
    try:                                      # a G-code file named on the command line may be anywhere
        rc, _, stderr = run(["mesh", os.path.relpath(GCODE), "-o", os.path.join(elsewhere, "o.msh"), "--size", "3"])
        assert rc == 0, stderr
    finally:
        shutil.rmtree(elsewhere)


@pytest.mark.parametrize("content", [SECRET, "G1 X1 Y1\n" + SECRET, ";WIDTH: " + SECRET, "G1 X" + SECRET])
def test_gcode_errors_never_echo_the_file(tmp_path, content):
    (tmp_path / "print.gcode").write_text(content + "\n")
    raw = base_pattern()
    raw["print"] = {"gcode": "print.gcode"}
    line = mesh_error(raw, str(tmp_path))
    assert re.search(r"\[print\] gcode print.gcode: line \d+:", line), line
    assert "SECRET" not in line and "root:" not in line, line


STRIPS = os.path.join(ROOT, "validation", "data", "strips_S1.csv")
#: every input file of every verb: name -> argv, with {IN} the input under test, {OUT} the output
INPUT_SLOTS = {
    "mesh pattern": ["mesh", "{IN}.toml", "-o", "{OUT}.msh"],
    "export gcode": ["export", "{IN}.gcode", "-o", "{OUT}.svg"],
    "simulate pattern": ["simulate", "{IN}.toml", "-o", "{OUT}"],
    "design target obj": ["design", "{IN}.obj", "-o", "{OUT}"],
    "design target ply": ["design", "{IN}.ply", "-o", "{OUT}"],
    "design --printer": ["design", TARGET, "-o", "{OUT}", "--stretch", "1.3", "--printer", "{IN}.toml"],
    "design --law": ["design", TARGET, "-o", "{OUT}", "--stretch", "1.3", "--law", "{IN}.csv"],
    "design --contraction": ["design", TARGET, "-o", "{OUT}", "--stretch", "1.3", "--contraction", "{IN}.csv"],
    "calibrate strips": ["calibrate", "strips", "{IN}.csv", "-o", "{OUT}"],
    "validate": ["validate", "{IN}.csv", "-o", "{OUT}"],
    "predict model": ["predict", "{IN}.json", STRIPS, "-o", "{OUT}.csv"],
    "predict data": ["predict", os.path.join(ROOT, "tests", "data", "model_S1.json"), "{IN}.csv", "-o", "{OUT}.csv"],
    "law build": ["law", "build", "{IN}.csv", "-o", "{OUT}.csv"],
    "sweep": ["sweep", "{IN}.toml", "-o", "{OUT}", "--workers", "0"],
    "calibration-print --printer": ["calibration-print", "strips", "-o", "{OUT}", "--printer", "{IN}.toml"],
}


def _not_a_file(kind, path):
    if kind == "named pipe":
        os.mkfifo(path)
    elif kind == "device":
        os.symlink("/dev/zero", path)
    else:
        os.mkdir(path)


@pytest.mark.parametrize("kind, word", [("named pipe", "is a named pipe (FIFO)"), ("device", "is a device"),
                                        ("directory", "is a directory")])
@pytest.mark.parametrize("slot", sorted(INPUT_SLOTS))
def test_an_input_that_is_not_a_regular_file_is_refused_before_reading(tmp_path, slot, kind, word):
    """Every input file of every verb given a named pipe, a device (/dev/zero behind a link)
    or a directory: one line naming it and what it is, status 2, nothing written, and no
    read (issue 19: a FIFO blocked forever, /dev/zero ran into a MemoryError, exit 3)."""
    import signal
    argv = [a.replace("{OUT}", str(tmp_path / "out")) for a in INPUT_SLOTS[slot]]
    i = next(k for k, a in enumerate(argv) if a.startswith("{IN}"))
    argv[i] = str(tmp_path / ("in" + argv[i][len("{IN}"):]))
    _not_a_file(kind, argv[i])

    def hung(*_):
        raise TimeoutError(f"{slot}: the verb blocked reading a {kind}")
    old = signal.signal(signal.SIGALRM, hung)
    signal.alarm(20)
    try:
        rc, stdout, stderr = run(argv)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    lines = stderr.splitlines()
    assert rc == 2 and len(lines) == 1 and stdout == "", (rc, stderr)
    assert os.path.basename(argv[i]) in lines[0] and word in lines[0], lines[0]
    assert not any(n.startswith("out") for n in os.listdir(tmp_path)), os.listdir(tmp_path)


def test_gcode_entirely_outside_the_fabric(tmp_path):
    shutil.copy(GCODE, tmp_path / "two_lines.gcode")
    raw = base_pattern()
    raw["print"] = {"gcode": "two_lines.gcode", "origin_mm": [150.0, 150.0]}
    line = mesh_error(raw, str(tmp_path))
    assert "[print] two_lines.gcode: the print lies entirely outside the fabric" in line, line


def test_bare_sheet_is_an_error_unless_it_drapes(tmp_path):
    raw = {"fabric": {"rectangle": [40.0, 30.0]}}
    line = mesh_error(raw, str(tmp_path))
    assert "nothing is printed" in line and "areal_weight_n_per_mm2" in line, line
    raw = {"fabric": {"rectangle": [40.0, 30.0], "areal_weight_n_per_mm2": 2e-6},
           "support": [{"points": [[20.0, 15.0]], "fix": "xyz"}]}
    (tmp_path / "drape.toml").write_text(tomli_w.dumps(raw))
    assert patterns.load_pattern(tmp_path / "drape.toml").elements == []
    assert patterns.load_pattern({"fabric": {"rectangle": [40.0, 30.0]}}).elements == []   # the Python API


def test_the_real_command_line_prints_one_line():
    """Out of process, the same contract holds: exit 2, one stderr line, no traceback."""
    with folder() as d:
        raw = base_pattern()
        raw["solver"]["sed"] = 3
        path = os.path.join(d, "pattern.toml")
        with open(path, "wb") as f:
            tomli_w.dump(raw, f)
        r = subprocess.run([sys.executable, "-m", "selfshape.cli", "mesh", path, "-o", os.path.join(d, "o.msh")],
                           capture_output=True, text=True, timeout=120, env=dict(os.environ, PYTHONPATH=ROOT))
    assert r.returncode == 2 and r.stdout == "" and len(r.stderr.splitlines()) == 1, r.stderr
    assert "pattern.toml: [solver]: unknown key 'sed' (did you mean 'seed'?)" in r.stderr


def test_ranges_in_the_docs_are_the_schema():
    text = open(os.path.join(ROOT, "docs", "pattern-format.md")).read()
    block = text.split("<!-- ranges: generated by geometry.schema.ranges_markdown(), do not edit by hand -->\n")[1]
    assert block.split("<!-- end of ranges -->")[0] == ranges_markdown()


def test_examples_and_test_patterns_are_inside_the_ranges():
    """Every shipped pattern parses under the ranges (a range that breaks one is wrong, or it is)."""
    import glob
    files = [f for f in glob.glob(os.path.join(ROOT, "examples", "**", "*.toml"), recursive=True)
             if not os.path.basename(f).startswith("sweep_")]             # sweep files: tests/test_sweep.py
    files += [f for f in glob.glob(os.path.join(ROOT, "tests", "data", "patterns", "*.toml"))
              if os.path.basename(f) not in ("malformed.toml", "region_outside.toml", "region_self_intersecting.toml",
                                             "typo.toml")]
    assert len(files) >= 12
    for f in files:
        patterns.load_pattern(f)
