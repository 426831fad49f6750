import math

import numpy as np
import pytest
import shapely
from shapely.geometry import Point

from geometry.outlines import hexagon, rectangle
from geometry.stars import lattice_points, star_elements, star_polygons
from shellfem.errors import SelfshapeError


def centred_hexagonal(n):
    """Lattice nodes within n rings of the centre: 3 n (n + 1) + 1."""
    return 3 * n * (n + 1) + 1


@pytest.mark.parametrize("spacing", [12.0, 16.0, 18.0, 22.3, 22.4, 30.0])
def test_star_count_on_hexagon(spacing):
    # hexagon of side 67 mm, vertex on +x, same orientation as the lattice: ring k is
    # inside iff k d <= 67, so floor(67 / d) full rings (seed Fig. 3.7: 37 stars)
    n = len(star_elements(hexagon(67.0), spacing, 0.5, 0.3, 0.8))
    assert n == centred_hexagonal(math.floor(67.0 / spacing))


def test_seed_figure_3_7_has_37_stars_and_zero_arm_length_omits():
    out = hexagon(67.0)
    assert len(star_elements(out, 18.0, 0.5, 0.3, 0.8)) == 37
    # ring 3 (r >= 3 * 18 * cos 30 = 46.8 mm) omitted -> 19 stars; ring 2 too -> 7
    assert len(star_elements(out, 18.0, "where(r > 46, 0, 0.5)", 0.3, 0.8)) == 19
    assert len(star_elements(out, 18.0, "where(r > 30, 0, 0.5)", 0.3, 0.8)) == 7
    assert len(star_elements(out, 18.0, 0.0, 0.3, 0.8)) == 0


def test_lattice_geometry():
    pts, idx = lattice_points(hexagon(67.0), 18.0)
    assert len(pts) == 37
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    np.fill_diagonal(d, np.inf)
    np.testing.assert_allclose(d.min(axis=1), 18.0, rtol=1e-12)           # nearest neighbours at d
    centre = np.flatnonzero((idx == 0).all(axis=1))[0]
    np.testing.assert_allclose(pts[centre], [0.0, 0.0], atol=1e-12)       # through the centroid
    nbr = pts[np.isclose(d[centre], 18.0)]
    ang = np.sort(np.degrees(np.arctan2(nbr[:, 1], nbr[:, 0])) % 360)
    np.testing.assert_allclose(ang, [0, 60, 120, 180, 240, 300], atol=1e-9)


def test_star_shape_area_and_arms():
    L, w = 7.0, 0.8
    s = star_polygons([[3.0, -2.0]], L, w)[0]
    assert s.is_valid and len(s.exterior.coords) == 10
    # three L x w arms minus the two-fold covered centre: 3 L w - (sqrt 3 / 4) w^2
    assert s.area == pytest.approx(3 * L * w - math.sqrt(3) / 4 * w * w, rel=1e-12)
    for a in (0, 120, 240):            # arms along the lattice axes, square tips at L
        t = np.radians(a)
        tip = np.array([3.0, -2.0]) + (L - 1e-6) * np.array([math.cos(t), math.sin(t)])
        assert s.covers(Point(tip))
        assert not s.covers(Point(np.array([3.0, -2.0]) + (L + 1e-6) * np.array([math.cos(t), math.sin(t)])))
    assert not s.covers(Point(3.0 - 1.0, -2.0))                        # no arm along 180 deg
    # short arms fall back to the exact union of the three rectangles
    tiny = star_polygons([[0.0, 0.0]], 0.1, 0.8)[0]
    assert tiny.is_valid and 0 < tiny.area < 3 * 0.1 * 0.8


def test_fields_evaluated_at_star_centres():
    out = hexagon(67.0)
    el = star_elements(out, 18.0, "0.2 + 0.005 * r", "0.2 + 0.004 * r", "0.6 + 0.01 * x / 18", side="back")
    assert len(el) == 37
    for e in el:
        i, j = (int(v) for v in e.label.split("(")[1].rstrip(")").split(","))
        c = np.array([18.0 * (i + 0.5 * j), 18.0 * math.sqrt(3) / 2 * j])
        r = np.hypot(*c)
        L, w = (0.2 + 0.005 * r) * 18.0, 0.6 + 0.01 * c[0] / 18
        assert e.thickness_mm == pytest.approx(0.2 + 0.004 * r, rel=1e-12)
        assert e.side == "back" and e.kind == "star"
        full = 3 * L * w - math.sqrt(3) / 4 * w * w
        if e.geometry.within(out):
            assert e.geometry.area == pytest.approx(full, rel=1e-9)


def test_stars_are_clipped_to_the_fabric():
    out = rectangle(50.0, 30.0)
    el = star_elements(out, 10.0, 0.9, 0.3, 0.8)
    clipped = 0
    for e in el:
        assert out.buffer(1e-9).covers(e.geometry)
        clipped += e.geometry.area < 3 * 9 * 0.8 - math.sqrt(3) / 4 * 0.64 - 1e-9
    assert clipped > 0
    # one element per lattice node, and together they print the unclipped stars cut by the fabric
    centres, _ = lattice_points(out, 10.0)
    assert len(el) == len(centres)
    cut = shapely.union_all(star_polygons(centres, 9.0, 0.8)).intersection(out)
    assert sum(e.geometry.area for e in el) == pytest.approx(cut.area, rel=1e-12)
    assert shapely.union_all([e.geometry for e in el]).symmetric_difference(cut).area < 1e-9 * cut.area


@pytest.mark.parametrize("kw,needle", [
    (dict(arm_length=1.2), "arm_length is 1.2 at the star centred at"),
    (dict(arm_length="0.5 - 0.02 * r"), "must be a fraction of spacing_mm in [0, 1]"),
    (dict(thickness="0.3 - 0.01 * r"), "thickness_mm is"),
    (dict(arm_width=0.0), "arm_width_mm is 0"),
    (dict(thickness="log(r)"), "is -inf at (x, y) = (0, 0)"),
    (dict(spacing=-1.0), "spacing_mm must be > 0"),
    (dict(side="top"), "side must be"),
])
def test_bad_star_fields(kw, needle):
    args = dict(spacing=18.0, arm_length=0.5, thickness=0.3, arm_width=0.8)
    args.update(kw)
    with pytest.raises(SelfshapeError) as e:
        star_elements(hexagon(67.0), where="[stars]", **args)
    assert str(e.value).startswith("[stars]") and needle in str(e.value)


def test_rotated_lattice_and_origin():
    out = hexagon(67.0)
    # rotating the lattice by 30 deg: its rings point at the hexagon's edge midpoints
    pts, idx = lattice_points(out, 18.0, angle_deg=30.0)
    assert len(pts) == 43 and shapely.contains_xy(out.buffer(1e-9), pts[:, 0], pts[:, 1]).all()
    centre = np.flatnonzero((idx == 0).all(axis=1))[0]
    d = np.linalg.norm(pts - pts[centre], axis=1)
    nbr = pts[np.isclose(d, 18.0)] - pts[centre]
    ang = np.sort(np.degrees(np.arctan2(nbr[:, 1], nbr[:, 0])) % 360)
    np.testing.assert_allclose(ang, [30, 90, 150, 210, 270, 330], atol=1e-9)
    pts, _ = lattice_points(out, 18.0, origin=(9.0, 0.0))
    assert np.isclose(np.min(np.hypot(pts[:, 0] - 9.0, pts[:, 1])), 0.0)
