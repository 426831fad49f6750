import math
import os

import gmsh
import meshio
import numpy as np
import pytest
import shapely

from geometry.arrangement import feature_width, piece_regions, printed_pieces, region_elements
from geometry.mesh_quality import mesh_quality
from geometry.meshing import mesh_pattern, mesh_pattern_file, quantise_size
from geometry.meshops import triangle_angles
from geometry.msh import read_msh
from geometry.patterns import load_pattern
from geometry.schema import DETAIL_MM
from geometry.stars import star_polygons
from shellfem.errors import SelfshapeError
from shellfem.sheet import Sheet

HERE = os.path.dirname(__file__)
EXAMPLES = os.path.join(HERE, "..", "examples")
STAR_C, STAR_L, STAR_W = (8.0, 19.0), 6.0, 0.8


def _raw():
    star = np.asarray(star_polygons([STAR_C], STAR_L, STAR_W)[0].exterior.coords)[:-1].tolist()
    return {
        "fabric": {"rectangle": [30.0, 26.0]},
        "region": [
            {"polygon": [[2, 2], [12, 2], [12, 12], [2, 12]], "thickness_mm": 0.3},               # A
            {"polygon": [[8, 8], [16, 8], [16, 14], [8, 14]], "thickness_mm": 0.2},               # B overlaps A
            {"polygon": [[20, 12], [26, 12], [26, 18], [20, 18]], "thickness_mm": 0.25},          # D alone
            {"polygon": star, "thickness_mm": 0.35},                                              # a star
        ],
        "ribbon": [{"path": [[4, 6], [29, 6]], "width_mm": 1.5, "thickness_mm": 0.4, "side": "back"}],  # C
        "mesh": {"size_mm": 2.0},
    }


@pytest.fixture(scope="module", params=["geo", "occ"])
def case(request):
    p = load_pattern(_raw())
    return p, mesh_pattern(p, kernel=request.param)


def _areas(sheet):
    p = sheet.points[sheet.triangles]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def test_gmsh_left_clean(case):
    assert not gmsh.isInitialized()


def test_total_and_region_areas(case):
    p, s = case
    a = _areas(s)
    assert a.sum() == pytest.approx(p.outline.area, rel=1e-12)
    union = shapely.union_all([e.geometry for e in p.elements])
    comps = sorted(shapely.get_parts(union), key=lambda g: -g.area)
    assert len(np.unique(s.region)) == 4                        # fabric + 3 printed regions
    # regions numbered by their first element: {A, B, C} = 1, D = 2, star = 3
    assert region_elements(p) == [[0, 1, 4], [2], [3]]
    expected = {1: comps[0].area, 2: 36.0, 3: 3 * STAR_L * STAR_W - math.sqrt(3) / 4 * STAR_W ** 2}
    for k, area in expected.items():
        assert a[s.region == k].sum() == pytest.approx(area, rel=1e-5)   # vertices snapped to 1e-5 mm
    assert a[s.region == 0].sum() == pytest.approx(p.outline.area - union.area, rel=1e-5)


def test_conforming_thickness_is_the_sum_of_what_covers_each_triangle(case):
    p, s = case
    c = s.points[s.triangles].mean(axis=1)
    front, back = np.zeros(len(c)), np.zeros(len(c))
    for e in p.elements:
        inside = shapely.contains_xy(e.geometry, c[:, 0], c[:, 1])
        (front if e.side == "front" else back)[inside] += e.thickness_mm
    np.testing.assert_allclose(s.thickness_front, front, atol=1e-12)
    np.testing.assert_allclose(s.thickness_back, back, atol=1e-12)
    # every triangle lies entirely in or out of each element: vertices too
    for e in p.elements:
        g = e.geometry.buffer(1e-4)          # geometry is snapped to a 1e-5 mm grid
        inside = shapely.contains_xy(e.geometry, c[:, 0], c[:, 1])
        v = s.points[s.triangles[inside]].reshape(-1, 2)
        assert shapely.contains_xy(g, v[:, 0], v[:, 1]).all()
    # the overlaps: A+B on the front, A (front) + C (back) on both faces
    assert np.isclose(s.thickness_front, 0.5).any() and np.isclose(s.thickness_front, 0.3).any()
    both = (s.thickness_front > 0) & (s.thickness_back > 0)
    assert both.any() and np.allclose(s.thickness_back[both], 0.4)
    assert set(np.round(s.thickness_front[both], 9)) == {0.3}
    assert (s.region[s.printed] > 0).all() and (s.region[~s.printed] == 0).all()


def _check_conforming(p, s):
    """Exact thickness by centroid; every edge in 1 or 2 triangles; open edges on the outline."""
    c = s.points[s.triangles].mean(axis=1)
    front, back = np.zeros(len(c)), np.zeros(len(c))
    for e in p.elements:
        inside = shapely.contains_xy(e.geometry, c[:, 0], c[:, 1])
        (front if e.side == "front" else back)[inside] += e.thickness_mm
    np.testing.assert_allclose(s.thickness_front, front, atol=1e-12)
    np.testing.assert_allclose(s.thickness_back, back, atol=1e-12)
    e = np.sort(np.vstack([s.triangles[:, [0, 1]], s.triangles[:, [1, 2]], s.triangles[:, [2, 0]]]), axis=1)
    edges, count = np.unique(e, axis=0, return_counts=True)
    assert count.max() == 2
    mid = s.points[edges[count == 1]].mean(axis=1)
    assert (shapely.distance(p.outline.exterior, shapely.points(mid)) < 1e-6).all()   # no hanging nodes
    assert _areas(s).sum() == pytest.approx(p.outline.area, rel=1e-12)


def test_no_hanging_nodes(case):
    _check_conforming(*case)


@pytest.mark.parametrize("kernel", ["geo", "occ"])
def test_random_overlapping_ribbons_conform(kernel):
    rng = np.random.default_rng(1)
    ribbons = []
    for i in range(25):
        a = rng.uniform(0, 40, 2)
        d = rng.normal(size=2)
        d /= np.linalg.norm(d)
        path = [a, a + rng.uniform(5, 30) * d]
        if i % 3 == 0:
            path.append(path[1] + rng.uniform(3, 10) * np.array([-d[1], d[0]]))
        ribbons.append({"path": np.array(path).tolist(), "width_mm": float(rng.uniform(0.8, 2.0)),
                        "thickness_mm": float(rng.uniform(0.1, 0.5)), "side": "front" if i % 5 else "back",
                        "ends": "round" if i % 4 == 0 else "square"})
    ribbons.append({"path": [[5, 5], [15, 5], [15, 15], [5, 15], [5, 5]], "width_mm": 1.5, "thickness_mm": 0.3})
    p = load_pattern({"fabric": {"rectangle": [40.0, 40.0]}, "ribbon": ribbons, "mesh": {"size_mm": 2.0}})
    s = mesh_pattern(p, kernel=kernel)
    _check_conforming(p, s)
    union = shapely.union_all([e.geometry for e in p.elements])
    assert _areas(s)[s.printed].sum() == pytest.approx(union.area, rel=1e-5)
    assert s.region.max() == len(shapely.get_parts(union))


def test_regions_are_connected_components(case):
    p, s = case
    c = s.points[s.triangles].mean(axis=1)
    geoms, _, _, owner = printed_pieces(p.elements)
    reg = piece_regions(geoms)
    for k in range(1, 4):
        g = shapely.union_all(geoms[reg == k])
        assert shapely.contains_xy(g, c[s.region == k, 0], c[s.region == k, 1]).all()


def _triangles_across(s, a, b):
    """Triangles whose interior a segment a-b crosses."""
    seg = shapely.linestrings([a, b])
    tris = shapely.polygons(s.points[s.triangles])
    hit = shapely.intersection(tris, seg)
    return int((shapely.length(hit) > 1e-9).sum())


def test_quality_and_resolution_of_narrow_features(case):
    p, s = case
    q = mesh_quality(s)
    assert q["min_angle_deg"] > 15.0
    assert q["edge_max_mm"] < 2.0 * 1.5                       # fabric at about size_mm
    # a 0.8 mm star arm (along +x from the star centre) has 2+ triangles across everywhere
    cx, cy = STAR_C
    counts = [_triangles_across(s, (cx + t, cy - 0.4), (cx + t, cy + 0.4)) for t in np.linspace(1.0, 5.5, 10)]
    assert min(counts) >= 2
    inner = (np.abs(s.points[:, 1] - cy) < 0.3) & (s.points[:, 0] > cx + 1) & (s.points[:, 0] < cx + 5.5)
    assert inner.sum() >= 3                                    # nodes inside the arm, not only on its edges
    counts = [_triangles_across(s, (x, 6 - 0.75), (x, 6 + 0.75)) for x in np.linspace(17, 28, 8)]
    assert min(counts) >= 2                                    # the 1.5 mm ribbon
    # fabric far from the print is not over-refined: its triangles reach the target size
    c = s.points[s.triangles].mean(axis=1)
    far = shapely.distance(shapely.union_all([e.geometry for e in p.elements]), shapely.points(c)) > 4.0
    edge = np.sqrt(4 / math.sqrt(3) * _areas(s))
    assert far.sum() > 10 and np.median(edge[far]) > 0.75 * 2.0


def test_msh_round_trip(tmp_path, case):
    p, s = case
    out = tmp_path / "case.msh"
    info = mesh_pattern_file(_write(tmp_path, p.raw), out)
    assert not gmsh.isInitialized()
    assert set(info) == {"n_vertices", "n_triangles", "n_regions", "min_angle_deg", "time_s"}
    assert info["n_regions"] == 3 and info["min_angle_deg"] > 15
    back = read_msh(out)
    assert (back.n_vertices, back.n_triangles) == (info["n_vertices"], info["n_triangles"])
    m = meshio.read(out)
    assert {k: int(v[0]) for k, v in m.field_data.items()} == {"region_1": 1, "region_2": 2, "region_3": 3,
                                                                "fabric": 4}
    assert set(m.cell_data) >= {"thickness_front", "thickness_back", "region", "gmsh:physical"}
    assert not any(k.startswith("gmsh:") for k in back.__dict__)
    # read back: same areas per region, and thickness still matches the geometry
    a = _areas(back)
    for k in range(4):
        assert a[back.region == k].sum() == pytest.approx(_areas(s)[s.region == k].sum(), rel=1e-9)
    c = back.points[back.triangles].mean(axis=1)
    front = sum(e.thickness_mm * shapely.contains_xy(e.geometry, c[:, 0], c[:, 1])
                for e in p.elements if e.side == "front")
    np.testing.assert_allclose(back.thickness_front, front, atol=1e-12)
    assert not list(tmp_path.glob("*partial*")) and not list(tmp_path.glob(".*"))   # no temporary file left


def _write(tmp_path, raw):
    import tomli_w
    f = tmp_path / "pattern.toml"
    f.write_bytes(tomli_w.dumps(raw).encode())
    return f


def test_strip_example_is_small_and_fully_printed():
    p = load_pattern(os.path.join(EXAMPLES, "strip.toml"))
    s = mesh_pattern(p)
    q = mesh_quality(s)
    assert q["n_triangles"] < 3000 and q["min_angle_deg"] > 15
    assert q["area_mm2"] == pytest.approx(400.0, rel=1e-12) and q["printed_area_mm2"] == pytest.approx(400.0)
    assert (s.region == 1).all() and np.allclose(s.thickness_front, 0.3) and (s.thickness_back == 0).all()


def test_size_override_and_errors_leave_gmsh_finalised():
    p = load_pattern(os.path.join(EXAMPLES, "strip.toml"))
    coarse = mesh_pattern(p, size_mm=2.5)
    assert coarse.n_triangles < mesh_pattern(p).n_triangles / 4
    for bad in (-1.0, float("nan"), 1e-5):
        with pytest.raises(SelfshapeError, match="mesh size"):
            mesh_pattern(p, size_mm=bad)
        assert not gmsh.isInitialized()


def test_mesh_file_errors(tmp_path):
    strip = os.path.join(EXAMPLES, "strip.toml")
    with pytest.raises(SelfshapeError, match=r"must be a \.msh file"):
        mesh_pattern_file(strip, tmp_path / "out.vtk")
    with pytest.raises(SelfshapeError, match="does not exist"):
        mesh_pattern_file(strip, tmp_path / "no" / "out.msh")
    with pytest.raises(SelfshapeError, match="file not found"):
        read_msh(tmp_path / "none.msh")
    (tmp_path / "junk.msh").write_text("not a mesh\n")
    with pytest.raises(SelfshapeError, match="junk.msh: cannot read the Gmsh mesh"):
        read_msh(tmp_path / "junk.msh")
    (tmp_path / "cut.msh").write_text("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 3 1 3\n")
    with pytest.raises(SelfshapeError, match="cut.msh: cannot read the Gmsh mesh"):
        read_msh(tmp_path / "cut.msh")


def test_cli_mesh(tmp_path, capsys):
    from selfshape.cli import main
    out = tmp_path / "strip.msh"
    assert main(["mesh", os.path.join(EXAMPLES, "strip.toml"), "-o", str(out), "--size", "2"]) == 0
    assert out.exists() and "printed regions" in capsys.readouterr().out
    bad = tmp_path / "bad.toml"
    bad.write_text("[fabric]\nrectangle = [10, 10]\n[[region]]\npolygon = [[1, 1], [5, 5], [5, 1], [1, 5]]\n"
                   "thickness_mm = 0.3\n")
    assert main(["mesh", str(bad), "-o", str(tmp_path / "bad.msh")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("[[region]] #1: polygon is self-intersecting at (3, 3)") and "\n" not in err
    assert not (tmp_path / "bad.msh").exists()


def test_gcode_input(tmp_path):
    g = os.path.join(HERE, "data", "patterns", "two_lines.gcode")
    info = mesh_pattern_file(g, tmp_path / "print.msh", size_mm=3.0)
    s = read_msh(tmp_path / "print.msh")
    assert info["n_regions"] == 2
    a = _areas(s)
    assert a.sum() == pytest.approx((31.5 + 20) * (11.5 + 20), rel=1e-9)    # bbox + 10 mm margin
    assert a[s.region > 0].sum() == pytest.approx(2 * 31.5 * 1.5, rel=1e-9)
    assert np.allclose(s.thickness_front[s.region > 0], 0.4)


def _region_pattern(points):
    return load_pattern({"fabric": {"rectangle": [80.0, 12.0], "stretch": 1.35}, "mesh": {"size_mm": 2.0},
                         "region": [{"polygon": np.asarray(points).tolist(), "thickness_mm": 0.3}]})


def test_detail_below_a_tenth_of_a_micron_is_dropped_before_meshing():
    """A region given as a 100,000-point circle (a CAD export) is simplified to the detail
    that matters (geometry.schema.DETAIL_MM): issue 19 found it > 60 s in Gmsh's boundary
    set-up (quadratic in a loop's vertices) and meshed into 0.0 deg slivers."""
    t = 2 * np.pi * np.arange(100_000) / 100_000
    pattern = _region_pattern(np.column_stack([40 + 3 * np.cos(t), 6 + 3 * np.sin(t)]))
    geom = pattern.elements[0].geometry
    assert shapely.get_num_coordinates(geom) < 1000
    assert abs(geom.area - math.pi * 9) <= DETAIL_MM * 2 * math.pi * 3      # each vertex moves < DETAIL_MM
    q = mesh_quality(mesh_pattern(pattern))       # the points Gmsh must keep are ~0.02 mm apart
    assert q["min_angle_deg"] > 2.0 and q["n_vertices"] < 5000, q


def test_a_polygon_with_too_many_vertices_is_refused_before_gmsh():
    """Detail above DETAIL_MM is kept, so an outline of 60,000 teeth 1 um high stays: it is
    refused in one line naming the element before Gmsh would take minutes on it."""
    x = np.linspace(10, 70, 60_001)
    teeth = np.column_stack([x, 2 + 1e-3 * (np.arange(len(x)) % 2)])
    pattern = _region_pattern(np.vstack([teeth, [[70, 10], [10, 10]]]))
    with pytest.raises(SelfshapeError, match=r"region #1 has 60,00\d boundary vertices .* more than the 50,000"):
        mesh_pattern(pattern)


def test_helpers_on_known_values():
    s = Sheet.rectangle(2.0, 1.0, 2, 1)
    q = mesh_quality(s)
    assert q["min_angle_deg"] == pytest.approx(45.0) and q["max_angle_deg"] == pytest.approx(90.0)
    assert q["area_mm2"] == pytest.approx(2.0) and q["n_regions"] == 0 and q["edge_max_mm"] == pytest.approx(math.sqrt(2))
    ang = triangle_angles(np.array([[0, 0], [1, 0], [0.5, math.sqrt(3) / 2]]), np.array([[0, 1, 2]]))
    np.testing.assert_allclose(ang, 60.0)
    np.testing.assert_allclose(quantise_size([0.4, 0.45, 0.47, 3.0], 2.0), [0.4, 0.4, 0.46, 2.0])
    strip = shapely.box(0, 0, 100, 1.5)
    assert feature_width(np.array([strip]))[0] == pytest.approx(2 * 150 / 203)


def _msh2(path, nodes, triangles, thickness_front=None):
    """A Gmsh 2.2 ASCII file with the given nodes (n, 3), triangles (1-based) and optional
    element data thickness_front."""
    lines = ["$MeshFormat", "2.2 0 8", "$EndMeshFormat", "$Nodes", str(len(nodes))]
    lines += [f"{i + 1} {x!r} {y!r} {z!r}" for i, (x, y, z) in enumerate(nodes)]
    lines += ["$EndNodes", "$Elements", str(len(triangles))]
    lines += [f"{i + 1} 2 2 0 1 {a} {b} {c}" for i, (a, b, c) in enumerate(triangles)]
    lines += ["$EndElements"]
    if thickness_front is not None:
        lines += ["$ElementData", "1", '"thickness_front"', "1", "0.0", "3", "0", "1", str(len(triangles))]
        lines += [f"{i + 1} {v!r}" for i, v in enumerate(thickness_front)]
        lines += ["$EndElementData"]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("nodes, tris, tf, word", [
    ([(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)], [(1, 2, 3), (2, 4, 3)], [0.3, float("nan")],
     "thickness_front of triangle 1"),
    ([(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)], [(1, 2, 3), (2, 4, 3)], [0.3, -0.1],
     "thickness_front of triangle 1"),
    ([(0, 0, 0), (1, 0, 0), (0, 1, 0), (2, 0, 0)], [(1, 2, 3), (1, 2, 4)], None, "triangle 1 has zero area"),
    ([(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)], [(1, 2, 3), (2, 2, 3)], None, "triangle 1 has zero area"),
    ([(0, 0, 0), (1, 0, 0), (0, float("inf"), 0), (1, 1, 0)], [(1, 2, 3), (2, 4, 3)], None,
     "node 2 has a non-finite coordinate"),
])
def test_msh_reader_refuses_what_is_not_a_printed_sheet(tmp_path, nodes, tris, tf, word):
    path = _msh2(tmp_path / "m.msh", nodes, tris, tf)
    with pytest.raises(SelfshapeError) as e:
        read_msh(path)
    assert word in str(e.value) and "m.msh" in str(e.value) and "\n" not in str(e.value)
    ok = _msh2(tmp_path / "ok.msh", [(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)], [(1, 2, 3), (2, 4, 3)], [0.3, 0.0])
    s = read_msh(ok)
    assert s.n_triangles == 2 and list(s.thickness_front) == [0.3, 0.0]


@pytest.mark.parametrize("kernel", ["geo", "occ"])
def test_fabric_holes_are_left_out_of_the_mesh(kernel):
    # ribbons and a region around two holes: the mesh covers the fabric without them, conforms to
    # the clipped print, and has one boundary loop per hole besides the outer edge
    from geometry.meshops import boundary_loop_count
    raw = {"fabric": {"disk": 20.0, "holes": [[[-8, -3], [-2, -3], [-2, 3], [-8, 3]], [[3, 3], [9, 3], [6, 9]]]},
           "region": [{"polygon": [[-10, -10], [0, -10], [0, -5], [-10, -5]], "thickness_mm": 0.3}],
           "ribbon": [{"path": [[-19, 0], [19, 0]], "width_mm": 1.5, "thickness_mm": 0.4},
                      {"path": [[6, -15], [6, 15]], "width_mm": 1.5, "thickness_mm": 0.3, "side": "back"}],
           "mesh": {"size_mm": 1.5}}
    p = load_pattern(raw)
    s = mesh_pattern(p, kernel=kernel)
    a = _areas(s)
    assert a.sum() == pytest.approx(p.outline.area, rel=1e-6)       # vertices snapped to 1e-5 mm
    assert boundary_loop_count(s.triangles, len(s.points)) == 3
    c = s.points[s.triangles].mean(axis=1)
    assert not shapely.contains_xy(shapely.union_all([shapely.Polygon(h) for h in p.outline.interiors]), c[:, 0], c[:, 1]).any()
    printed = shapely.union_all([e.geometry for e in p.elements])
    assert a[(s.thickness_front + s.thickness_back) > 0].sum() == pytest.approx(printed.area, rel=1e-5)

