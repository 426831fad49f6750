"""CAD exports (geometry.cad): the flat pattern as DXF and SVG in mm with a layer per side and
thickness, the deployed surface as OBJ/STL/PLY; each read back (ezdxf, xml.etree, meshio).
End to end: `selfshape simulate` and `design` write them beside their other outputs."""
import json
import os

import meshio
import numpy as np
import pytest

from geometry import cad
from geometry.patterns import load_pattern, parse_pattern
from selfshape.cli import main
from shellfem.outfiles import NonFiniteOutput, write_atomic

ROOT = os.path.join(os.path.dirname(__file__), "..")
EXAMPLE = os.path.join(ROOT, "examples", "strip_narrow.toml")

#: a 40 x 20 mm fabric with a front region holding a hole, a back region and a front ribbon
PATTERN = {
    "fabric": {"rectangle": [40.0, 20.0], "stretch": 1.3},
    "region": [{"polygon": [[2, 2], [18, 2], [18, 18], [2, 18]], "thickness_mm": 0.4, "side": "front"},
               {"polygon": [[22, 2], [38, 2], [38, 8], [22, 8]], "thickness_mm": 0.8, "side": "back"}],
    "ribbon": [{"path": [[22, 14], [38, 14]], "width_mm": 2.0, "thickness_mm": 0.4, "side": "front"}],
}


def _pattern():
    return parse_pattern(PATTERN, "t.toml", ROOT)


def _same(a, b, tol=1e-3):
    """Two drawings hold the same shapes (layer, closed flag, points within ``tol`` mm), in any order."""
    if len(a) != len(b):
        return False
    left = list(b)
    for s in a:
        hit = next((i for i, t in enumerate(left) if t.layer == s.layer and t.closed == s.closed and
                    t.points.shape == s.points.shape and np.abs(t.points - s.points).max() <= tol), None)
        if hit is None:
            return False
        left.pop(hit)
    return True


def test_pattern_drawing_has_a_layer_per_side_and_thickness():
    d = cad.pattern_drawing(_pattern())
    layers = [s.layer for s in d]
    assert layers.count("fabric") == 1
    assert set(layers) == {"fabric", "front_0.40mm", "back_0.80mm"}
    fabric = next(s for s in d if s.layer == "fabric")
    assert np.allclose(fabric.points.min(0), [0, 0]) and np.allclose(fabric.points.max(0), [40, 20])
    ribbon = [s for s in d if s.layer == "front_0.40mm" and s.points[:, 1].min() > 10]
    assert len(ribbon) == 1 and np.allclose(np.ptp(ribbon[0].points[:, 1]), 2.0)   # width 2 mm
    assert all(s.closed for s in d)


def test_fabric_holes_are_drawn_on_the_fabric_layer(tmp_path):
    raw = {**PATTERN, "fabric": {**PATTERN["fabric"], "holes": [[[25, 10], [30, 10], [30, 12], [25, 12]]]}}
    d = cad.pattern_drawing(parse_pattern(raw, "t.toml", ROOT))
    fabric = sorted((s for s in d if s.layer == "fabric"), key=lambda s: -np.ptp(s.points[:, 0]))
    assert len(fabric) == 2 and all(s.closed for s in fabric)
    assert np.allclose(fabric[1].points.min(0), [25, 10]) and np.allclose(fabric[1].points.max(0), [30, 12])
    cad.write_drawing(os.path.join(tmp_path, "p.dxf"), d)
    assert _same(cad.read_drawing(os.path.join(tmp_path, "p.dxf")), d)


def test_dxf_round_trip_in_mm_with_layers(tmp_path):
    import ezdxf
    d = cad.pattern_drawing(_pattern())
    p = str(tmp_path / "pattern.dxf")
    write_atomic(p, lambda tmp: cad.write_dxf(tmp, d))
    shapes, insunits = cad.read_dxf(p)
    assert insunits == 4                                   # millimetres
    assert _same(shapes, d) and all(s.closed for s in shapes)
    doc = ezdxf.readfile(p)
    assert doc.header["$MEASUREMENT"] == 1
    assert doc.header["$EXTMIN"][:2] == pytest.approx((0, 0)) and doc.header["$EXTMAX"][:2] == pytest.approx((40, 20))
    assert {"fabric", "front_0.40mm", "back_0.80mm"} <= {layer.dxf.name for layer in doc.layers}
    assert doc.layers.get("front_0.40mm").color == 1 and doc.layers.get("back_0.80mm").color == 5
    assert {e.dxftype() for e in doc.modelspace()} == {"LWPOLYLINE"}
    auditor = doc.audit()                                  # what a CAD program would complain about
    assert not auditor.has_errors and not auditor.has_fixes


def test_svg_round_trip_size_and_viewbox_in_mm(tmp_path):
    import xml.etree.ElementTree as ET
    d = cad.pattern_drawing(_pattern())
    p = str(tmp_path / "pattern.svg")
    write_atomic(p, lambda tmp: cad.write_svg(tmp, d, margin_mm=2.0))
    shapes, info = cad.read_svg(p)
    assert _same(shapes, d)
    assert info["width_mm"] == pytest.approx(44.0) and info["height_mm"] == pytest.approx(24.0)
    x0, y0, w, h = info["viewbox"]
    assert (x0, w, h) == pytest.approx((-2.0, 44.0, 24.0)) and y0 == pytest.approx(-22.0)   # y up: -ymax
    root = ET.parse(p).getroot()
    groups = [g.get("id") for g in root.iter("{http://www.w3.org/2000/svg}g")]
    assert groups == ["fabric", "front_0.40mm", "back_0.80mm"]
    assert root.get("width").endswith("mm") and root.get("height").endswith("mm")


@pytest.mark.parametrize("suffix", [".obj", ".stl", ".ply"])
def test_surface_round_trip(tmp_path, suffix):
    from geometry.target import cylinder_patch
    V, F = cylinder_patch(n_arc=8, n_len=5)
    V = V * 10.0
    p = str(tmp_path / f"deployed{suffix}")
    write_atomic(p, lambda tmp: cad.write_surface(tmp, V, F))
    X, T = cad.read_surface(p)
    assert len(T) == len(F)
    assert np.allclose(X[T], V[F], atol=1e-4 * np.abs(V).max())      # STL is float32, corners merged


def test_one_call_per_job_by_suffix(tmp_path):
    from shellfem.errors import SelfshapeError
    d = cad.pattern_drawing(_pattern())
    for name in ("p.dxf", "p.SVG"):
        cad.write_drawing(str(tmp_path / name), d)
        assert _same(cad.read_drawing(str(tmp_path / name)), d)
    for name in ("p.png", "p"):
        with pytest.raises(SelfshapeError, match=".dxf or .svg"):
            cad.write_drawing(str(tmp_path / name), d)
    with pytest.raises(SelfshapeError, match=".obj"):
        cad.write_surface(str(tmp_path / "s.vtk"), np.zeros((3, 3)), [[0, 1, 2]])


def test_non_finite_coordinates_are_refused_and_nothing_written(tmp_path):
    bad = [cad.Shape(np.array([[0.0, 0.0], [1.0, np.nan], [0.0, 1.0]]), "fabric")]
    for name, fn in (("p.dxf", cad.write_dxf), ("p.svg", cad.write_svg)):
        with pytest.raises(NonFiniteOutput, match="shape 1"):
            write_atomic(str(tmp_path / name), lambda tmp: fn(tmp, bad))
    with pytest.raises(NonFiniteOutput, match="positions"):
        write_atomic(str(tmp_path / "d.obj"),
                     lambda tmp: cad.write_surface(tmp, np.array([[0, 0, np.inf], [1, 0, 0], [0, 1, 0]]), [[0, 1, 2]]))
    assert os.listdir(tmp_path) == []


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "strip"
    assert main(["simulate", EXAMPLE, "-o", str(out), "--size", "3", "--no-png"]) == 0
    return out


def test_simulate_writes_the_cad_files(simulated):
    vtu = meshio.read(simulated / "deployed.vtu")
    for suffix in (".obj", ".stl", ".ply"):
        X, T = cad.read_surface(str(simulated / f"deployed{suffix}"))
        assert np.allclose(X[T], vtu.points[vtu.cells_dict["triangle"]], atol=1e-4)
    shapes, units = cad.read_dxf(str(simulated / "pattern.dxf"))
    assert units == 4
    assert _same(shapes, cad.pattern_drawing(load_pattern(EXAMPLE)))
    svg, info = cad.read_svg(str(simulated / "pattern.svg"))
    assert _same(svg, shapes)
    assert "index.html" in os.listdir(simulated)
    assert json.loads((simulated / "summary.json").read_text())["converged"] is True


def test_design_writes_the_flat_pattern_per_side(tmp_path):
    """design (no verify): pattern.dxf/.svg hold the fabric outline of pattern.toml and the
    ribbons on front_/back_ layers, as the written pattern clips them."""
    from geometry.target import cylinder_patch
    from inverse.design import design_file
    V, F = cylinder_patch(n_arc=16, n_len=12)
    target = tmp_path / "cyl.obj"
    with open(target, "w") as f:
        f.writelines(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in V)
        f.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F)
    out = tmp_path / "d"
    rep = design_file(str(target), str(out), edge_mm=2.0)
    assert {"pattern.dxf", "pattern.svg", "index.html"} <= set(rep["files"])
    pattern = load_pattern(str(out / "pattern.toml"))
    shapes, units = cad.read_dxf(str(out / "pattern.dxf"))
    assert units == 4
    assert _same(shapes, cad.pattern_drawing(pattern))
    layers = {s.layer for s in shapes}
    assert "fabric" in layers and any(x.startswith(("front_", "back_")) for x in layers)
    sides = {r["side"] for r in pattern.raw["ribbon"]}
    assert {x.split("_")[0] for x in layers} - {"fabric"} == sides
    svg, _ = cad.read_svg(str(out / "pattern.svg"))
    assert _same(svg, shapes)


def test_export_verb_writes_the_drawing_without_simulating(tmp_path, capsys):
    for name in ("strip.dxf", "strip.svg"):
        out = tmp_path / name
        assert main(["export", EXAMPLE, "-o", str(out)]) == 0
        assert capsys.readouterr().out.startswith(f"wrote {out}: 2 polylines on layers fabric, front_0.30mm")
        assert _same(cad.read_drawing(str(out)), cad.pattern_drawing(load_pattern(EXAMPLE)))
    for bad, names in ((tmp_path / "strip.png", "must be a .dxf or .svg"), (tmp_path, "is a folder"),
                       (tmp_path / "no" / "such" / "x.dxf", None)):
        rc = main(["export", EXAMPLE, "-o", str(bad)])
        err = capsys.readouterr().err.splitlines()
        if names is None:                     # a missing folder is created, as for the other verbs
            assert rc == 0 and bad.is_file()
            continue
        assert rc == 2 and len(err) == 1 and names in err[0] and str(bad) in err[0], err
    assert main(["export", str(tmp_path / "missing.toml"), "-o", str(tmp_path / "m.dxf")]) == 2
    assert len(capsys.readouterr().err.splitlines()) == 1
