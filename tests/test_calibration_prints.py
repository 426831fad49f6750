"""Calibration prints (issue 23): `selfshape calibration-print strips|law`.

The G-code reads back through the project's own reader (geometry.gcode.read_gcode) to the
specimens the template lists (thickness, width, length, orientation, side, position), every
printer setting the files state lies in geometry.schema's physical ranges, and a strip set
filled from the bilayer model with seeded noise calibrates back to the ratio it was filled with.
"""
import csv
import json
import math
import os

import numpy as np
import pytest
import shapely

from geometry.gcode import parse_gcode, read_gcode, read_header
from geometry.schema import PRINTER_NUMBERS
from selfshape.cli import main
from validation.calibration_prints import fill_strips_from_model, layer_height_for, serpentine
from inverse.printer import Printer
from shellfem.errors import SelfshapeError

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def rows_of(path):
    with open(path) as f:
        return list(csv.DictReader(line for line in f if not line.startswith("#")))


def run(argv, capsys):
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def rect(e):
    """(centre (2,), long side, short side, angle of the long side in [0, 180) deg) of an element."""
    r = shapely.minimum_rotated_rectangle(e.geometry)
    c = np.asarray(r.exterior.coords)[:4]
    a, b = c[1] - c[0], c[2] - c[1]
    long_, short = (a, b) if np.linalg.norm(a) >= np.linalg.norm(b) else (b, a)
    ang = math.degrees(math.atan2(long_[1], long_[0])) % 180.0
    return c.mean(axis=0), float(np.linalg.norm(long_)), float(np.linalg.norm(short)), ang


def check_header_ranges(path, printer_layer=None):
    """Every printer setting a file states is inside its geometry.schema range, and every
    extruded segment lies on the bed."""
    h = read_header(path)
    pairs = {"nozzle_diameter_mm": "nozzle_mm", "filament_diameter_mm": "filament_diameter_mm",
             "layer_height_mm": "layer_height_mm", "print_speed_mm_s": "print_speed_mm_s",
             "travel_speed_mm_s": "travel_speed_mm_s", "retract_length_mm": "retraction_mm",
             "retract_speed_mm_s": "retraction_speed_mm_s", "retract_lift_mm": "z_hop_mm",
             "temperature_c": "nozzle_temperature_c", "bed_temperature_c": "bed_temperature_c",
             "extrusion_multiplier": "extrusion_multiplier", "bed_offset_z_mm": "bed_offset_z_mm",
             "mirror_axis_x_mm": "mirror_axis_x"}
    for f, key in pairs.items():
        spec = PRINTER_NUMBERS[key]
        assert spec.lo <= getattr(h, f) <= spec.hi, (f, getattr(h, f))
    seg = parse_gcode(path)
    bx, by = h.bed_shape_mm
    for c in ("x0", "x1"):
        assert seg[c].min() >= 0 and seg[c].max() <= bx
    for c in ("y0", "y1"):
        assert seg[c].min() >= 0 and seg[c].max() <= by
    return h


# ----------------------------------------------------------------------------- strips
def test_serpentine_fills_the_rectangle():
    p, w = serpentine(40.0, 10.0, 0.8)
    assert len(p) == 2 * 12 and w == pytest.approx(10 / 12)
    g = shapely.LineString(p).buffer(w / 2, cap_style="square", join_style="round")
    assert g.bounds == pytest.approx((-20, -5, 20, 5), abs=1e-9)
    corners = 2 * 11 * (1 - math.pi / 4) * (w / 2) ** 2     # only the 11 turns' outer corners are round
    assert g.area == pytest.approx(400.0 - corners, rel=1e-4)


def test_layer_height_is_a_common_divisor_of_the_thicknesses():
    assert layer_height_for([0.3, 0.35, 0.4, 0.45], Printer()) == pytest.approx(0.05)
    assert layer_height_for([0.2, 0.4], Printer()) == pytest.approx(0.2)
    assert layer_height_for([0.2, 0.3], Printer()) == pytest.approx(0.1)
    with pytest.raises(SelfshapeError, match=r"thickness 0\.35 mm is not a whole number of 0\.2 mm layers"):
        layer_height_for([0.2, 0.35], Printer(), 0.2)
    with pytest.raises(SelfshapeError, match="not whole numbers of layers"):
        layer_height_for([0.2, 0.2013], Printer())


def bed_outline(r, origin, axis, side):
    """The cut rectangle of a strips.csv row in raw bed mm, by the flipped-frame convention
    written out here rather than taken from geometry.gcode: front at origin + (x, y); back,
    printed after flipping the frame about the bed line x = axis, at (2 axis - origin_x - x,
    origin_y + y)."""
    a = math.radians(float(r["orientation_deg"]))
    L, W = float(r["length_mm"]), float(r["width_mm"])
    local = np.array([[-L, -W], [L, -W], [L, W], [-L, W]]) / 2 @ np.array([[math.cos(a), math.sin(a)],
                                                                          [-math.sin(a), math.cos(a)]])
    xy = local + [float(r["x_mm"]), float(r["y_mm"])] + origin
    if side == "back":
        xy[:, 0] = 2 * axis - xy[:, 0]
    return shapely.Polygon(xy)


def test_strips_gcode_reads_back_to_the_specimens(tmp_path, capsys):
    """Two stretches (one frame set each), two orientations, both sides, a printer file whose
    flip line (x = 97 mm) is not the origin's x (95 mm), so that a back file printed unflipped
    or flipped about another line cannot land on the template's places: each specimen of
    strips.csv is one printed element of its frame's front or back file, at its position, with
    its thickness, width, length and orientation; the raw bed moves of each file lie in the
    template's rectangles placed by the flipped-frame convention, every one filled."""
    printer = tmp_path / "p.toml"
    printer.write_text("[printer]\nbed_size = [200, 180]\nnozzle_mm = 0.6\nfilament_diameter_mm = 1.75\n"
                       "origin = [95, 88]\nmirror_axis_x = 97\n")
    out = tmp_path / "strips"
    rc, so, err = run(["calibration-print", "strips", "-o", str(out), "--printer", str(printer), "--repetitions", "2",
                       "--thickness", "0.3", "0.45", "--orientation", "0", "30", "--stretch", "1.2", "1.35",
                       "--width", "8", "--length", "30"], capsys)
    assert rc == 0, err
    assert "32 strips on 2 frame(s), layer height 0.05 mm" in so
    rows = rows_of(out / "strips.csv")
    assert len(rows) == 32 and len({r["specimen"] for r in rows}) == 32
    header = list(rows[0])
    assert header[:10] == ["specimen", "side", "stretch", "orientation_deg", "plastic_thickness_mm",
                           "fabric_thickness_mm", "width_mm", "length_mm", "curvature_per_mm", "rest_curvature_per_mm"]
    assert all(r["curvature_per_mm"] == "" and r["rest_curvature_per_mm"] == "" for r in rows)
    assert all(r[c] != "" for r in rows for c in header if c not in ("curvature_per_mm", "rest_curvature_per_mm"))
    summary = json.loads((out / f"{out.name}_summary.json").read_text())
    assert summary["printer"]["nozzle_mm"] == 0.6 and summary["layer_height_mm"] == pytest.approx(0.05)
    seen = 0
    for fr in summary["frames"]:
        mine = [r for r in rows if int(r["frame"]) == fr["frame"]]
        assert {float(r["stretch"]) for r in mine} == {fr["stretch"]}      # one stretch per frame
        assert (out / fr["files"]["map"]).stat().st_size > 10_000
        outlines = {}
        for side, name in fr["files"].items():
            if side == "map":
                continue
            h = check_header_ranges(out / name)
            assert h.side == side and h.layer_height_mm == pytest.approx(0.05) and h.bed_shape_mm == (200, 180)
            assert h.filament_diameter_mm == 1.75 and h.nozzle_diameter_mm == 0.6
            els = read_gcode(out / name)
            want = [r for r in mine if r["side"] == side]
            assert h.origin_mm == (95, 88) and h.mirror_axis_x_mm == 97
            boxes = [bed_outline(r, (95.0, 88.0), 97.0, side) for r in want]
            seg = parse_gcode(out / name)
            lines = shapely.linestrings(np.stack([np.c_[seg["x0"], seg["y0"]], np.c_[seg["x1"], seg["y1"]]], axis=1))
            home = np.array([[b.buffer(0.01).contains(ln) for b in boxes] for ln in lines])
            assert np.all(home.sum(axis=1) == 1)                    # every bead in exactly one template rectangle
            assert np.all(home.any(axis=0))                         # and every rectangle printed
            assert len(els) == len(want) and not els.meta["warnings"]
            for e in els:
                c, L, W, ang = rect(e)
                d = [np.hypot(float(r["x_mm"]) - c[0], float(r["y_mm"]) - c[1]) for r in want]
                r = want[int(np.argmin(d))]
                assert min(d) < 0.01, (name, c)
                assert e.side == side and e.thickness_mm == pytest.approx(float(r["plastic_thickness_mm"]), abs=1e-9)
                assert L == pytest.approx(float(r["length_mm"]), abs=0.01)
                assert W == pytest.approx(float(r["width_mm"]), abs=0.01)
                assert min(abs(ang - float(r["orientation_deg"])), 180 - abs(ang - float(r["orientation_deg"]))) < 0.05
                outlines[r["specimen"]] = e.geometry
                seen += 1
        # front and back specimens sit on different fabric: no two outlines overlap
        geo = list(outlines.values())
        assert sum(g.area for g in geo) == pytest.approx(shapely.union_all(geo).area, rel=1e-9)
    assert seen == 32


def test_strips_round_trip_recovers_the_filled_ratio(tmp_path, capsys):
    """Seed defaults (4 thicknesses 0.3-0.45 mm x 10 strips x 2 sides at stretch 1.35) -> fill
    curvature_per_mm from the strip model at ratio 1800 with 1.5 % seeded noise -> calibrate
    strips gives back 1800 within its 95 % interval and 2 %."""
    out = tmp_path / "strips"
    rc, so, err = run(["calibration-print", "strips", "-o", str(out)], capsys)
    assert rc == 0, err
    assert "80 strips" in so
    rows = rows_of(out / "strips.csv")
    assert {r["plastic_thickness_mm"] for r in rows} == {"0.3", "0.35", "0.4", "0.45"}
    assert {r["stretch"] for r in rows} == {"1.35"} and {r["side"] for r in rows} == {"front", "back"}
    filled = tmp_path / "filled.csv"
    k = fill_strips_from_model(out / "strips.csv", filled, 1800.0, noise=0.015, seed=11)
    assert np.all(k > 0)
    rc, _, err = run(["calibrate", "strips", str(filled), "-o", str(tmp_path / "cal")], capsys)
    assert rc == 0, err
    p = json.loads((tmp_path / "cal" / "parameters.json").read_text())
    ratio, se = p["modulus_ratio"]
    lo, hi = p["confidence_intervals_95"]["modulus_ratio"]
    assert lo <= 1800.0 <= hi and ratio == pytest.approx(1800.0, rel=0.02)
    # the template itself, not filled: one line naming the file, the specimen and the column
    rc, _, err = run(["calibrate", "strips", str(out / "strips.csv"), "-o", str(tmp_path / "cal2")], capsys)
    assert rc == 2 and err.count("\n") == 1
    assert "strips.csv: row 1 (specimen ST-001), column curvature_per_mm: empty" in err


@pytest.mark.parametrize("argv, needle", [
    (["--thickness", "0.35", "--layer-height", "0.2"], "thickness 0.35 mm is not a whole number of 0.2 mm layers"),
    (["--width", "300"], "does not fit the 223 x 223 mm bed"),
    (["--stretch", "7"], "--stretch must be <= 5"),
    (["--sides", "front", "front"], "--sides must be front and/or back (each once)"),
    (["--printer", "{printer}"], "printer.nozzle_mm must be in [0.1, 2] mm, got 5"),
])
def test_strips_bad_options_are_one_line_errors(tmp_path, capsys, argv, needle):
    (tmp_path / "p.toml").write_text("nozzle_mm = 5\n")
    argv = [a.format(printer=tmp_path / "p.toml") for a in argv]
    rc, _, err = run(["calibration-print", "strips", "-o", str(tmp_path / "o")] + argv, capsys)
    assert rc == 2 and err.count("\n") == 1 and needle in err, err
    assert not (tmp_path / "o").exists()                    # checked before anything is written


@pytest.mark.parametrize("argv, needle", [
    # 1.5 mm ribbons in rows 1 mm apart overlap: a plate, not the law's parallel ribbons
    (["--spacing", "1", "3.9"], "--spacing 1 mm: rows of 1.5 mm wide ribbons must be more than their width apart"),
    (["--rows", "40"], "does not fit the 223 x 223 mm bed"),
    (["--thickness", "0.25", "--layer-height", "0.2"], "thickness 0.25 mm is not a whole number of 0.2 mm layers"),
])
def test_law_bad_options_are_one_line_errors(tmp_path, capsys, argv, needle):
    rc, _, err = run(["calibration-print", "law", "-o", str(tmp_path / "o")] + argv, capsys)
    assert rc == 2 and err.count("\n") == 1 and needle in err, err
    assert not (tmp_path / "o").exists()                    # checked before anything is written


# ----------------------------------------------------------------------------- law
def test_law_gcode_reads_back_to_the_patches(tmp_path, capsys):
    """A 2 x 2 grid per side: every dash of every patch is one printed element of the patch's
    side, inside the patch's cut rectangle, 1.5 mm wide, of the patch's thickness; the dash
    count is the simulated patch's (validation.law_tables.patch_pattern)."""
    from validation.law_tables import patch_pattern
    out = tmp_path / "law"
    rc, so, err = run(["calibration-print", "law", "-o", str(out), "--thickness", "0.2", "0.4", "--spacing", "3.9",
                       "6.5", "--stretch", "1.3"], capsys)
    assert rc == 0, err
    rows = rows_of(out / "law_measurements.csv")
    assert len(rows) == 8 and {r["side"] for r in rows} == {"front", "back"}
    assert all(r[c] == "" for r in rows for c in ("kappa_per_mm", "kappa_across_per_mm", "contraction_along",
                                                   "contraction_across"))
    summary = json.loads((out / f"{out.name}_summary.json").read_text())
    for fr in summary["frames"]:
        for side in ("front", "back"):
            if side not in fr["files"]:
                continue
            check_header_ranges(out / fr["files"][side])
            els = read_gcode(out / fr["files"][side], cap="flat")      # a pattern ribbon ends at its path's ends
            mine = [r for r in rows if int(r["frame"]) == fr["frame"] and r["side"] == side]
            boxes = [shapely.box(float(r["x_mm"]) - float(r["patch_length_mm"]) / 2,
                                 float(r["y_mm"]) - float(r["patch_width_mm"]) / 2,
                                 float(r["x_mm"]) + float(r["patch_length_mm"]) / 2,
                                 float(r["y_mm"]) + float(r["patch_width_mm"]) / 2) for r in mine]
            count = [0] * len(mine)
            for e in els:
                k = [i for i, b in enumerate(boxes) if b.buffer(0.01).contains(e.geometry)]
                assert len(k) == 1 and e.side == side
                r = mine[k[0]]
                assert e.thickness_mm == pytest.approx(float(r["thickness_mm"]), abs=1e-9)
                _, L, W, ang = rect(e)
                assert W == pytest.approx(float(r["ribbon_width_mm"]), abs=0.01) and min(ang, 180 - ang) < 0.01
                assert L <= float(r["ribbon_length_mm"]) + 0.002
                count[k[0]] += 1
            for r, n in zip(mine, count):
                raw = patch_pattern(float(r["thickness_mm"]), float(r["spacing_mm"]), side, 1.3,
                                    n_rows=int(r["rows"]), n_motifs=3)
                assert raw["fabric"]["rectangle"] == [float(r["patch_length_mm"]), float(r["patch_width_mm"])]
                assert n == len(raw["ribbon"])


@pytest.mark.parametrize("stretch, grid, rows_json", [
    ("1.3", (["0.2", "0.3", "0.4"], ["3.9", "6.5"]), "thickness_law_s1.3_sim_rows.json"),
    ("1.6", (["0.2", "0.25", "0.3", "0.35", "0.4"], ["3.9", "6.5"]), "thickness_law_s1.6_rows.json"),
    ("1.1", (["0.2", "0.3", "0.4", "0.5"], ["3.9", "6.5"]), "thickness_law_s1.1_sim_rows.json"),
    ("1.05", (["0.2", "0.3", "0.4", "0.5"], ["3.9", "6.5"]), "thickness_law_s1.05_sim_rows.json"),
])
def test_law_from_rows_then_build_is_the_shipped_law(tmp_path, capsys, stretch, grid, rows_json):
    """The shipped laws were built from these rows JSONs (front rows, back = front): the
    template filled from them and built is the shipped table, row for row, with its stretch
    and plastic keys; the designer loads and inverts it."""
    from inverse.thickness_law import load_thickness_law, thickness_for_curvature
    out = tmp_path / "law"
    rc, so, err = run(["calibration-print", "law", "-o", str(out), "--stretch", stretch, "--thickness", *grid[0],
                       "--spacing", *grid[1], "--from-rows", os.path.join(ROOT, "inverse", "data", rows_json),
                       "--mirror-back", "--calibration",
                       os.path.join(ROOT, "inverse", "data", "strips_S1_calibration.json")], capsys)
    assert rc == 0, err
    law_csv = tmp_path / "law.csv"
    rc, so, err = run(["law", "build", str(out / "law_measurements.csv"), "-o", str(law_csv)], capsys)
    assert rc == 0, err
    mine, shipped = load_thickness_law(law_csv), load_thickness_law(os.path.join(ROOT, "inverse", "data",
                                                                                 f"thickness_law_s{stretch}.csv"))
    assert mine.stretch == shipped.stretch == float(stretch)
    assert mine.plastic_young_modulus_mpa == shipped.plastic_young_modulus_mpa
    for side in ("front", "back"):
        a, b = mine.table(side), shipped.table(side)
        np.testing.assert_array_equal(a.thickness, b.thickness)
        np.testing.assert_array_equal(a.spacing, b.spacing)
        np.testing.assert_allclose(a.kappa, b.kappa, rtol=1e-5)
    assert any("law_measurements.csv" in ln for ln in mine.provenance)
    assert any(rows_json in ln for ln in mine.provenance)
    t, _ = thickness_for_curvature(mine, [0.1, 0.15], [4.0, 6.0], "front", 0.05)
    assert np.all((t >= 0.2) & (t <= 0.4))
    # the designer takes it (design --law): at its stretch, and refuses it at another
    from geometry.target import cylinder_patch
    from inverse.design import design
    V, F = cylinder_patch()
    d = design(V, F, diagonal_mm=None, edge_mm=None, thickness_law=str(law_csv), stretch=float(stretch))
    assert d.ribbons and all(0.2 <= r.thickness_mm <= 0.4 for r in d.ribbons)
    with pytest.raises(SelfshapeError, match=f"the law was made at fabric stretch {stretch}"):
        design(V, F, diagonal_mm=None, edge_mm=None, thickness_law=str(law_csv), stretch=1.45)


def test_law_simulate_one_patch_is_the_shipped_cell(tmp_path, capsys):
    """--simulate runs the project's patch simulation (validation.law_tables.simulate_row) on
    the printed patch: at the shipped s = 1.6 law's settings (3 rows x 2 motifs, mesh 3 mm, 1
    triangle row across a ribbon, the strips_S1 plastic) the 0.3 mm / 3.9 mm cell is the shipped
    table's, and the contraction columns are filled. One cell is too sparse to build a law: said
    in one line naming the file."""
    from inverse.thickness_law import curvature, load_thickness_law
    out = tmp_path / "sim"
    rc, so, err = run(["calibration-print", "law", "-o", str(out), "--stretch", "1.6", "--thickness", "0.3",
                       "--spacing", "3.9", "--sides", "front", "--rows", "3", "--motifs", "2", "--simulate",
                       "--mesh-size", "3", "--across", "1", "--max-iterations", "1000"], capsys)
    assert rc == 0, err
    (r,) = rows_of(out / "law_measurements.csv")
    shipped = float(curvature(load_thickness_law(), 0.3, 3.9, "front"))
    assert float(r["kappa_per_mm"]) == pytest.approx(shipped, rel=1e-4)
    assert 1.0 < float(r["contraction_along"]) < 1.6 and 1.0 < float(r["contraction_across"]) < 1.6
    assert abs(float(r["kappa_across_per_mm"])) < float(r["kappa_per_mm"])
    text = (out / "law_measurements.csv").read_text()
    modulus = load_thickness_law().plastic_young_modulus_mpa          # the shipped law's plastic
    assert f"# plastic_young_modulus_mpa = {modulus:g}" in text and "filled by simulation" in text
    # the simulated rows refill the template without simulating (--from-rows)
    again = tmp_path / "again"
    rc, _, err = run(["calibration-print", "law", "-o", str(again), "--stretch", "1.6", "--thickness", "0.3",
                      "--spacing", "3.9", "--sides", "front", "--rows", "3", "--motifs", "2",
                      "--from-rows", str(out / "law_sim_rows.json")], capsys)
    assert rc == 0, err
    (r2,) = rows_of(again / "law_measurements.csv")
    assert {k: r2[k] for k in r2 if k != "note"} == {k: r[k] for k in r if k != "note"}
    rc, _, err = run(["law", "build", str(out / "law_measurements.csv"), "-o", str(tmp_path / "law.csv")], capsys)
    assert rc == 2 and err.count("\n") == 1
    assert "law_measurements.csv: cannot build a law: side front: 1 thickness(es) x 1 spacing(s), too sparse" in err
    assert not (tmp_path / "law.csv").exists()


@pytest.mark.slow
def test_law_simulate_grid_then_build_matches_the_shipped_law(tmp_path, capsys):
    """The in-silico law by the lab's command: a 2 x 2 grid simulated at the shipped s = 1.6
    settings (3-row patches), back mirrored, built: within 3 % of the shipped table (whose
    mu2 6.5 mm / 0.3 mm cell came from a 112.5 mm patch), then `design --law` takes it."""
    from inverse.thickness_law import curvature, load_thickness_law
    out = tmp_path / "sim"
    rc, so, err = run(["calibration-print", "law", "-o", str(out), "--stretch", "1.6", "--thickness", "0.2", "0.3",
                       "--spacing", "3.9", "6.5", "--rows", "3", "--motifs", "2", "--simulate", "--mirror-back",
                       "--mesh-size", "3", "--across", "1", "--max-iterations", "1000"], capsys)
    assert rc == 0, err
    law_csv = tmp_path / "law.csv"
    assert run(["law", "build", str(out / "law_measurements.csv"), "-o", str(law_csv)], capsys)[0] == 0
    mine, shipped = load_thickness_law(law_csv), load_thickness_law()
    for side in ("front", "back"):
        t = mine.table(side)
        T, S = np.meshgrid(t.thickness, t.spacing, indexing="ij")
        np.testing.assert_allclose(t.kappa, curvature(shipped, T, S, side), rtol=0.03)
    from geometry.target import cylinder_patch
    V, F = cylinder_patch(n_arc=16, n_len=12)
    obj = tmp_path / "cyl.obj"
    obj.write_text("".join(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in V)
                   + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F))
    rc, _, err = run(["design", str(obj), "-o", str(tmp_path / "design"), "--law", str(law_csv)], capsys)
    assert rc == 0, err
    assert json.loads((tmp_path / "design" / "report.json").read_text())["thickness_law"] == str(law_csv)


def test_layout_keeps_specimens_apart_and_on_the_bed():
    """The default law grid (96 patches of six sizes, first-fit decreasing-height shelves): on
    every frame the cut outlines are >= the gap apart and inside the bed less its margins; ids
    are unique and numbered in frame order."""
    from validation.calibration_prints import GAP_MM, MARGIN_MM, layout, patch_specimens
    sps = patch_specimens()
    frames = layout(sps, (223.0, 223.0), "LP")
    assert sum(len(f[2]) for f in frames) == 96 and len({sp.id for sp in sps}) == 96
    assert len(frames) <= 22
    k = 0
    for frame, s, fs in frames:
        boxes = [shapely.Polygon(sp.outline + np.asarray(sp.centre)) for sp in fs]
        for i in range(len(boxes)):
            for j in range(i):
                assert boxes[i].distance(boxes[j]) >= GAP_MM - 1e-9
        lo = np.min([b.bounds[:2] for b in boxes], axis=0)
        hi = np.max([b.bounds[2:] for b in boxes], axis=0)
        assert np.all(hi - lo <= 223.0 - 2 * MARGIN_MM + 1e-9) and np.allclose(lo + hi, 0.0)
        for sp in fs:
            k += 1
            assert sp.frame == frame and sp.id == f"LP-{k:03d}"


def test_outputs_are_checked_first_replaced_by_kind_and_removed_on_failure(tmp_path, capsys, monkeypatch):
    """-o a file: one line, exit 2. A strips and a law print share a folder; a rerun with fewer
    frames removes its own stale frame files only. A failure half-way (here the second G-code
    file) leaves none of the run's files (shellfem.outfiles.OutputDir)."""
    (tmp_path / "f").write_text("x")
    rc, _, err = run(["calibration-print", "strips", "-o", str(tmp_path / "f")], capsys)
    assert rc == 2 and err.count("\n") == 1 and "the output must be a folder" in err
    out = tmp_path / "both"
    assert run(["calibration-print", "strips", "-o", str(out), "--repetitions", "6"], capsys)[0] == 0   # 2 frames
    assert (out / "strips_frame02_back.gcode").exists()
    law = ["calibration-print", "law", "-o", str(out), "--thickness", "0.2", "0.4", "--spacing", "3.9", "6.5"]
    assert run(law, capsys)[0] == 0
    assert run(["calibration-print", "strips", "-o", str(out), "--repetitions", "2"], capsys)[0] == 0   # 1 frame
    names = set(os.listdir(out))
    assert "strips_frame02_back.gcode" not in names and "strips_frame01_front.gcode" in names
    assert {"law_measurements.csv", "law_summary.json", "law_frame01_front.gcode", "strips.csv"} <= names
    import inverse.gcode
    real, calls = inverse.gcode.write_gcode, []

    def failing(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **k)
    monkeypatch.setattr(inverse.gcode, "write_gcode", failing)
    fresh = tmp_path / "fresh"
    rc, _, err = run(["calibration-print", "strips", "-o", str(fresh), "--repetitions", "2"], capsys)
    assert rc == 130 and not fresh.exists()


def test_shuffle_is_seeded_and_only_reorders():
    from validation.calibration_prints import layout, strip_specimens

    def placed(seed):
        sps = strip_specimens(repetitions=3)
        layout(sps, (223.0, 223.0), "ST", shuffle=seed)
        return [(sp.id, sp.side, sp.thickness_mm, sp.centre) for sp in sorted(sps, key=lambda sp: sp.id)]
    a, b, c = placed(None), placed(7), placed(7)
    assert b == c and a != b
    assert [x[3] for x in a] == [x[3] for x in b]                  # the same places, other specimens on them
    assert sorted((x[1], x[2]) for x in a) == sorted((x[1], x[2]) for x in b)


def test_a_simulation_that_does_not_converge_leaves_its_cell_empty(tmp_path, capsys, monkeypatch):
    """--simulate never writes a value it did not converge to: the cell stays empty with a note
    (kappa null in law_sim_rows.json), and law build names the patch, the column and why."""
    import validation.law_tables as lt

    def fake(t, mu, side, stretch, **kw):
        ok = not (t == 0.4 and mu == 6.5)
        return {"thickness_mm": t, "spacing_mm": mu, "side": side, "kappa_per_mm": 0.1 / t if ok else float("nan"),
                "converged": ok, "reason": "converged" if ok else "iteration limit", "newton_iterations": 7,
                "n_triangles": 10, "time_s": 0.0, "kappa_across_per_mm": 0.001, "k1_angle_deg": 0.5,
                "sigma_along": 1.2, "sigma_across": 1.4}
    monkeypatch.setattr(lt, "simulate_row", fake)
    out = tmp_path / "sim"
    rc, so, err = run(["calibration-print", "law", "-o", str(out), "--thickness", "0.2", "0.4", "--spacing", "3.9",
                       "6.5", "--simulate", "--mirror-back"], capsys)
    assert rc == 0, err
    assert "4 simulated, 1 not converged, 4 mirrored" in so
    rows = {(r["side"], r["thickness_mm"], r["spacing_mm"]): r for r in rows_of(out / "law_measurements.csv")}
    bad = rows[("front", "0.4", "6.5")]
    assert bad["kappa_per_mm"] == "" and "simulation not converged (iteration limit" in bad["note"]
    assert rows[("back", "0.4", "6.5")]["kappa_per_mm"] == "" and rows[("front", "0.2", "3.9")]["kappa_per_mm"] == "0.5"
    sim = json.loads((out / "law_sim_rows.json").read_text())["rows"]
    assert sum(r["kappa_per_mm"] is None for r in sim) == 1 and len(sim) == 4
    rc, _, err = run(["law", "build", str(out / "law_measurements.csv"), "-o", str(tmp_path / "l.csv")], capsys)
    assert rc == 2 and err.count("\n") == 1
    assert f"patch {bad['patch']}, column kappa_per_mm: empty (simulation not converged" in err
    # refilled from its rows: the same empty cell, said so
    rc, so, err = run(["calibration-print", "law", "-o", str(tmp_path / "again"), "--thickness", "0.2", "0.4",
                       "--spacing", "3.9", "6.5", "--from-rows", str(out / "law_sim_rows.json"), "--mirror-back"],
                      capsys)
    assert rc == 0, err
    assert "1 missing" in so
    again = {(r["side"], r["thickness_mm"], r["spacing_mm"]): r
             for r in rows_of(tmp_path / "again" / "law_measurements.csv")}
    cell = again[("front", "0.4", "6.5")]
    assert cell["kappa_per_mm"] == "" and "did not converge" in cell["note"]
    # a rows JSON with two rows for one cell is refused, naming the row
    dup = {"rows": sim + sim[:1]}
    (tmp_path / "dup.json").write_text(json.dumps(dup))
    rc, _, err = run(["calibration-print", "law", "-o", str(tmp_path / "dup"), "--from-rows",
                      str(tmp_path / "dup.json")], capsys)
    assert rc == 2 and "dup.json: rows[4]: a second row for thickness" in err and not (tmp_path / "dup").exists()


def test_replicates_are_simulated_once(tmp_path, capsys, monkeypatch):
    import validation.law_tables as lt
    calls = []

    def fake(t, mu, side, stretch, **kw):
        calls.append((t, mu, side))
        return {"thickness_mm": t, "spacing_mm": mu, "side": side, "kappa_per_mm": 0.1 / t, "converged": True,
                "reason": "converged", "newton_iterations": 7, "n_triangles": 10, "time_s": 0.0}
    monkeypatch.setattr(lt, "simulate_row", fake)
    out = tmp_path / "sim"
    rc, so, err = run(["calibration-print", "law", "-o", str(out), "--thickness", "0.2", "0.4", "--spacing", "3.9",
                       "6.5", "--repetitions", "2", "--simulate"], capsys)
    assert rc == 0, err
    assert len(calls) == len(set(calls)) == 8 and "16 patches" in so
    assert len({r["patch"] for r in rows_of(out / "law_measurements.csv")}) == 16


def test_contraction_columns_are_printed_over_deployed_length():
    """validation.law_tables.curvature_state's sigma_along / sigma_across (the template's
    contraction columns from a simulation): a flat sheet shrunk to 0.8 along x and 0.9 along y
    has 1.25 and 1/0.9; rolled isometrically, 1 and 1."""
    from types import SimpleNamespace

    from geometry.target import grid_triangles
    from shellfem.model import ShellModel
    from shellfem.sheet import Sheet
    from validation.law_tables import curvature_state
    X, Y = np.meshgrid(np.linspace(0, 60, 31), np.linspace(0, 24, 13), indexing="ij")
    P = np.column_stack([X.ravel(), Y.ravel()])
    sheet = Sheet(P, grid_triangles(30, 12))
    model = ShellModel.homogeneous(sheet, 1.0, 0.3, 0.5)

    def state(pos):
        q = np.concatenate([pos.ravel(), np.zeros(model.n_dofs - pos.size)])
        return curvature_state(SimpleNamespace(sheet=sheet, model=model, result=SimpleNamespace(q=q)), (15, 6, 45, 18))
    s = state(np.column_stack([0.8 * P[:, 0], 0.9 * P[:, 1], np.zeros(len(P))]))
    assert s["sigma_along"] == pytest.approx(1.25, rel=1e-9) and s["sigma_across"] == pytest.approx(1 / 0.9, rel=1e-9)
    R = 20.0
    s = state(np.column_stack([R * np.sin(P[:, 0] / R), P[:, 1], R * (1 - np.cos(P[:, 0] / R))]))
    assert s["sigma_along"] == pytest.approx(1.0, rel=2e-3) and s["sigma_across"] == pytest.approx(1.0, rel=1e-9)


@pytest.mark.parametrize("edit, needle", [
    ({"sigma_along": "x"}, "rows[0], sigma_along: must be a number (or null), got 'x'"),
    ({"rows": "abc"}, "rows[0], rows: must be an integer >= 1 (or null), got 'abc'"),
    ({"k1_angle_deg": "abc"}, "rows[0], k1_angle_deg: must be a number (or null)"),
    ({"kappa_per_mm": -0.1}, "rows[0], kappa_per_mm: must be >= 0, got -0.1"),
    ({"kappa_across_per_mm": float("inf")}, "rows[0], kappa_across_per_mm: must be finite"),
    ({"side": "top"}, "rows[0], side: must be \"front\" or \"back\", got 'top'"),
    ({"converged": "yes"}, "rows[0], converged: must be true or false, got 'yes'"),
    ({"thickness_mm": 0}, "rows[0], thickness_mm: must be > 0"),
])
def test_a_bad_rows_json_is_one_line_naming_the_row_and_key(tmp_path, capsys, edit, needle):
    """--from-rows copies a rows JSON's values into the template: every field it reads is
    checked first (a string where a number belongs was an internal error, exit 3; a negative or
    infinite curvature went into the template, the infinite one as an empty cell)."""
    row = {"thickness_mm": 0.2, "spacing_mm": 3.9, "side": "front", "kappa_per_mm": 0.3, "converged": True,
           "sigma_along": 1.2, "rows": 3, "motifs": 2} | edit
    (tmp_path / "rows.json").write_text(json.dumps({"rows": [row]}))
    rc, _, err = run(["calibration-print", "law", "-o", str(tmp_path / "o"), "--thickness", "0.2", "--spacing", "3.9",
                      "--sides", "front", "--from-rows", str(tmp_path / "rows.json")], capsys)
    assert rc == 2 and err.count("\n") == 1 and f"rows.json: {needle}" in err, err
    assert not (tmp_path / "o").exists()
