"""G-code planning (inverse.gcode), the printer record (inverse.printer), the writer and header
(geometry.gcode) and the write/read round trip of the header and the moves."""
import dataclasses
import math
import os
import re

import numpy as np
import pytest
import shapely

from geometry.elements import Ribbon
from geometry.beads import bead_area, bead_width
from geometry.gcode import GcodeHeader, GcodeWriter, from_bed, parse_gcode, read_gcode, read_header, to_bed
from inverse.gcode import greedy_order, layer_counts, ribbons_to_gcode_files, write_gcode
from inverse.printer import Printer, load_printer
from shellfem.errors import SelfshapeError


def design():
    """Mixed design: straight, bent and wavy ribbons, several widths and thicknesses, both sides."""
    t = np.linspace(0.0, 1.0, 25)
    rib = []
    for i in range(4):
        for j in range(3):
            x0, y0 = 12.0 * i, 9.0 * j
            if (i + j) % 3 == 0:
                path = np.array([[x0, y0], [x0 + 8.0, y0]])
            elif (i + j) % 3 == 1:
                path = np.array([[x0, y0], [x0 + 6.0, y0], [x0 + 6.0, y0 + 4.0]])
            else:
                path = np.column_stack([x0 + 8.0 * t, y0 + 1.5 * np.sin(2 * math.pi * t)])
            rib.append(Ribbon(path=path, width_mm=[0.8, 1.5, 2.0][j], thickness_mm=[0.2, 0.4, 0.3, 0.6][i],
                              side="back" if (i * 3 + j) % 4 == 3 else "front", label=f"r{i}{j}"))
    return rib


def reference_polygon(r, cap="square"):
    return shapely.buffer(shapely.LineString(r.path), r.width_mm / 2, cap_style=cap, join_style="round",
                          quad_segs=8)


def gcode_lines(path):
    with open(path) as f:
        return f.read().splitlines()


# ---------------------------------------------------------------- printer

def test_printer_defaults_follow_the_seed():
    p = Printer()
    assert (p.nozzle_mm, p.print_speed_mm_s, p.filament_diameter_mm) == (0.8, 15.0, 2.85)
    assert p.flip_axis_x == p.bed_size[0] / 2
    assert p.filament_area_mm2 == pytest.approx(math.pi * 2.85 ** 2 / 4, rel=1e-15)


@pytest.mark.parametrize("kw, word", [
    (dict(nozzle_mm=0), "nozzle_mm"), (dict(layer_height_mm=-0.1), "layer_height_mm"),
    (dict(layer_height_mm=1.0), "layer_height_mm"), (dict(bed_size=(200,)), "bed_size"),
    (dict(print_speed_mm_s=float("nan")), "print_speed_mm_s"), (dict(origin=("a", 0)), "origin"),
    (dict(retraction_mm=-1), "retraction_mm"), (dict(nozzle_temperature_c=500), "nozzle_temperature_c"),
    (dict(relative_e="yes"), "relative_e"),
])
def test_printer_validation_is_one_line(kw, word):
    with pytest.raises(SelfshapeError) as e:
        Printer(**kw)
    assert word in str(e.value) and "\n" not in str(e.value)


def test_bead_model_round_trips_and_matches_slic3r():
    w, h = np.array([0.45, 0.8, 1.5, 2.0]), np.array([0.2, 0.3, 0.2, 0.25])
    # Slic3r Flow::mm3_per_mm for a non-bridge extrusion: h * (w - h * (1 - pi / 4))
    assert np.allclose(bead_area(w, h), h * (w - h * (1 - math.pi / 4)), rtol=1e-14)
    assert np.allclose(bead_width(bead_area(w, h), h), w, rtol=1e-14)
    assert bead_area(h[0], h[0]) == pytest.approx(math.pi * h[0] ** 2 / 4)   # w = h: a circle


# ---------------------------------------------------------------- writer

def test_layer_counts_round_half_up():
    assert layer_counts([0.05, 0.2, 0.29, 0.3, 0.4, 0.5, 0.6], 0.2).tolist() == [1, 1, 1, 2, 2, 3, 3]


def test_greedy_order_matches_brute_force_and_is_deterministic():
    rng = np.random.default_rng(3)
    n = 400
    starts = np.round(rng.uniform(0, 60, (n, 2)))          # integer grid: many exact ties
    ends = starts + np.round(rng.uniform(-4, 4, (n, 2)))
    order, rev, last = greedy_order(starts, ends, (0.0, 0.0))
    alive = np.ones(n, bool)
    cur = np.zeros(2)
    for i, r in zip(order, rev):          # every step goes to a nearest free endpoint, ties to lower index
        d = np.hypot(*(np.concatenate([starts, ends]) - cur).T)
        d[np.r_[~alive, ~alive]] = np.inf
        cand = np.flatnonzero(d <= d.min() + 1e-12)
        best = cand[np.argmin((cand % n) * 2 + (cand >= n))]
        assert (i, r) == (best % n, best >= n)
        alive[i] = False
        cur = starts[i] if r else ends[i]
    assert sorted(order) == list(range(n)) and np.array_equal(cur, last)
    o2, r2, _ = greedy_order(starts, ends, (0.0, 0.0))
    assert np.array_equal(order, o2) and np.array_equal(rev, r2)


def test_greedy_order_shortens_travel():
    rng = np.random.default_rng(5)
    starts = rng.uniform(0, 100, (300, 2))
    ends = starts + rng.uniform(-3, 3, (300, 2))
    order, rev, _ = greedy_order(starts, ends)
    s = np.where(rev[:, None], ends[order], starts[order])
    e = np.where(rev[:, None], starts[order], ends[order])
    greedy = np.hypot(*(s[1:] - e[:-1]).T).sum()
    naive = np.hypot(*(starts[1:] - ends[:-1]).T).sum()
    assert greedy < 0.25 * naive


def test_extrusion_is_the_bead_volume(tmp_path):
    p = Printer(filament_diameter_mm=1.75, extrusion_multiplier=1.0)
    rib = [Ribbon(path=np.array([[0.0, 0.0], [30.0, 0.0], [30.0, 10.0]]), width_mm=1.2, thickness_mm=0.4)]
    out = tmp_path / "a.gcode"
    stats = write_gcode(rib, out, p)
    seg = parse_gcode(out)
    length = np.hypot(seg["x1"] - seg["x0"], seg["y1"] - seg["y0"])
    expect = bead_area(1.2, 0.2) * length / p.filament_area_mm2
    assert len(seg) == 4 and np.allclose(seg["e_mm"], expect, atol=5e-6)
    assert stats["extruded_filament_mm"] == pytest.approx(2 * 40.0 * bead_area(1.2, 0.2) / p.filament_area_mm2)
    assert stats["plastic_volume_mm3"] == pytest.approx(2 * 40.0 * bead_area(1.2, 0.2))
    p2 = Printer(filament_diameter_mm=1.75, extrusion_multiplier=1.1)
    s2 = write_gcode(rib, tmp_path / "b.gcode", p2)
    assert s2["extruded_filament_mm"] == pytest.approx(1.1 * stats["extruded_filament_mm"])


def test_layers_hints_and_only_the_requested_side(tmp_path):
    rib = design()
    h = 0.2
    out = tmp_path / "front.gcode"
    stats = write_gcode(rib, out, Printer())
    lines = gcode_lines(out)
    front = [r for r in rib if r.side == "front"]
    n_layers = layer_counts([r.thickness_mm for r in front], h)
    assert stats["n_ribbons"] == len(front) and stats["n_layers"] == n_layers.max()
    assert lines.count(";LAYER_CHANGE") == n_layers.max()
    zs = [float(l[3:]) for l in lines if l.startswith(";Z:")]
    assert np.allclose(zs, h * np.arange(1, n_layers.max() + 1))
    assert sum(l.startswith(";HEIGHT:0.2") for l in lines) == n_layers.max()
    widths = sorted({float(l[7:]) for l in lines if l.startswith(";WIDTH:")})
    assert widths == sorted({r.width_mm for r in front})
    assert sum(l.startswith(";TYPE:Ribbon") for l in lines) == n_layers.sum()      # one print per ribbon and layer
    labels = {m.group(1) for l in lines if (m := re.match(r"; ribbon \d+ \((r\d\d)\)", l))}
    assert labels == {r.label for r in front}
    assert stats["thickness_printed_mm"] == pytest.approx((n_layers * h).tolist())
    assert stats["thickness_error_max_mm"] == pytest.approx(0.1)        # 0.3 mm -> 2 layers = 0.4 mm


def test_travel_retracts_and_hops(tmp_path):
    p = Printer(retraction_mm=4.5, z_hop_mm=0.5, relative_e=True)
    rib = [Ribbon(path=np.array([[10.0 * i, 0.0], [10.0 * i + 5, 0.0]]), width_mm=1.0, thickness_mm=0.2)
           for i in range(5)]
    out = tmp_path / "t.gcode"
    stats = write_gcode(rib, out, p)
    z, e_net, hops = 0.0, 0.0, []
    retracts = 0
    for l in gcode_lines(out):
        if l.startswith("G1 Z") or l.startswith("G0 Z"):
            z = float(l.split()[1][1:])
        if l.startswith("G0 X"):
            hops.append(z)
        m = re.match(r"G1 E(-?[\d.]+)", l)
        if m:
            e_net += float(m.group(1))
            retracts += float(m.group(1)) < 0
    assert hops == [pytest.approx(0.7)] * 5 and retracts == stats["n_retractions"] == 6   # 5 travels + end
    assert e_net == pytest.approx(-4.5)        # every retraction undone except the final one
    seg = parse_gcode(out)
    assert len(seg) == 5 and np.unique(seg["path"]).size == 5


def test_absolute_e_is_cumulative(tmp_path):
    rib = design()
    a = write_gcode(rib, tmp_path / "abs.gcode", Printer(relative_e=False))
    lines = gcode_lines(tmp_path / "abs.gcode")
    assert "M82 ; absolute extrusion" in lines
    last_e = [float(m.group(1)) for l in lines if (m := re.search(r" E(-?[\d.]+)", l))][-1]
    assert last_e == pytest.approx(a["extruded_filament_mm"] - 4.5, abs=1e-5)   # final retraction


def test_out_of_bed_and_bad_ribbons_are_one_line_errors(tmp_path):
    out = tmp_path / "x.gcode"
    big = [Ribbon(path=np.array([[0.0, 0.0], [300.0, 0.0]]), width_mm=1.0, thickness_mm=0.2, label="long")]
    with pytest.raises(SelfshapeError, match=r"ribbon 0 \(long\): falls outside the 223 x 223 mm bed"):
        write_gcode(big, out)
    near = [Ribbon(path=np.array([[0.0, 0.0], [10.0, 0.0]]), width_mm=1.0, thickness_mm=0.2)]
    with pytest.raises(SelfshapeError, match="outside"):
        write_gcode(near, out, Printer(origin=(0.2, 50.0)))       # the bead's edge crosses x = 0
    assert not out.exists()                                        # nothing partial left behind
    bad = [
        (Ribbon(path=np.array([[1.0, 1.0], [1.0, 1.0]])), "zero length"),
        (Ribbon(path=np.array([[0.0, 0.0], [5.0, 0.0]]), width_mm=0.1), "below the layer height"),
        (Ribbon(path=np.array([[0.0, 0.0], [5.0, 0.0]]), thickness_mm=-0.2), "must be > 0"),
        (Ribbon(path=np.array([[0.0, 0.0], [5.0, 0.0]]), side="top"), "side"),
        (Ribbon(path=np.array([[0.0, np.nan], [5.0, 0.0]])), "non-finite"),
        (Ribbon(path=np.array([0.0, 5.0])), "shape"),
    ]
    for r, word in bad:
        with pytest.raises(SelfshapeError) as e:
            write_gcode([near[0], r], out)
        assert word in str(e.value) and str(e.value).startswith("ribbon 1") and "\n" not in str(e.value)
    with pytest.raises(SelfshapeError, match="side"):
        write_gcode(near, out, side="both")


def test_ribbons_to_gcode_files_writes_back_only_when_needed(tmp_path):
    front_only = [Ribbon(path=np.array([[0.0, 0.0], [10.0, 0.0]]))]
    assert [os.path.basename(p) for p in ribbons_to_gcode_files(front_only, tmp_path / "a")] == ["front.gcode"]
    paths = ribbons_to_gcode_files(design(), tmp_path / "b")
    assert [os.path.basename(p) for p in paths] == ["front.gcode", "back.gcode"]
    assert all(os.path.getsize(p) > 0 for p in paths)


# ---------------------------------------------------------------- mirror convention

def test_back_side_lands_on_the_same_fabric_point(tmp_path):
    p = Printer(origin=(40.0, 30.0), mirror_axis_x=100.0)
    r = Ribbon(path=np.array([[5.0, 2.0], [25.0, 2.0], [25.0, 12.0]]), width_mm=1.0, thickness_mm=0.2,
               side="front")
    rb = Ribbon(path=r.path, width_mm=1.0, thickness_mm=0.2, side="back")
    write_gcode([r, rb], tmp_path / "f.gcode", p, side="front")
    write_gcode([r, rb], tmp_path / "b.gcode", p, side="back")
    f, b = parse_gcode(tmp_path / "f.gcode"), parse_gcode(tmp_path / "b.gcode")
    fp = {(round(x, 3), round(y, 3)) for x, y in zip(np.r_[f["x0"], f["x1"]], np.r_[f["y0"], f["y1"]])}
    bp = {(round(x, 3), round(y, 3)) for x, y in zip(np.r_[b["x0"], b["x1"]], np.r_[b["y0"], b["y1"]])}
    assert fp == {(45.0, 32.0), (65.0, 32.0), (65.0, 42.0)}           # front: + origin
    assert bp == {(2 * 100.0 - x, y) for x, y in fp}                   # back: x -> 2 a - x
    # flipping the frame about bed x = a moves the fabric point printed at bed x to 2a - x
    xy = r.path
    assert np.allclose(from_bed(to_bed(xy, p.origin, "back", 100.0), p.origin, "back", 100.0), xy)


# ---------------------------------------------------------------- round trip

@pytest.mark.parametrize("relative_e", [True, False])
def test_round_trip_write_then_read(tmp_path, relative_e):
    rib = design()
    p = Printer(relative_e=relative_e)
    files = ribbons_to_gcode_files(rib, tmp_path, p)
    for side, path in zip(("front", "back"), files):
        ref = [r for r in rib if r.side == side]
        els = read_gcode(path)                       # side, origin, axis from the header
        assert els.meta["side"] == side and els.meta["warnings"] == []
        assert len(els) == len(ref)
        ref_poly = [reference_polygon(r) for r in ref]
        ref_c = np.array([[q.centroid.x, q.centroid.y] for q in ref_poly])
        matched = set()
        for e in els:
            c = np.array([e.geometry.centroid.x, e.geometry.centroid.y])
            k = int(np.argmin(np.hypot(*(ref_c - c).T)))
            matched.add(k)
            assert np.hypot(*(ref_c[k] - c)) < 0.1
            assert e.geometry.area == pytest.approx(ref_poly[k].area, rel=0.03)
            assert e.thickness_mm == pytest.approx(layer_counts([ref[k].thickness_mm], 0.2)[0] * 0.2, abs=1e-9)
            assert e.side == side and e.kind == "gcode"
        assert len(matched) == len(ref)


def test_round_trip_widths_are_recovered_from_volume_alone(tmp_path):
    rib = design()
    out = tmp_path / "f.gcode"
    write_gcode(rib, out, Printer())
    text = re.sub(r";WIDTH:.*\n", "", out.read_text())
    (tmp_path / "nohint.gcode").write_text(text)
    els = read_gcode(tmp_path / "nohint.gcode")
    assert els.meta["width_source"] == "volume"
    want = sorted({r.width_mm for r in rib if r.side == "front"})
    got = np.array(els.meta["path_widths_mm"])
    assert np.allclose(np.sort(np.unique(np.round(got, 3))), want)
    assert np.abs(got[:, None] - np.array(want)[None]).min(axis=1).max() < 1e-4


def test_round_trip_back_side_with_an_explicit_axis(tmp_path):
    rib = [Ribbon(path=np.array([[0.0, 0.0], [20.0, 5.0]]), width_mm=1.5, thickness_mm=0.4, side="back")]
    p = Printer(origin=(50.0, 60.0), mirror_axis_x=90.0)
    write_gcode(rib, tmp_path / "b.gcode", p, side="back")
    (tmp_path / "plain.gcode").write_text("\n".join(
        l for l in (tmp_path / "b.gcode").read_text().splitlines() if "selfshape" not in l))
    els = read_gcode(tmp_path / "plain.gcode", side="back", mirror_axis_x=90.0, origin_mm=(50.0, 60.0))
    ref = reference_polygon(rib[0])
    assert len(els) == 1 and els[0].thickness_mm == pytest.approx(0.4)
    assert els[0].geometry.symmetric_difference(ref).area < 1e-3 * ref.area
    wrong = read_gcode(tmp_path / "plain.gcode", side="back", mirror_axis_x=100.0, origin_mm=(50.0, 60.0))
    assert wrong[0].geometry.centroid.x == pytest.approx(ref.centroid.x + 20.0)    # shifts by 2 (a' - a)


def test_load_printer_reads_a_printer_table_and_keeps_defaults(tmp_path):
    p = tmp_path / "printer.toml"
    p.write_text("[printer]\nbed_size = [300, 250]\nnozzle_mm = 0.6\nprint_speed_mm_s = 20\n")
    pr = load_printer(str(p))
    assert pr.bed_size == (300.0, 250.0) and pr.nozzle_mm == 0.6 and pr.print_speed_mm_s == 20.0
    assert pr.layer_height_mm == Printer().layer_height_mm          # untouched keys keep the defaults
    flat = tmp_path / "flat.toml"
    flat.write_text("nozzle_mm = 0.4\nlayer_height_mm = 0.1\n")     # top-level keys work too
    assert load_printer(str(flat)).nozzle_mm == 0.4


@pytest.mark.parametrize("text, word", [
    ("[printer]\nnozle_mm = 0.6\n", "unknown key 'nozle_mm'"),
    ("[printer]\nnozzle_mm = -1\n", "nozzle_mm must be in [0.1, 2] mm, got -1"),
    ("[printer\n", "malformed TOML"),
])
def test_load_printer_errors_are_one_line(tmp_path, text, word):
    p = tmp_path / "printer.toml"
    p.write_text(text)
    with pytest.raises(SelfshapeError) as e:
        load_printer(str(p))
    assert word in str(e.value) and "\n" not in str(e.value) and "printer.toml" in str(e.value)


def test_load_printer_missing_file():
    with pytest.raises(SelfshapeError, match="printer file /nonexistent/printer.toml: file not found"):
        load_printer("/nonexistent/printer.toml")


def test_load_printer_binary_file_is_a_one_line_error(tmp_path):
    p = tmp_path / "printer.toml"
    p.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(SelfshapeError, match="not a UTF-8 text file"):
        load_printer(str(p))


# ---------------------------------------------------------------- header round trip

def odd_printer(relative_e):
    """Every setting away from its default, each exactly representable in the header's format."""
    return Printer(bed_size=(250.0, 210.0), nozzle_mm=0.6, filament_diameter_mm=1.75, layer_height_mm=0.15,
                   print_speed_mm_s=22.5, travel_speed_mm_s=120.0, z_speed_mm_s=8.0, retraction_mm=3.25,
                   retraction_speed_mm_s=35.0, retract_min_travel_mm=2.0, z_hop_mm=0.375, extrusion_multiplier=1.05,
                   nozzle_temperature_c=231.0, bed_temperature_c=55.0, bed_offset_z_mm=0.5, origin=(60.25, 70.5),
                   mirror_axis_x=120.125, relative_e=relative_e)


@pytest.mark.parametrize("side, relative_e", [("front", True), ("back", False)])
def test_header_round_trips_every_field(tmp_path, side, relative_e):
    p = odd_printer(relative_e)
    out = tmp_path / f"{side}.gcode"
    stats = write_gcode(design(), out, p, side=side)
    expected = GcodeHeader(
        side=side, origin_mm=(60.25, 70.5), mirror_axis_x_mm=120.125, bed_offset_z_mm=0.5,
        ribbons=stats["n_ribbons"], layers=stats["n_layers"], bed_shape_mm=(250.0, 210.0), nozzle_diameter_mm=0.6,
        filament_diameter_mm=1.75, layer_height_mm=0.15, first_layer_height_mm=0.15, extrusion_multiplier=1.05,
        print_speed_mm_s=22.5, travel_speed_mm_s=120.0, retract_length_mm=3.25, retract_speed_mm_s=35.0,
        retract_lift_mm=0.375, temperature_c=231.0, bed_temperature_c=55.0, relative_e=relative_e)
    got = read_header(out)
    for f in dataclasses.fields(GcodeHeader):
        assert getattr(got, f.name) == getattr(expected, f.name), f.name
    # the test can fail: each field read back differs from what the default printer writes
    write_gcode(design(), tmp_path / "default.gcode", Printer(relative_e=not relative_e), side="back" if
                side == "front" else "front")
    default = read_header(tmp_path / "default.gcode")
    same = [f.name for f in dataclasses.fields(GcodeHeader) if getattr(default, f.name) == getattr(got, f.name)]
    assert same == []


def test_every_header_line_is_read_back(tmp_path):
    out = tmp_path / "f.gcode"
    write_gcode(design(), out, odd_printer(True))
    lines = gcode_lines(out)
    keyed = [(i, m.group(1)) for i, l in enumerate(lines) if (m := re.fullmatch(r"; (?:selfshape )?(\w+) = .*", l))]
    assert len(keyed) == len(dataclasses.fields(GcodeHeader)) - 1         # relative_e is the M83/M82 line
    for i, key in keyed:                                                   # drop one line: the reader misses it
        (tmp_path / "cut.gcode").write_text("\n".join(lines[:i] + lines[i + 1:]) + "\n")
        with pytest.raises(SelfshapeError, match=rf"cut.gcode: .*\b{key} is missing"):
            read_header(tmp_path / "cut.gcode")
        (tmp_path / "bad.gcode").write_text("\n".join(lines[:i] + [f"{lines[i].split('=')[0]}= ?"]
                                                      + lines[i + 1:]) + "\n")
        with pytest.raises(SelfshapeError, match=rf"bad.gcode: line {i + 1}: .*\b{key} is not valid"):
            read_header(tmp_path / "bad.gcode")
    with pytest.raises(SelfshapeError, match="no selfshape header"):
        read_header(os.path.join(os.path.dirname(__file__), "data", "gcode", "prusa_relative.gcode"))


def test_writer_moves_read_back_as_written(tmp_path):
    h = GcodeHeader(side="front", origin_mm=(0.0, 0.0), mirror_axis_x_mm=100.0, bed_offset_z_mm=0.0, ribbons=1,
                    layers=1, bed_shape_mm=(200.0, 200.0), nozzle_diameter_mm=0.4, filament_diameter_mm=1.75,
                    layer_height_mm=0.2, first_layer_height_mm=0.2, extrusion_multiplier=1.0, print_speed_mm_s=20.0,
                    travel_speed_mm_s=100.0, retract_length_mm=2.0, retract_speed_mm_s=30.0, retract_lift_mm=0.4,
                    temperature_c=220.0, bed_temperature_c=0.0, relative_e=False)
    w = GcodeWriter(h, z_speed_mm_s=10.0, retract_min_travel_mm=1.0)
    pts = np.array([[10.0, 10.0], [40.0, 10.0], [40.0, 30.0], [25.0, 45.5]])
    e_per_mm = bead_area(1.0, 0.2) / (math.pi * 1.75 ** 2 / 4)
    w.layer_change(0.2, 0.2)
    w.travel(pts[0], 0.2)
    w.feature("Ribbon", 1.0, "one path")
    w.extrude(pts, e_per_mm)
    w.finish()
    w.write(tmp_path / "w.gcode")
    assert read_header(tmp_path / "w.gcode") == h
    seg = parse_gcode(tmp_path / "w.gcode")
    np.testing.assert_allclose(np.column_stack([seg["x0"], seg["y0"]]), pts[:-1], atol=5e-4)
    np.testing.assert_allclose(np.column_stack([seg["x1"], seg["y1"]]), pts[1:], atol=5e-4)
    length = np.hypot(*np.diff(pts, axis=0).T)
    np.testing.assert_allclose(seg["e_mm"], e_per_mm * length, atol=5e-6)    # E has 5 decimals
    assert seg["z"].tolist() == [0.2] * 3 and seg["width_hint"].tolist() == [1.0] * 3
    assert w.stats["print_length_mm"] == pytest.approx(length.sum()) and w.stats["n_retractions"] == 2
    els = read_gcode(tmp_path / "w.gcode")
    ref = shapely.buffer(shapely.LineString(pts), 0.5, cap_style="square", join_style="round", quad_segs=8)
    assert len(els) == 1 and els[0].thickness_mm == pytest.approx(0.2)
    assert els[0].geometry.symmetric_difference(ref).area < 1e-4 * ref.area


@pytest.mark.parametrize("side", ["front", "back"])
def test_written_ribbons_read_back_as_the_same_printed_elements(tmp_path, side):
    rib = [r for r in design() if r.side == side]
    out = tmp_path / f"{side}.gcode"
    write_gcode(design(), out, odd_printer(side == "front"), side=side)
    els = read_gcode(out)
    assert len(els) == len(rib)
    ref = [reference_polygon(r) for r in rib]
    for e in els:                                 # each element is one ribbon's bead, to G-code resolution
        k = int(np.argmin([e.geometry.symmetric_difference(q).area for q in ref]))
        assert e.geometry.symmetric_difference(ref[k]).area < 1e-3 * ref[k].area
        assert e.thickness_mm == pytest.approx(layer_counts([rib[k].thickness_mm], 0.15)[0] * 0.15, abs=1e-9)
        ref.pop(k), rib.pop(k)
