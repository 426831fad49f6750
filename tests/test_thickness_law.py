import numpy as np
import pytest

from inverse.thickness_law import (curvature, format_thickness_law, load_thickness_law, parse_thickness_law,
                                   printable_range, thickness_for_curvature)
from shellfem.errors import SelfshapeError

T = [0.2, 0.4, 0.6, 1.0]
MU = [4.0, 6.0, 10.0]


def bilinear(t, mu, side):
    # strictly decreasing in t for every mu in range (like a bilayer beyond its peak)
    base = 0.30 if side == "front" else 0.20
    return base - 0.2 * t + 0.004 * mu + 0.01 * t * mu


def table_text(fn=bilinear, sides=("front", "back")):
    rows = [(t, mu, s, fn(t, mu, s)) for s in sides for t in T for mu in MU]
    return format_thickness_law(rows, ["test table", "bilinear"])


def test_interpolation_exact_on_a_bilinear_table():
    law = parse_thickness_law(table_text())
    rng = np.random.default_rng(1)
    t = rng.uniform(0.2, 1.0, 50)
    mu = rng.uniform(4.0, 10.0, 50)
    for side in ("front", "back"):
        np.testing.assert_allclose(curvature(law, t, mu, side), bilinear(t, mu, side), rtol=0, atol=1e-12)
    assert law.provenance == ["test table", "bilinear"]
    assert law.table("front").increasing is False


def test_inverse_round_trips_and_quantizes():
    law = parse_thickness_law(table_text())
    rng = np.random.default_rng(2)
    t = rng.uniform(0.2, 1.0, 40)
    mu = rng.uniform(4.0, 10.0, 40)
    k = curvature(law, t, mu, "back")
    t2, info = thickness_for_curvature(law, k, mu, "back", quantize=False)
    np.testing.assert_allclose(t2, t, atol=1e-12)
    assert info["clamped_low"] == info["clamped_high"] == info["spacing_clamped"] == 0
    # quantized: the nearest multiple of 0.2 mm (here the exact thicknesses of the grid)
    tq, _ = thickness_for_curvature(law, curvature(law, [0.4, 0.6], [5.0, 5.0], "front"), [5.0, 5.0], "front",
                                    layer_height_mm=0.2)
    np.testing.assert_allclose(tq, [0.4, 0.6], atol=1e-12)
    tq, _ = thickness_for_curvature(law, curvature(law, [0.47], [5.0], "front"), [5.0], "front",
                                    layer_height_mm=0.1)
    np.testing.assert_allclose(tq, [0.5], atol=1e-12)


def test_increasing_table_inverts_too_and_sign_is_ignored():
    inc = lambda t, mu, s: 0.01 + 0.05 * t + 0.001 * mu + 0.002 * t * mu  # noqa: E731
    law = parse_thickness_law(table_text(inc))
    assert law.table("front").increasing
    t2, _ = thickness_for_curvature(law, -inc(0.7, 8.0, "front"), 8.0, "front", quantize=False)
    assert t2 == pytest.approx(0.7, abs=1e-12)


def test_the_law_states_its_plastic():
    assert parse_thickness_law(table_text()).plastic_young_modulus_mpa is None
    law = parse_thickness_law("# made with\n#  plastic_young_modulus_mpa = 1180.5\n" + table_text())
    assert law.plastic_young_modulus_mpa == 1180.5


def test_clamping_is_counted():
    law = parse_thickness_law(table_text())
    # decreasing law: too little curvature -> thickest; too much -> thinnest; spacing clamped to range
    k = [0.0, 10.0, bilinear(0.6, 10.0, "front")]
    t, info = thickness_for_curvature(law, k, [5.0, 5.0, 30.0], "front", layer_height_mm=0.2)
    np.testing.assert_allclose(t, [1.0, 0.2, 0.6], atol=1e-12)
    assert (info["clamped_low"], info["clamped_high"], info["spacing_clamped"]) == (1, 1, 1)
    assert printable_range(law.table("front"), 0.3) == pytest.approx((0.3, 0.9))


@pytest.mark.parametrize("mutate, word", [
    (lambda s: s.replace("kappa_per_mm", "kappa"), "missing column 'kappa_per_mm'"),
    (lambda s: s.replace(f",{bilinear(0.4, 6.0, 'front'):.6g}", ",nan", 1), "must be finite"),
    (lambda s: s.replace(f",{bilinear(0.6, 6.0, 'front'):.6g}", ",0.9", 1), "not strictly monotone"),
    (lambda s: "\n".join(ln for ln in s.splitlines() if not ln.startswith("1,10,back")), "missing row"),
    (lambda s: s.replace("0.2,4,front", "0.2,4,top"), "side must be"),
    (lambda s: s + "0.2,4,front,0.5\n", "duplicate row"),
    (lambda s: s.replace("0.2,4,front", "0.2,abc,front"), "spacing_mm must be a number"),
    (lambda s: "# plastic_young_modulus_mpa = -3\n" + s, "plastic_young_modulus_mpa must be in [0.1, 100000]"),
    (lambda s: "# plastic_young_modulus_mpa = soft\n" + s, "plastic_young_modulus_mpa must be a number"),
    # physical ranges (issue 19: a kappa of 1e300 1/mm designed with exit 0), the csv field limit
    (lambda s: s.replace(f",{bilinear(0.4, 6.0, 'front'):.6g}", ",1e300", 1), "kappa_per_mm must be in [0, 10]"),
    (lambda s: s.replace("0.2,4,front", "1e300,4,front"), "thickness_mm must be in [0.01, 10]"),
    (lambda s: s.replace("0.2,4,front", "0.2,1e300,front"), "spacing_mm must be in [0.1, 1000]"),
    (lambda s: "# fabric_stretch = 1e300\n" + s, "fabric_stretch must be in (1, 3]"),
    (lambda s: s + "x" * 200_000 + ",4,front,0.1\n", "csv module's limit"),
])
def test_bad_tables_one_line_errors(mutate, word):
    with pytest.raises(SelfshapeError) as e:
        parse_thickness_law(mutate(table_text()), "law.csv")
    assert word in str(e.value) and "law.csv" in str(e.value) and "\n" not in str(e.value)


def test_shipped_law_loads_with_provenance():
    law = load_thickness_law()
    assert set(law.sides) == {"front", "back"}
    text = " ".join(law.provenance)
    assert "SOURCE" in text and "git" in text
    tab = law.table("front")
    assert tab.kappa.shape == (len(tab.thickness), len(tab.spacing)) and (tab.kappa > 0).all()


def test_missing_file(tmp_path):
    with pytest.raises(SelfshapeError, match="not found"):
        load_thickness_law(tmp_path / "nope.csv")
    with pytest.raises(SelfshapeError, match="is a directory"):
        load_thickness_law(tmp_path)


def test_law_with_a_byte_order_mark_reads_as_without(tmp_path):
    """Windows editors save UTF-8 with a BOM; it is not part of the header (issue 19: the law
    was refused for a "missing column 'thickness_mm'")."""
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + table_text().encode())
    (tmp_path / "plain.csv").write_text(table_text())
    a, b = load_thickness_law(tmp_path / "bom.csv"), load_thickness_law(tmp_path / "plain.csv")
    np.testing.assert_array_equal(a.table("front").kappa, b.table("front").kappa)


def test_simulation_patch_has_the_layout_stagger():
    from geometry.patterns import load_pattern
    from validation.law_tables import MU1, RIBBON_LENGTH, patch_pattern
    raw = patch_pattern(0.6, 5.0, "back", 1.6, n_rows=4, n_motifs=3)
    pat = load_pattern(raw)
    W, H = 3 * MU1, 4 * 5.0
    assert pat.outline.bounds == (0.0, 0.0, W, H) and pat.fabric.stretch == (1.6, 1.6)
    rows = {}
    for r in raw["ribbon"]:
        (x0, y0), (x1, y1) = r["path"]
        assert y0 == y1 and r["side"] == "back" and r["thickness_mm"] == 0.6
        rows.setdefault(y0, []).append(0.5 * (x0 + x1) if x1 - x0 == RIBBON_LENGTH else None)
    assert sorted(rows) == [2.5, 7.5, 12.5, 17.5]                     # rows mu2 apart
    full0 = [c for c in rows[2.5] if c is not None]
    full1 = [c for c in rows[7.5] if c is not None]
    assert np.allclose(np.diff(full0), MU1) and np.allclose((np.array(full1) - full0[0]) % MU1, MU1 / 2)
    assert len(pat.elements) == len(raw["ribbon"])


def test_strip_table_is_the_coverage_blend():
    from shellfem.materials import Fabric, Plastic
    from shellfem.strip import strip_curvature
    from validation.law_tables import strip_rows
    fab, pla = Fabric(), Plastic()
    rows = strip_rows([0.4, 0.8], [1.5, 6.0], 1.6, fab, pla)
    assert len(rows) == 8
    k = {(t, mu, s): v for t, mu, s, v in rows}
    ratio = pla.young_modulus / fab.young_modulus
    plate = strip_curvature(0.4, fab.thickness, 1.6, ratio, mode="plate")
    narrow = strip_curvature(0.8, fab.thickness, 1.6, ratio, mode="narrow")
    plate8 = strip_curvature(0.8, fab.thickness, 1.6, ratio, mode="plate")
    assert k[(0.4, 1.5, "front")] == pytest.approx(abs(plate))            # full coverage: a plate
    assert k[(0.8, 6.0, "back")] == pytest.approx(abs(0.25 * plate8 + 0.75 * narrow))
    # the shipped strip-model table is this model at the default materials
    import os

    from inverse.thickness_law import DEFAULT_LAW
    law = load_thickness_law(os.path.join(os.path.dirname(DEFAULT_LAW), "thickness_law_s1.6_strip.csv"))
    t = law.table("front")
    i, j = list(t.thickness).index(0.8), list(t.spacing).index(15.0)
    kk = strip_rows([0.8], [15.0], 1.6, fab, pla)[0][3]
    assert t.kappa[i, j] == pytest.approx(kk, rel=1e-5)


@pytest.mark.slow
def test_simulated_row_runs():
    from validation.law_tables import simulate_row
    r = simulate_row(0.6, 6.5, "front", 1.6, mesh_size=3.0, across=1.0, n_rows=4, n_motifs=2, max_iterations=100)
    assert r["converged"] is True and r["kappa_per_mm"] > 0    # a printed patch curls: |kappa| > 0


def test_curvature_measurement_is_exact_on_a_rolled_sheet():
    from types import SimpleNamespace

    from geometry.target import grid_triangles
    from shellfem.model import ShellModel
    from shellfem.sheet import Sheet
    from validation.law_tables import curvature_along_x
    X, Y = np.meshgrid(np.linspace(0, 60, 31), np.linspace(0, 24, 13), indexing="ij")
    P = np.column_stack([X.ravel(), Y.ravel()])
    sheet = Sheet(P, grid_triangles(30, 12))
    model = ShellModel.homogeneous(sheet, 1.0, 0.3, 0.5)
    R = 20.0

    def measured(pos):
        q = np.concatenate([pos.ravel(), np.zeros(model.n_dofs - pos.size)])
        return curvature_along_x(SimpleNamespace(sheet=sheet, model=model, result=SimpleNamespace(q=q)),
                                 (15, 6, 45, 18))
    # rolled about y (along the ribbons, x): 1/R; rolled about x: 0 along x
    assert measured(np.column_stack([R * np.sin(P[:, 0] / R), P[:, 1], R * (1 - np.cos(P[:, 0] / R))])) \
        == pytest.approx(1 / R, rel=0.005)
    assert measured(np.column_stack([P[:, 0], R * np.sin(P[:, 1] / R), R * (1 - np.cos(P[:, 1] / R))])) \
        == pytest.approx(0.0, abs=1e-9)


def test_curvature_state_and_rolled_start():
    """curvature_state: normal curvature along and across the ribbons and the principal
    direction on exactly rolled sheets; rolled_start rolls the printed patch isometrically."""
    from types import SimpleNamespace

    from geometry.target import grid_triangles
    from shellfem.model import ShellModel
    from shellfem.sheet import Sheet
    from validation.law_tables import curvature_state, rolled_start
    X, Y = np.meshgrid(np.linspace(0, 60, 31), np.linspace(0, 24, 13), indexing="ij")
    P = np.column_stack([X.ravel(), Y.ravel()])
    sheet = Sheet(P, grid_triangles(30, 12))
    model = ShellModel.homogeneous(sheet, 1.0, 0.3, 0.5)

    def state(pos):
        q = np.concatenate([pos.ravel(), np.zeros(model.n_dofs - pos.size)])
        return curvature_state(SimpleNamespace(sheet=sheet, model=model, result=SimpleNamespace(q=q)),
                               (15, 6, 45, 18))
    R = 20.0
    for direction, angle in (("along", 0.0), ("across", 90.0)):
        pos = rolled_start(P, 1 / R, seed=0, direction=direction)
        pos[:, 2] -= rolled_start(P, 0.0, seed=0)[:, 2]               # without the 1 % perturbation
        e = sheet.triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        l0 = np.linalg.norm(P[e[:, 0]] - P[e[:, 1]], axis=1)
        l3 = np.linalg.norm(pos[e[:, 0]] - pos[e[:, 1]], axis=1)
        assert np.allclose(l3, l0, rtol=2e-3)                            # isometric up to chord error
        s = state(pos)
        along, across = (s["kappa_along_signed"], s["kappa_across_signed"])
        big, small = (along, across) if direction == "along" else (across, along)
        assert abs(big) == pytest.approx(1 / R, rel=0.01) and abs(small) < 1e-6
        assert abs(s["k1_per_mm"]) == pytest.approx(1 / R, rel=0.01) and s["k1_angle_deg"] == pytest.approx(angle, abs=1)
        assert abs(s["gaussian_per_mm2"]) < 1e-6


def test_shipped_default_law_is_the_simulated_table():
    """The default law comes from forward simulation (studies/thickness_law_sim.py, validation.law_tables), says so,
    is a full grid decreasing in thickness, and its back rows mirror the front rows."""
    import json
    import os

    from inverse.thickness_law import DEFAULT_LAW
    law = load_thickness_law()
    text = "\n".join(law.provenance)
    assert "SOURCE: forward simulation" in text and "relative difference" in text
    assert "from strips_S1_calibration.json" in text      # the plastic modulus comes from measured strips
    with open(os.path.join(os.path.dirname(DEFAULT_LAW), "strips_S1_calibration.json")) as fh:
        ratio = json.load(fh)["modulus_ratio"][0]
    assert f"plastic: E {ratio * 1.05:g} MPa" in text
    f, b = law.table("front"), law.table("back")
    assert np.all(np.diff(f.kappa, axis=0) < 0)
    assert np.array_equal(f.kappa, b.kappa)
    # the table's rows (issue 18: 3-row rows where they agree with 112.5 mm patches, the
    # 112.5 mm rows elsewhere, each bending along the ribbons) are kept with the study's runs
    with open(os.path.join(os.path.dirname(DEFAULT_LAW), "thickness_law_s1.6_rows.json")) as fh:
        rows = {(r["thickness_mm"], r["spacing_mm"]): r for r in json.load(fh)["rows"] if r["side"] == "front"}
    for i, tk in enumerate(f.thickness):
        for j, mu in enumerate(f.spacing):
            r = rows[(float(tk), float(mu))]
            assert r["converged"] and f.kappa[i, j] == pytest.approx(r["kappa_per_mm"], rel=1e-5)
            if r.get("patch_mm", [0])[0] >= 112:        # a design-size patch: bends along the ribbons
                assert r["k1_angle_deg"] < 35              # (0.4 / 3.9: 34 deg, said in the table's NOTE)
            else:                                          # a 3-row patch: only the thin rows
                assert tk <= 0.35


def test_law_from_previous_rows_writes_the_requested_subgrid(tmp_path):
    """--from-json rebuilds a table without simulating; --table-* keep a sub-grid, the other
    rows are listed in the provenance; --back mirror copies the front rows."""
    import json

    from validation.law_tables import main
    rows = []
    for t in (0.4, 0.8, 1.2):
        for mu in (4.0, 8.0):
            k = 1.0 / (t * mu) if t < 1.0 else 0.9          # not monotone at 1.2 mm
            rows.append(dict(thickness_mm=t, spacing_mm=mu, side="front", kappa_per_mm=k, converged=True,
                             reason="ok", newton_iterations=10, n_triangles=100, time_s=1.0))
    rows.append(dict(rows[3], side="back"))                  # the mirror check row (t=0.8, mu=8)
    src = tmp_path / "rows.json"
    src.write_text(json.dumps({"rows": rows}))
    out = tmp_path / "law.csv"
    assert main(["--model", "sim", "--back", "mirror", "--thickness", "0.4", "0.8", "1.2", "--spacing", "4", "8",
                 "--from-json", str(src), "--table-thickness", "0.4", "0.8", "--out", str(out)]) == 0
    law = load_thickness_law(out)
    f = law.table("front")
    assert list(f.thickness) == [0.4, 0.8] and list(f.spacing) == [4.0, 8.0]
    assert f.kappa[1, 1] == pytest.approx(1.0 / 6.4) and np.array_equal(law.table("back").kappa, f.kappa)
    text = "\n".join(law.provenance)
    assert "t=1.2 mu2=4 front: kappa 0.9" in text and "relative difference 0.0e+00" in text


def test_calibrated_plastic_is_named_in_the_provenance(tmp_path):
    """--calibration (a `selfshape calibrate strips` parameters.json) sets the plastic modulus of
    the simulated law and the header says where it came from; a bad file is a one-line exit."""
    import json

    from validation.law_tables import main, read_modulus_ratio
    cal = tmp_path / "parameters.json"
    cal.write_text(json.dumps({"modulus_ratio": [1000.0, 20.0], "fit": {"data": "strips_X.csv"}}))
    assert read_modulus_ratio(str(cal)) == (1000.0, 20.0, "strips_X.csv")
    rows = [dict(thickness_mm=t, spacing_mm=mu, side="front", kappa_per_mm=0.1 / t, converged=True, reason="ok",
                 newton_iterations=10, n_triangles=100, time_s=1.0) for t in (0.2, 0.4) for mu in (4.0, 8.0)]
    src = tmp_path / "rows.json"
    src.write_text(json.dumps({"rows": rows}))
    out = tmp_path / "law.csv"
    assert main(["--model", "sim", "--sides", "front", "--thickness", "0.2", "0.4", "--spacing", "4", "8",
                 "--from-json", str(src), "--calibration", str(cal), "--out", str(out)]) == 0
    text = out.read_text()
    assert "plastic: E 1050 MPa" in text and "modulus_ratio 1000.0 +- 20.0" in text and "strips_X.csv" in text
    for content, word in (("{}", "not a `selfshape calibrate strips`"), ('{"modulus_ratio": [-1, 1]}', "must be > 0")):
        cal.write_text(content)
        with pytest.raises(SystemExit) as e:
            read_modulus_ratio(str(cal))
        assert word in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(SystemExit, match="file not found"):
        read_modulus_ratio(str(tmp_path / "missing.json"))


def test_law_states_its_stretch_and_design_refuses_another():
    from inverse.design import design
    from inverse.thickness_law import check_law_stretch, law_for_stretch, shipped_laws
    from geometry.target import sphere_cap
    law = parse_thickness_law(format_thickness_law([(t, mu, s, bilinear(t, mu, s)) for s in ("front", "back")
                                                    for t in T for mu in MU], ["fabric_stretch = 1.4"]), "my.csv")
    assert law.stretch == pytest.approx(1.4)
    check_law_stretch(law, 1.4)
    with pytest.raises(SelfshapeError, match=r"my.csv: the law was made at fabric stretch 1.4, the design asks for 1.6"):
        check_law_stretch(law, 1.6)
    with pytest.raises(SelfshapeError, match="fabric_stretch must be in"):
        parse_thickness_law(table_text().replace("# test table", "# fabric_stretch = 0.9"))
    shipped = shipped_laws()
    assert 1.6 in shipped and law_for_stretch(1.6).stretch == pytest.approx(1.6)
    # every shipped law states the stretch its file name says
    for s, path in shipped.items():
        assert load_thickness_law(path).stretch == pytest.approx(s)
    # a stretch with no shipped law is a one-line error naming the shipped ones, before any work
    V, F = sphere_cap(radius=40.0, half_angle_deg=30.0, n_radial=6)
    with pytest.raises(SelfshapeError, match=r"no shipped thickness law for fabric stretch 1.37 \(shipped: .*1\.6"):
        design(V, F, stretch=1.37, diagonal_mm=40.0)
    # the 1.6 law given explicitly to a design at another stretch is refused (it was used silently before)
    with pytest.raises(SelfshapeError, match="made at fabric stretch 1.6, the design asks for 1.37"):
        design(V, F, stretch=1.37, diagonal_mm=40.0, thickness_law=shipped[1.6])


def test_curvature_reach_fractions_and_size_hint():
    from inverse.thickness_law import curvature_reach, reach_warning
    law = parse_thickness_law(table_text())
    # front at spacing 6: the printable range (0.2 mm layers, t 0.2..1.0) gives kappa 0.116 .. 0.284
    lo, hi = sorted(curvature(law, [1.0, 0.2], [6.0, 6.0], "front"))
    kappa = np.array([0.05, 0.06, 0.2, 0.3])             # two below the range, one inside, one above
    length = np.array([10.0, 30.0, 40.0, 20.0])
    r = curvature_reach(law, kappa, [6.0] * 4, ["front"] * 4, length, 0.2, diagonal_mm=100.0)
    f = r["front"]
    assert f["law_range_per_mm"] == pytest.approx([lo, hi])
    assert f["length_below_range"] == pytest.approx(0.4) and f["length_above_range"] == pytest.approx(0.2)
    assert f["asked_per_mm"]["p50"] == pytest.approx(0.2)      # length-weighted median
    # curvature scales as 1/size: the median 0.2 is in range for diagonals 100 * 0.2 / [hi, lo]
    assert r["diagonal_in_range_mm"] == pytest.approx([100 * 0.2 / hi, 100 * 0.2 / lo])
    assert reach_warning(r) is None                            # 40 % below: not most of it
    r = curvature_reach(law, kappa / 10, [6.0] * 4, ["front"] * 4, length, 0.2, diagonal_mm=100.0,
                        min_diagonal_mm=60.0)
    assert r["front"]["length_below_range"] == 1.0
    assert r["diagonal_in_range_mm"] is None                   # it would need < 60 mm
    assert "100 % of the ribbon length asks for less curvature" in reach_warning(r)
    assert "no size of this target" in reach_warning(r)
    assert "finer layers" not in reach_warning(r)            # 1.0 mm, the law's thickest, is printable
    # with 0.3 mm layers the thickest printable row is 0.9 mm: the warning names the finer printer
    r = curvature_reach(law, kappa / 10, [6.0] * 4, ["front"] * 4, length, 0.3, diagonal_mm=100.0,
                        min_diagonal_mm=60.0)
    assert r["front"]["law_thickness_mm"][1] == 1.0 and r["front"]["printable_thickness_mm"][1] < 1.0
    assert "the law's 1 mm row is not a multiple of the printer's layers" in reach_warning(r)


def test_reach_warning_does_not_predict_a_curl_for_ribbons_along_twist_directions():
    from inverse.thickness_law import curvature_reach, reach_warning
    law = parse_thickness_law(table_text())
    length = np.array([10.0, 30.0, 40.0, 20.0])
    # ribbons asking for almost no curvature: the law's lowest is far above, a curl is predicted...
    r = curvature_reach(law, np.full(4, 1e-7), [6.0] * 4, ["front"] * 4, length, 0.2, diagonal_mm=100.0)
    assert "will curl more than the target" in reach_warning(r)
    # ...unless they run where the target hardly bends (a minimal surface's asymptotic lines)
    r["bend_share"] = 0.01
    w = reach_warning(r)
    assert "hardly bends (1 % of its largest principal curvature" in w and "--verify" in w
    assert "curl" not in w
    r["bend_share"] = 0.9                                         # a principal field: the law's statement
    assert "will curl more than the target" in reach_warning(r)
