"""G-code reader (geometry.gcode) and bead geometry (geometry.beads): dialects, bead widths,
retractions, errors, speed.

The files in tests/data/gcode were designed by hand (see their README): every count and
width asserted here is the one put into the file.
"""
import json
import math
import os
import time

import numpy as np
import pytest
import shapely

from geometry.elements import Ribbon
from geometry.beads import bead_area, stack_beads
from geometry.gcode import parse_gcode, read_gcode
from inverse.gcode import write_gcode
from inverse.printer import Printer
from shellfem.errors import SelfshapeError

DATA = os.path.join(os.path.dirname(__file__), "data", "gcode")


def data(name):
    return os.path.join(DATA, name)


def fil(d):
    return math.pi * d * d / 4


def e_of(w, h, length, d):
    return bead_area(w, h) * length / fil(d)


def bead(path, w, cap="square"):
    return shapely.buffer(shapely.LineString(path), w / 2, cap_style=cap, join_style="round", quad_segs=8)


def write(tmp_path, text, name="t.gcode"):
    p = tmp_path / name
    p.write_text(text)
    return p


# ---------------------------------------------------------------- dialects

def test_prusaslicer_relative_e_with_hints():
    f = data("prusa_relative.gcode")
    seg = parse_gcode(f)
    els = read_gcode(f)
    m = els.meta
    assert (len(seg), m["n_paths"], m["n_layers"]) == (12, 4, 2)
    assert m["layer_z_mm"] == [0.2, 0.4] and m["e_mode"] == "relative" and m["units"] == "mm"
    assert (m["filament_diameter_mm"], m["filament_diameter_source"]) == (1.75, "file comment")
    assert np.all(seg["height_hint"][2:] == 0.2) and np.isnan(seg["height_hint"][:2]).all()  # intro line before ;HEIGHT:
    assert sorted(set(seg["width_hint"][2:])) == [0.45, 0.5]
    assert m["width_hint_vs_volume_max_rel"] < 1e-4         # E was written with the same bead model
    assert m["types"] == ["Custom", "External perimeter", "Solid infill"]
    # intro line (1 element), square loop printed twice (0.4 mm), infill line (0.2 mm)
    assert [round(e.thickness_mm, 9) for e in els] == [0.2, 0.4, 0.2]
    square = [(100, 100), (120, 100), (120, 120), (100, 120), (100, 100)]
    assert els[1].geometry.area == pytest.approx(bead(square, 0.45).area, rel=1e-6)
    assert els[2].geometry.area == pytest.approx(0.5 * (20 + 0.5), rel=1e-6)
    assert els[0].label == "prusa_relative.gcode path 0" and els[1].label == "prusa_relative.gcode paths 1, 3"
    # deposit: intro 9 + 12.5, two square loops, one line; retractions and wipes deposit nothing
    want = 9.0 + 12.5 + 2 * e_of(0.45, 0.2, 80, 1.75) + e_of(0.5, 0.2, 20, 1.75)
    assert m["extruded_filament_mm"] == pytest.approx(want, abs=1e-4)
    assert m["n_retractions"] == 6 and m["stationary_extrusion_mm"] == 0.0
    no_intro = read_gcode(f, exclude_types=("Custom",))         # the intro line is ;TYPE:Custom
    assert [round(e.thickness_mm, 9) for e in no_intro] == [0.4, 0.2]
    assert no_intro.meta["excluded_segments"] == 2


def test_cura_absolute_e_without_width_hints():
    f = data("cura_absolute.gcode")
    seg = parse_gcode(f)
    els = read_gcode(f)
    m = els.meta
    assert (len(seg), m["n_paths"], m["n_layers"]) == (7, 3, 2)
    assert m["layer_z_mm"] == [0.3, 0.5] and m["e_mode"] == "absolute" and m["layer_change_hints"] == 2
    assert (m["filament_diameter_mm"], m["filament_diameter_source"]) == (2.85, "file comment")   # ;SETTING_3
    assert m["width_source"] == "volume"
    # first layer 0.3 mm thick (z from the bed), second 0.2 mm (z step)
    assert m["path_widths_mm"] == pytest.approx([0.8, 1.0, 0.8], abs=1e-4)
    assert m["stationary_extrusion_mm"] == pytest.approx(3.0)     # the prime blob is not a path
    assert [round(e.thickness_mm, 9) for e in els] == [0.5, 0.3]
    assert els[0].geometry.area == pytest.approx(0.8 * 30.8, rel=1e-4)      # E has 5 decimals
    zigzag = [(50, 60), (80, 60), (80, 62), (50, 62)]
    assert els[1].geometry.area == pytest.approx(bead(zigzag, 1.0).area, rel=1e-4)
    want = e_of(0.8, 0.3, 30, 2.85) + e_of(1.0, 0.3, 62, 2.85) + e_of(0.8, 0.2, 30, 2.85)
    assert m["extruded_filament_mm"] == pytest.approx(want, abs=1e-4)


def test_simplify3d_plain_stacks_into_constant_thickness_pieces():
    f = data("s3d_plain.gcode")
    els = read_gcode(f)
    m = els.meta
    assert (m["n_segments"], m["n_paths"], m["n_layers"]) == (5, 2, 2)
    assert m["layer_z_mm"] == [0.25, 0.5] and m["layer_change_hints"] == 0 and m["types"] == []
    assert m["filament_diameter_mm"] == 1.75 and m["layer_height_setting_mm"] == 0.25
    assert m["path_widths_mm"] == pytest.approx([0.48, 0.40], abs=2e-4)     # E has 4 decimals
    # the 0.40 mm line of layer 2 lies on the 0.48 mm ring of layer 1
    ring = bead([(40, 40), (50, 40), (50, 45), (40, 45), (40, 40)], 0.48)
    line = bead([(42, 40), (48, 40)], 0.40)
    by_t = {round(e.thickness_mm, 9): e.geometry for e in els}
    assert sorted(by_t) == [0.25, 0.5]
    assert by_t[0.5].area == pytest.approx(line.area, rel=1e-3)
    assert by_t[0.25].area == pytest.approx(ring.area - line.area, rel=1e-3)


def test_plain_marlin_arcs_units_relative_moves_firmware_retraction():
    f = data("plain_marlin.gcode")
    els = read_gcode(f)
    m = els.meta
    assert (m["n_paths"], m["n_layers"], m["n_arcs"], m["n_firmware_retractions"]) == (3, 1, 2, 3)
    assert m["units"] == "inch+mm" and m["slicer"] is None
    assert m["filament_diameter_source"] == "default" and "assuming 1.75 mm" in m["warnings"][0]
    assert m["path_widths_mm"] == pytest.approx([0.8, 0.6, 1.0], rel=2e-4)   # chords shorten arcs by ~1e-4
    arc = np.column_stack([40 + 10 * np.sin(np.linspace(0, math.pi / 2, 200)),
                           30 - 10 * np.cos(np.linspace(0, math.pi / 2, 200))])
    p0 = bead(np.vstack([[20, 20], arc]), 0.8)
    p1 = bead([(20, 50), (30, 50), (30, 60)], 0.6)           # the G91 relative moves
    ring_area = math.pi * (5.5 ** 2 - 4.5 ** 2)               # full G2 circle given in inches
    got = [e.geometry for e in els]
    assert got[0].symmetric_difference(p0).area < 2e-3 * p0.area
    assert got[1].symmetric_difference(p1).area < 1e-4 * p1.area
    assert got[2].area == pytest.approx(ring_area, rel=1e-3) and len(got[2].interiors) == 1
    assert got[2].centroid.distance(shapely.Point(65, 40)) < 1e-3
    assert read_gcode(f, filament_diameter_mm=2.85).meta["path_widths_mm"][1] == pytest.approx(
        (0.6 - 0.2 * (1 - math.pi / 4)) * (2.85 / 1.75) ** 2 + 0.2 * (1 - math.pi / 4), rel=1e-5)


# ---------------------------------------------------------------- widths and E modes

@pytest.mark.parametrize("w, h, d", [(0.45, 0.2, 1.75), (0.8, 0.3, 2.85), (1.5, 0.2, 2.85), (2.0, 0.25, 1.75)])
def test_width_from_e_is_exact_for_the_bead_model(tmp_path, w, h, d):
    e1, e2 = e_of(w, h, 10.0, d), e_of(w, h, math.hypot(3, 4), d)
    f = write(tmp_path, f"M83\nG1 Z{h!r}\nG1 X10 E{e1!r}\nG1 X13 Y4 E{e2!r}\n")
    els = read_gcode(f, filament_diameter_mm=d)
    assert els.meta["path_widths_mm"] == pytest.approx([w], rel=1e-12)
    assert els[0].thickness_mm == pytest.approx(h, rel=1e-12)


def test_relative_and_absolute_e_give_the_same_deposit(tmp_path):
    moves = [(10, 0, 0.5), (10, 10, 0.7), (None, None, -2.0), (None, None, 2.0), (20, 10, 0.3), (25, 10, -0.5),
             (None, None, 0.5), (25, 20, 0.6)]
    rel, ab, e = ["M83", "G1 Z0.2"], ["M82", "G1 Z0.2", "G92 E0"], 0.0
    for x, y, de in moves:
        e += de
        xy = "" if x is None else f"X{x} Y{y} "
        rel.append(f"G1 {xy}E{de}")
        ab.append(f"G1 {xy}E{e:.5f}")
    s_rel = parse_gcode(write(tmp_path, "\n".join(rel), "rel.gcode"))
    s_abs = parse_gcode(write(tmp_path, "\n".join(ab), "abs.gcode"))
    for k in ("x0", "y0", "x1", "y1", "e_mm", "path"):
        assert np.allclose(s_rel[k], s_abs[k])
    assert s_rel["e_mm"].sum() == pytest.approx(0.5 + 0.7 + 0.3 + 0.6)
    # writer output in both modes reads back identically
    rib = [Ribbon(path=np.array([[0.0, 0.0], [10.0, 3.0], [20.0, 0.0]]) + [0, 8 * k], width_mm=1.2,
                  thickness_mm=0.2 * (k + 1)) for k in range(3)]
    a = read_gcode(write_gcode_path(tmp_path, rib, True))
    b = read_gcode(write_gcode_path(tmp_path, rib, False))
    assert [e.thickness_mm for e in a] == [e.thickness_mm for e in b]
    assert all(x.geometry.symmetric_difference(y.geometry).area < 1e-6 for x, y in zip(a, b))


def write_gcode_path(tmp_path, rib, relative):
    p = tmp_path / f"w{int(relative)}.gcode"
    write_gcode(rib, p, Printer(relative_e=relative))
    return p


def test_retraction_and_unretraction_are_not_extrusion(tmp_path):
    text = "\n".join([
        "M83", "G1 Z0.2",
        "G1 X10 E1",            # path 0
        "G1 E-2", "G1 E2",      # retract in place and restore: no deposit, breaks the path
        "G1 X20 E1",            # path 1
        "G1 X25 E-0.5",         # wipe: moving while retracting deposits nothing
        "G1 E0.8",              # unretract 0.5 + 0.3 extra prime (stationary)
        "G10", "G1 X30 E1", "G11",   # firmware retraction leaves E alone: path 2
        "G1 E-1", "G0 X40", "G1 X50 E1.5",   # travel, then the first 1 mm only restores the retraction
    ])
    seg = parse_gcode(write(tmp_path, text))
    assert seg["e_mm"].tolist() == pytest.approx([1.0, 1.0, 1.0, 0.5])
    assert seg["path"].tolist() == [0, 1, 2, 3]


def test_stack_beads_overlay():
    a = bead([(0, 0), (10, 0)], 1.0)
    b = bead([(5, -5), (5, 5)], 1.0)
    pieces = stack_beads(np.array([a, a, b]), np.array([0, 1, 1]), np.array([0.2, 0.2, 0.2]))
    # layer 0: a; layer 1: a again and b across it. a is 0.4 mm everywhere (the crossing is
    # covered by layers 0 and 1 only); b's two arms outside a are 0.2 mm.
    arm = (b.area - a.intersection(b).area) / 2
    got = sorted((round(th, 9), round(g.area, 9)) for g, th in pieces)
    assert got == sorted([(0.2, round(arm, 9)), (0.2, round(arm, 9)), (0.4, round(a.area, 9))])


# ---------------------------------------------------------------- errors

@pytest.mark.parametrize("text, where, word", [
    ("G1 X10 Y10\nG0 X0\n", "line 2", "no extruding move"),
    ("G21\nG70\nG1 X10 E1\n", "line 2", "unknown units"),
    ("M83\nG1 Xabc E1\n", "line 2", "malformed parameters"),
    ("M83\nG1 X E1\n", "line 2", "has no value"),
    ("M83\nG5 I1 J1 P1 Q1 X3 Y3 E1\n", "line 2", "spline"),
    ("M83\nG18\nG2 X10 I5 E1\n", "line 3", "plane"),
    ("M83\nG1 Z0.2\nG2 X10 Y0 R2 E1\n", "line 3", "radius"),
    ("M83\nG1 Z0.2\nG1 X10 Z0.4 E1\n", "line 3", "changes Z"),
    ("M83\nG1 Z0.2\nhello world\n", "line 3", "not a G-code command"),
    ("M83\nX10 Y10 E1\n", "line 2", "without a command word"),
    ("M83\n;WIDTH:wide\nG1 X10 E1\n", "line 2", "WIDTH"),
    ("M83\nG1 X10 E1\n", "line 2", "not above the fabric"),
    ("M83\n;HEIGHT:0.4\nG1 Z-5\nG0 X1 Y1\nG1 X10 E1\n", "line 5", "z = -5 mm is not above the fabric"),
    # E1e12 on a 30 mm move: a 1e11 mm bead on a fabric to match, exit 0 (issue 19)
    ("M83\nG1 Z0.4\nG0 X10 Y10\nG1 X40 Y10 E1e12\n", "line 4", "deposits a bead 2.004e+11 mm wide"),
    ("M83\n;WIDTH:1.5\nG1 Z0.4\nG0 X10 Y10\nG1 X40 Y10 E1e12\n", "line 5", "deposits a bead 2.004e+11 mm wide"),
])
def test_errors_are_one_line_with_file_and_line(tmp_path, text, where, word):
    f = write(tmp_path, text, "bad.gcode")
    with pytest.raises(SelfshapeError) as e:
        read_gcode(f)
    msg = str(e.value)
    assert msg.startswith("bad.gcode: " + where + ":") and word in msg and "\n" not in msg


def test_unreadable_files(tmp_path):
    with pytest.raises(SelfshapeError, match="missing.gcode: file not found"):
        read_gcode(tmp_path / "missing.gcode")
    os.mkfifo(tmp_path / "pipe.gcode")
    with pytest.raises(SelfshapeError, match="pipe.gcode: is a named pipe"):
        read_gcode(tmp_path / "pipe.gcode")
    (tmp_path / "b.bgcode").write_bytes(b"GCDE\x01\x00\x00\x00" + bytes(50))
    with pytest.raises(SelfshapeError, match=r"b.bgcode: line 1: binary G-code"):
        read_gcode(tmp_path / "b.bgcode")
    (tmp_path / "z.gcode").write_bytes(b"G1 X1\x00\x00\x00")
    with pytest.raises(SelfshapeError, match="not a text G-code"):
        read_gcode(tmp_path / "z.gcode")
    with pytest.raises(SelfshapeError, match="cap"):
        read_gcode(data("s3d_plain.gcode"), cap="butt")
    with pytest.raises(SelfshapeError, match="mirror_axis_x must be a finite number"):
        read_gcode(data("s3d_plain.gcode"), side="back", mirror_axis_x="middle")


def test_a_byte_order_mark_is_not_a_command(tmp_path):
    """G-code saved by a Windows editor starts with a BOM: "line 1: not a G-code command"
    before (issue 19); it reads as the same file without it."""
    text = open(data("plain_marlin.gcode"), "rb").read()
    (tmp_path / "bom.gcode").write_bytes(b"\xef\xbb\xbf" + text)
    a, b = read_gcode(data("plain_marlin.gcode")), read_gcode(tmp_path / "bom.gcode")
    assert len(a) == len(b) and all(x.geometry.equals(y.geometry) for x, y in zip(a, b))


def test_thin_paths_are_dropped_and_caps_follow_the_option(tmp_path):
    w_ok, w_thin = 1.0, 0.05           # the thin one: ooze below min_width_mm = 0.1
    text = "\n".join(["M83", "G1 Z0.2", f"G1 X10 E{e_of(w_ok, 0.2, 10, 1.75)!r}", "G1 E-1", "G0 X20 Y5",
                      "G1 E1", f"G1 X30 E{e_of(w_thin, 0.2, 10, 1.75)!r}"])
    f = write(tmp_path, text)
    els = read_gcode(f)
    assert len(els) == 1 and els.meta["dropped_thin_paths"] == 1
    assert els.meta["path_widths_mm"] == pytest.approx([w_ok, w_thin])
    square, round_, flat = (read_gcode(f, cap=c)[0].geometry.area for c in ("square", "round", "flat"))
    assert square == pytest.approx(w_ok * (10 + w_ok))
    assert flat == pytest.approx(w_ok * 10)
    assert round_ == pytest.approx(w_ok * 10 + math.pi * w_ok ** 2 / 4, rel=1e-2)


# ---------------------------------------------------------------- speed

def big_file(path):
    """A writer-made file of about 40k lines: 1290 wavy ribbons, 1-2 layers."""
    t = np.linspace(0, 1, 12)
    rib = [Ribbon(path=np.column_stack([7.0 * i + 5 * t, 4.0 * j + 0.8 * np.sin(6 * t)]), width_mm=1.5,
                  thickness_mm=0.4 if (i + j) % 3 else 0.2) for i in range(30) for j in range(43)]
    write_gcode(rib, path)
    return rib


def test_parsing_40k_lines_takes_under_a_second(tmp_path):
    f = tmp_path / "big.gcode"
    big_file(f)
    n = sum(1 for _ in open(f))
    cpu = min(_timed(parse_gcode, f, clock=time.process_time) for _ in range(2))
    assert n >= 40000 and cpu < 1.0          # CPU time: the shared machine's load does not count


def _timed(fn, *a, clock=time.perf_counter):
    t = clock()
    fn(*a)
    return clock() - t


if __name__ == "__main__":          # benchmark: one JSON line
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        f = os.path.join(d, "big.gcode")
        t0 = time.perf_counter()
        rib = big_file(f)
        t_write = time.perf_counter() - t0
        n = sum(1 for _ in open(f))
        t_parse = min(_timed(parse_gcode, f) for _ in range(3))
        t_read = min(_timed(read_gcode, f) for _ in range(3))
        c_parse = min(_timed(parse_gcode, f, clock=time.process_time) for _ in range(3))
        c_read = min(_timed(read_gcode, f, clock=time.process_time) for _ in range(3))
        print(json.dumps(dict(benchmark="gcode_io", lines=n, ribbons=len(rib), write_s=round(t_write, 3),
                              parse_s=round(t_parse, 3), read_s=round(t_read, 3), parse_cpu_s=round(c_parse, 3),
                              read_cpu_s=round(c_read, 3), parse_lines_per_cpu_s=round(n / c_parse),
                              elements=len(read_gcode(f)), load_avg_1min=os.getloadavg()[0])))
