import copy
import glob
import math
import os
import shutil
import tomllib

import numpy as np
import pytest
import tomli_w

from geometry.patterns import fabric_table, load_pattern, plastic_table, write_pattern
from shellfem.materials import MEMBRANE_MODELS, Fabric, Plastic
from shellfem.errors import SelfshapeError

HERE = os.path.dirname(__file__)
DATA = os.path.join(HERE, "data", "patterns")
EXAMPLES = os.path.join(HERE, "..", "examples")

BASE = {
    "fabric": {"rectangle": [40.0, 20.0], "stretch": 1.35},
    "region": [{"polygon": [[1.0, 1.0], [9.0, 1.0], [9.0, 9.0], [1.0, 9.0]], "thickness_mm": 0.3},
               {"polygon": [[12.0, 1.0], [20.0, 1.0], [20.0, 9.0]], "thickness_mm": 0.2, "side": "back"}],
    "ribbon": [{"path": [[2.0, 15.0], [38.0, 15.0]], "width_mm": 1.5, "thickness_mm": 0.4}],
    "support": [{"points": [[0.0, 0.0]], "fix": "z"}],
}


def test_all_entries_round_trip(tmp_path):
    path = os.path.join(DATA, "all_entries.toml")
    p = load_pattern(path)
    f = p.fabric
    assert f.stretch == (1.6, 1.2) and f.thickness == 0.7 and f.model == "orthotropic"
    assert (f.young_modulus, f.poisson, f.bending_stiffness, f.course_angle_deg, f.areal_weight) == \
        (1.2, 0.25, 0.02, 15.0, 1e-6)
    assert f.parameters["orthotropic"] == dict(a1=0.03, a2=0.09, a3=0.06, b1=0.03, b2=0.02, g1=1.5, g2=1.5)
    assert (p.plastic.young_modulus, p.plastic.poisson, p.plastic.rest_curvature) == (70.0, 0.45, 0.01)
    assert p.outline.area == 2400.0 and p.outline.bounds == (0.0, 0.0, 60.0, 40.0)
    assert p.mesh_size == 2.0 and p.seed == 7 and p.raw["solver"]["max_iterations"] == 50 and p.max_iterations == 50
    kinds = [e.kind for e in p.elements]
    assert kinds[:2] == ["region", "ribbon"] and set(kinds[2:]) == {"star"}
    reg, rib = p.elements[:2]
    assert (reg.geometry.area, reg.thickness_mm, reg.side, reg.label) == (100.0, 0.4, "back", "region #1")
    # ribbon: 45 mm of 1.5 mm bead with a mitred corner and round ends (polygonised)
    assert rib.geometry.area == pytest.approx(45 * 1.5 + math.pi * 0.75 ** 2, rel=0.01)
    assert (rib.thickness_mm, rib.side) == (0.3, "front")
    stars = p.elements[2:]
    # stars where x > 30 (origin (30, 30), spacing 12): thickness 0.2 + 0.001 r
    for s in stars:
        assert s.geometry.centroid.x > 30 - 12 * 0.5
        assert 0.2 < s.thickness_mm < 0.2 + 0.001 * 73
    assert [s.fix for s in p.supports] == ["z", "xyz"]
    np.testing.assert_array_equal(p.supports[0].points, [[0, 0], [60, 0]])
    np.testing.assert_array_equal(p.supports[1].position, [[20, 25, 0]])
    # dict -> TOML file -> Pattern gives the same result
    out = tmp_path / "again.toml"
    out.write_bytes(tomli_w.dumps(p.raw).encode())
    q = load_pattern(out)
    assert q.raw == p.raw and q.outline.equals(p.outline)
    assert [(e.kind, e.label, e.thickness_mm, e.side) for e in q.elements] == \
        [(e.kind, e.label, e.thickness_mm, e.side) for e in p.elements]
    assert all(a.geometry.equals(b.geometry) for a, b in zip(p.elements, q.elements))
    assert load_pattern(p.raw).elements[0].geometry.equals(reg.geometry)


def test_defaults_and_shapes():
    p = load_pattern({"fabric": {"hexagon": 67.0}})
    assert p.outline.area == pytest.approx(3 * math.sqrt(3) / 2 * 67 ** 2, rel=1e-12)
    assert p.outline.bounds[2] == pytest.approx(67.0)           # vertex on +x
    assert p.fabric.stretch == (1.35, 1.35) and p.mesh_size == 1.0 and p.seed == 0
    assert p.elements == [] and p.supports == [] and p.source == "<dict>"
    d = load_pattern({"fabric": {"disk": 30.0}, "mesh": {"size_mm": 0.5}})
    n = len(d.outline.exterior.coords) - 1
    assert n == math.ceil(2 * math.pi * 30 / 0.5)                # edges of about the mesh size
    assert d.outline.area == pytest.approx(0.5 * n * 30 ** 2 * math.sin(2 * math.pi / n), rel=1e-12)
    cw = load_pattern({"fabric": {"outline": [[0, 0], [0, 10], [10, 10], [10, 0], [0, 0]]}})
    assert cw.outline.area == 100.0 and cw.outline.exterior.is_ccw


def test_fabric_with_holes_clips_the_print():
    raw = copy.deepcopy(BASE)
    whole = load_pattern(raw).elements[-1].geometry.area
    raw["fabric"]["holes"] = [[[24.0, 12.0], [34.0, 12.0], [34.0, 18.0], [24.0, 18.0]],
                              [[2.0, 11.0], [2.0, 12.5], [0.5, 12.5]]]        # clockwise: any orientation
    p = load_pattern(raw)
    assert p.outline.area == pytest.approx(800.0 - 60.0 - 1.125, rel=1e-12)
    assert len(p.outline.interiors) == 2 and all(not r.is_ccw for r in p.outline.interiors)
    ribbon = p.elements[-1].geometry                   # the ribbon at y = 15 crosses the first hole
    assert ribbon.geom_type == "MultiPolygon" and ribbon.area == pytest.approx(whole - 10.0 * 1.5, rel=1e-12)
    assert load_pattern({"fabric": {"disk": 20.0, "holes": []}}).outline.interiors.__len__() == 0


def test_ribbon_and_gcode_clipped_to_fabric():
    raw = copy.deepcopy(BASE)
    raw["ribbon"] = [{"path": [[-10.0, 10.0], [50.0, 10.0]], "width_mm": 2.0}]
    p = load_pattern(raw)
    rib = p.elements[-1]
    assert rib.geometry.area == pytest.approx(40.0 * 2.0, rel=1e-12)
    assert rib.thickness_mm == 0.4 and rib.side == "front"        # defaults


def test_examples_load():
    files = sorted(f for f in glob.glob(os.path.join(EXAMPLES, "*.toml"))
                   if not os.path.basename(f).startswith("sweep_"))       # sweep files: tests/test_sweep.py
    assert {os.path.basename(f) for f in files} >= {"strip.toml", "stars_tube.toml", "stars_dome.toml",
                                                    "stars_flat_centre.toml", "ribbons.toml"}
    for f in files:
        p = load_pattern(f)
        assert p.elements
    assert len(load_pattern(os.path.join(EXAMPLES, "stars_dome.toml")).elements) == 37
    strip = load_pattern(os.path.join(EXAMPLES, "strip.toml"))
    assert strip.elements[0].geometry.equals(strip.outline) and strip.elements[0].thickness_mm == 0.3


def _bad(mutate):
    raw = copy.deepcopy(BASE)
    mutate(raw)
    with pytest.raises(SelfshapeError) as e:
        load_pattern(raw)
    return str(e.value)


BAD = [
    (lambda r: r["region"][1].update(polygon=[[12, 1], [20, 9], [20, 1], [12, 9]]),
     "<dict>: [[region]] #2: polygon is self-intersecting at (16, 5)"),
    (lambda r: r["region"][0].update(polygon=[[30, 1], [45, 1], [45, 5]]),
     "[[region]] #1: polygon crosses the fabric outline"),
    (lambda r: r["region"][0].update(polygon=[[50, 1], [55, 1], [55, 5]]),
     "[[region]] #1: polygon is outside the fabric"),
    (lambda r: r["region"][1].update(thickness_mm=-0.1), "[[region]] #2: thickness_mm must be in [0.01, 10] mm, got -0.1"),
    (lambda r: r["region"][1].update(thickness_mm=0), "[[region]] #2: thickness_mm must be in [0.01, 10] mm, got 0"),
    (lambda r: r["region"][1].update(thickness_mm=float("nan")), "[[region]] #2: thickness_mm must be a finite number"),
    (lambda r: r["region"][1].update(side="top"), "[[region]] #2: side must be one of 'front', 'back'"),
    (lambda r: r["region"][0].update(thikness_mm=0.3), "[[region]] #1: unknown key 'thikness_mm'"),
    (lambda r: r["region"][0].pop("polygon"), "[[region]] #1: missing polygon"),
    (lambda r: r["region"][0].update(polygon=[[0, 0], [1, 1]]), "[[region]] #1: polygon needs at least 3 distinct"),
    (lambda r: r["region"][0].update(polygon=[[0, 0], [1, 1], [2, 2]]), "[[region]] #1: polygon"),
    (lambda r: r["region"][0].update(polygon="square"), "[[region]] #1: polygon must be a list of [x, y] points"),
    (lambda r: r["fabric"].update(stretch=0.9), "[fabric]: stretch must be in [1, 3], got 0.9"),
    (lambda r: r["fabric"].update(stretch=[1.2, 0.95]), "[fabric]: stretch must be in [1, 3], got 0.95"),
    (lambda r: r["fabric"].update(stretch=[1.2, 1.3, 1.4]), "[fabric]: stretch must be a number or [sx, sy]"),
    (lambda r: r["fabric"].update(stretch=float("nan")), "[fabric]: stretch must be a finite number"),
    (lambda r: r["fabric"].update(disk=10.0), "[fabric]: give exactly one of rectangle, outline, disk, hexagon"),
    (lambda r: r["fabric"].pop("rectangle"), "[fabric]: give exactly one of"),
    (lambda r: r["fabric"].update(outline=[[0, 0], [10, 10], [10, 0], [0, 10]], rectangle=None) or
     r["fabric"].pop("rectangle"), "[fabric] outline: polygon is self-intersecting at (5, 5)"),
    (lambda r: r["fabric"].update(model="linear"), "fabric.model must be"),
    (lambda r: r["fabric"].update(poisson=0.7), "[fabric]: poisson must be in [-0.99, 0.499], got 0.7"),
    (lambda r: r["fabric"].update(thickness_mm=True), "[fabric]: thickness_mm must be a number in [0.01, 10] mm, got true/false"),
    (lambda r: r["fabric"].update(orthotropic={"a4": 1.0}), "[fabric] orthotropic: unknown key 'a4'"),
    (lambda r: r.pop("fabric"), "<dict>: missing [fabric] table"),
    (lambda r: r.update(fabrik={}), "<dict>: unknown key 'fabrik'"),
    (lambda r: r.update(plastic={"young_modulus_mpa": 0}), "<dict>: [plastic]: young_modulus_mpa must be in [0.1, 100000] MPa, got 0"),
    (lambda r: r.update(plastic={"poison": 0.3}), "[plastic]: unknown key 'poison'"),
    (lambda r: r["ribbon"][0].update(path=[[50, 50], [60, 50]]), "[[ribbon]] #1: ribbon lies entirely outside"),
    (lambda r: r["ribbon"][0].update(width_mm=0.0), "[[ribbon]] #1: width_mm must be in [0.1, 500] mm, got 0"),
    (lambda r: r["ribbon"][0].update(ends="pointy"), "[[ribbon]] #1: ends must be one of 'square', 'round'"),
    (lambda r: r["ribbon"][0].update(path=[[1, 1], [1, 1]]), "[[ribbon]] #1: path needs at least 2 distinct"),
    (lambda r: r["ribbon"][0].update(path=[[1, 1], [float("inf"), 1]]), "[[ribbon]] #1 path: point 2"),
    (lambda r: r.update(stars={"spacing_mm": 10, "arm_length": "0.5 +"}), "[stars] arm_length: cannot parse"),
    (lambda r: r.update(stars={"spacing_mm": 10, "arm_length": 1.5}), "[stars]: arm_length must be in [0, 1], got 1.5"),
    (lambda r: r.update(stars={"spacing_mm": 10, "arm_length": "1.5 + 0 * x"}), "[stars] arm_length is 1.5 at the star"),
    (lambda r: r.update(stars={"arm_length": 0.5}), "[stars]: missing spacing_mm"),
    (lambda r: r.update(stars={"spacing_mm": 10, "arm_lenght": 0.5}), "[stars]: unknown key 'arm_lenght'"),
    (lambda r: r["support"][0].update(points=[[0, 0], [41, 5]]), "[[support]] #1: point 2 (41, 5) is outside"),
    (lambda r: r["support"][0].update(fix="x"), "[[support]] #1: fix must be one of 'z', 'xyz'"),
    (lambda r: r["support"][0].update(position=[[0, 0, 0]]), "[[support]] #1: position is only meaningful"),
    (lambda r: r["support"][0].update(fix="xyz", position=[[0, 0, 0], [1, 1, 1]]),
     "[[support]] #1: position has 2 entries but points has 1"),
    (lambda r: r.update(mesh={"size_mm": 0}), "[mesh]: size_mm must be in [0.01, 1000] mm, got 0"),
    (lambda r: r.update(mesh={"size": 1}), "[mesh]: unknown key 'size'"),
    (lambda r: r.update(solver={"seed": 1.5}), "[solver]: seed must be an integer in"),
    (lambda r: r.update(solver={"max_iterations": 0}), "[solver]: max_iterations must be an integer in [1, 100000], got 0"),
    (lambda r: r.update(solver={"max_iterations": "many"}), "[solver]: max_iterations must be an integer in [1, 100000], got the string"),
    (lambda r: r.update(solver={"metric_floor": -1.0}), "[solver]: metric_floor must be in [0, 1e+06], got -1"),
    (lambda r: r.update(solver={"metric_floor": "high"}), "[solver]: metric_floor must be a number in [0, 1e+06], got the string"),
    (lambda r: r.update(solver={"metric_floor": True}), "[solver]: metric_floor must be a number in [0, 1e+06], got true/false"),
    (lambda r: r.update(solver={"metric_floor": float("nan")}), "[solver]: metric_floor must be a finite number"),
    (lambda r: r.update(solver={"metric_predictor": "no"}), "[solver]: metric_predictor must be true or false"),
    (lambda r: r.update(print={"gcode": 3}), "[print]: gcode must be a file name"),
    (lambda r: r["fabric"].update(holes=[[[35, 5], [45, 5], [45, 10], [35, 10]]]),
     "[fabric] holes[1]: the hole is not inside the fabric (near (42.5"),
    (lambda r: r["fabric"].update(holes=[[[30, 5], [39.95, 5], [39.95, 10], [30, 10]]]),
     "[fabric] holes[1]: the hole is 0.05 mm from the fabric's edge; at least 0.1 mm"),
    (lambda r: r["fabric"].update(holes=[[[24, 4], [30, 4], [30, 8], [24, 8]], [[28, 6], [34, 6], [34, 9], [28, 9]]]),
     "[fabric] holes[2]: the hole overlaps hole 1"),
    (lambda r: r["fabric"].update(holes=[[[24, 4], [30, 4], [30, 8], [24, 8]], [[30.05, 4], [34, 4], [34, 8]]]),
     "[fabric] holes[2]: the hole is 0.05 mm from hole 1"),
    (lambda r: r["fabric"].update(holes=[[[24, 4], [30, 8], [30, 4], [24, 8]]]),
     "[fabric] holes[1]: polygon is self-intersecting at (27, 6)"),
    (lambda r: r["fabric"].update(holes=[[24, 4], [30, 4], [30, 8]]), "[fabric] holes[1]: polygon must be a list of"),
    (lambda r: r["fabric"].update(holes="square"), "[fabric] holes must be a list of polygons"),
    (lambda r: r["fabric"].update(holes=[[[2, 2], [8, 2], [8, 8], [2, 8]]]),
     "[[region]] #1: polygon crosses a hole of the fabric"),
    (lambda r: r["fabric"].update(holes=[[[0.5, 0.5], [9.5, 0.5], [9.5, 9.5], [0.5, 9.5]]]),
     "[[region]] #1: polygon lies in a hole of the fabric"),
    (lambda r: r["fabric"].update(holes=[[[24, 4], [30, 4], [30, 8], [24, 8]]]) or
     r["support"][0].update(points=[[25, 5]]), "[[support]] #1: point 1 (25, 5) is in a hole of the fabric"),
    (lambda r: r["fabric"].update(holes=[[[1, 12], [39, 12], [39, 18], [1, 18]]]),
     "[[ribbon]] #1: ribbon lies entirely outside"),
]


@pytest.mark.parametrize("mutate,message", BAD)
def test_bad_input_names_the_entry(mutate, message):
    msg = _bad(mutate)
    assert message in msg and "\n" not in msg


@pytest.mark.parametrize("name,message", [
    ("malformed.toml", "malformed.toml: malformed TOML: "),
    ("region_self_intersecting.toml", "region_self_intersecting.toml: [[region]] #2: polygon is self-intersecting "
                                      "at (15, 7)"),
    ("region_outside.toml", "region_outside.toml: [[region]] #1: polygon crosses the fabric outline"),
    ("typo.toml", "typo.toml: [fabric]: unknown key 'strech'"),
    ("missing.toml", "missing.toml: file not found"),
])
def test_bad_files(name, message):
    with pytest.raises(SelfshapeError) as e:
        load_pattern(os.path.join(DATA, name))
    assert message in str(e.value) and "\n" not in str(e.value)


def test_malformed_toml_names_the_line():
    with pytest.raises(SelfshapeError, match=r"malformed\.toml: malformed TOML: .*line 7"):
        load_pattern(os.path.join(DATA, "malformed.toml"))
    with pytest.raises(tomllib.TOMLDecodeError):           # the file really is malformed
        tomllib.loads(open(os.path.join(DATA, "malformed.toml")).read())


def test_gcode_print_entry_and_bare_gcode(tmp_path):
    gpath = os.path.join(DATA, "two_lines.gcode")
    raw = {"fabric": {"rectangle": [30.0, 30.0]}, "print": {"gcode": gpath}}
    p = load_pattern(raw)
    # two 30 mm x 1.5 mm beads at y = 10 and 20, square caps (x 9.25..40.75) clipped at x = 30
    assert [e.kind for e in p.elements] == ["gcode", "gcode"]
    for e in p.elements:
        assert e.geometry.bounds[2] == pytest.approx(30.0) and e.thickness_mm == pytest.approx(0.4)
        assert e.geometry.area == pytest.approx((30.0 - 9.25) * 1.5, rel=1e-9)
    bare = load_pattern(gpath)
    assert bare.outline.bounds == pytest.approx((9.25 - 10, 9.25 - 10, 40.75 + 10, 20.75 + 10))
    assert len(bare.elements) == 2 and bare.fabric.stretch == (1.35, 1.35)
    with pytest.raises(SelfshapeError, match=r"\[print\] gcode nothere.gcode: G-code file .* not found"):
        load_pattern({"fabric": {"rectangle": [30.0, 30.0]}, "print": {"gcode": "nothere.gcode"}})


def _every_entry(model: str) -> dict:
    """A pattern with every key of every table set, each to a value other than its default."""
    return {
        "fabric": {"rectangle": [60.0, 40.0], "stretch": [1.6, 1.2], "thickness_mm": 0.7, "model": model,
                   "young_modulus_mpa": 1.2, "poisson": 0.25, "bending_stiffness_nmm": 0.02,
                   "course_angle_deg": 15.0, "areal_weight_n_per_mm2": 1e-6,
                   "orthotropic": {"a1": 0.03, "a2": 0.09, "a3": 0.06, "b1": 0.03, "b2": 0.02, "g1": 1.5, "g2": 1.5},
                   "orthotropic-stvk": {"e1_mpa": 0.6, "e2_mpa": 1.4, "g12_mpa": 0.25, "nu12": 0.35}},
        "plastic": {"young_modulus_mpa": 70.0, "poisson": 0.45, "rest_curvature_per_mm": 0.01},
        "region": [{"polygon": [[5.0, 5.0], [15.0, 5.0], [15.0, 15.0], [5.0, 15.0]], "thickness_mm": 0.4,
                    "side": "back"}],
        "ribbon": [{"path": [[20.0, 5.0], [50.0, 5.0], [50.0, 20.0]], "width_mm": 1.2, "thickness_mm": 0.3,
                    "side": "back", "ends": "round"}],
        "stars": {"spacing_mm": 12.0, "arm_length": "where(x > 30, 0.5, 0)", "thickness_mm": "0.2 + 0.001 * r",
                  "arm_width_mm": 0.9, "side": "back", "origin": [30.0, 30.0], "angle_deg": 10.0},
        "print": {"gcode": os.path.abspath(os.path.join(DATA, "two_lines.gcode")), "side": "back",
                  "origin_mm": [170.0, 3.0]},    # the back is mirrored about x = 111.5 mm
        "support": [{"points": [[0.0, 0.0], [60.0, 0.0]], "fix": "z"},
                    {"points": [[30.0, 40.0]], "fix": "xyz", "position": [[20.0, 25.0, 1.0]]},
                    {"boundary": True, "fix": "xyz"}],
        "mesh": {"size_mm": 2.0, "across": 1.5},
        "solver": {"seed": 7, "max_iterations": 50, "metric_floor": 3.0, "coarse_levels": 2,
                   "metric_predictor": False},
        "contact": {"exclusion_mm": 5.0},
        "meta": {"generator": "tests/test_patterns.py"},
    }


@pytest.mark.parametrize("model", sorted(MEMBRANE_MODELS))
def test_every_field_round_trips_through_the_writer(tmp_path, model):
    """raw -> Pattern -> fabric_table / plastic_table -> write_pattern -> Pattern: the same
    Fabric, Plastic, elements, supports, mesh and solver fields; the tables give back every
    [fabric] and [plastic] entry that was set."""
    raw = _every_entry(model)
    p = load_pattern(raw)
    fab, pla = fabric_table(p.fabric), plastic_table(p.plastic)
    given = {k: v for k, v in raw["fabric"].items() if k != "rectangle"}
    assert {k: fab[k] for k in given if k in fab} == given and set(fab) <= set(given)
    assert pla == raw["plastic"]
    again = {**raw, "fabric": {"rectangle": raw["fabric"]["rectangle"], **fab}, "plastic": pla}
    # a pattern file's [print] files live in its folder (geometry.patterns.gcode_path)
    shutil.copy(raw["print"]["gcode"], tmp_path / "two_lines.gcode")
    again["print"] = {**raw["print"], "gcode": "two_lines.gcode"}
    path = tmp_path / "again.toml"
    write_pattern(path, again)
    q = load_pattern(path)
    assert q.fabric == p.fabric and q.plastic == p.plastic
    assert q.fabric.model == model and q.fabric.parameters == p.fabric.parameters
    assert q.outline.equals(p.outline)
    assert [(e.kind, e.label, e.thickness_mm, e.side) for e in q.elements] == \
        [(e.kind, e.label, e.thickness_mm, e.side) for e in p.elements]
    assert {e.kind for e in p.elements} == {"region", "ribbon", "star", "gcode"}
    assert all(a.geometry.equals(b.geometry) for a, b in zip(p.elements, q.elements))
    assert [(s.fix, s.boundary, s.label) for s in q.supports] == [(s.fix, s.boundary, s.label) for s in p.supports]
    for a, b in zip(p.supports, q.supports):
        np.testing.assert_array_equal(a.points, b.points)
        assert (a.position is None) == (b.position is None)
        if a.position is not None:
            np.testing.assert_array_equal(a.position, b.position)
    fields = ("mesh_size", "mesh_across", "seed", "max_iterations", "metric_floor", "coarse_levels",
              "metric_predictor", "contact_exclusion")
    assert [getattr(q, f) for f in fields] == [getattr(p, f) for f in fields] == [2.0, 1.5, 7, 50, 3.0, 2, False, 5.0]
    assert q.raw["meta"] == raw["meta"]


def test_fabric_table_writes_the_model_in_use_and_changed_tables_only():
    default = fabric_table(Fabric())
    assert default["model"] == "neo-hookean" and default["stretch"] == 1.35
    assert not set(default) & set(MEMBRANE_MODELS)            # neo-Hookean has no own parameters
    ortho = fabric_table(Fabric(model="orthotropic"))
    assert ortho["orthotropic"] == Fabric().parameters["orthotropic"] and "orthotropic-stvk" not in ortho
    changed = Fabric(parameters={"orthotropic": {"a1": 0.05}})
    assert fabric_table(changed)["orthotropic"]["a1"] == 0.05
    assert load_pattern({"fabric": {"disk": 10.0, **fabric_table(changed)}}).fabric == changed
    assert plastic_table(Plastic()) == {"young_modulus_mpa": 72.3, "poisson": 0.5, "rest_curvature_per_mm": 0.0}

