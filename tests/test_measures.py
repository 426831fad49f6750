"""validation.measures' curves on the deployed surface against analytic surfaces (mm, 1/mm)."""
import numpy as np
import pytest

from shellfem.sheet import Sheet
from validation.measures import (coarse_curvature_tensor, curve_curvatures, deployed_at, line_contractions,
                                 normal_curvature, ribbon_curvatures, sampled_centre_quadric)

R = 8.0


def _cylinder(width=30.0, height=20.0, nx=30, ny=40, angle_deg=0.0, R=R):
    """A flat rectangle rolled isometrically about an axis at angle_deg from x, radius R, bending
    away from its +z (front) side: the centre of curvature on the -normal side."""
    sh = Sheet.rectangle(width, height, nx, ny)
    P = sh.points
    a = np.radians(angle_deg)
    ax, ac = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
    u, v = P @ ax, P @ ac                          # along the axis, around it
    X = (u[:, None] * np.append(ax, 0) + R * np.sin(v / R)[:, None] * np.append(ac, 0)
         + (R * np.cos(v / R) - R)[:, None] * np.array([0, 0, 1.0]))
    return sh, X


def _cap(Rs=30.0, half=10.0, n=80):
    """The flat square [-half, half]^2 lifted to the sphere of radius Rs below +z (not
    isometric, but every normal curvature of a sphere is -1 / Rs)."""
    sh = Sheet.rectangle(2 * half, 2 * half, n, n)
    P = sh.points - half
    X = np.column_stack([P, np.sqrt(Rs ** 2 - (P ** 2).sum(1)) - Rs])
    return Sheet(P, sh.triangles), X


def test_three_points_on_a_circle_give_its_curvature_towards_the_normal():
    t = np.array([0.3, 0.9, 1.7])
    c = np.array([1.0, -2.0, 0.5])
    p = c + 5.0 * np.column_stack([np.cos(t), np.sin(t), np.zeros(3)])
    towards_centre = (c - p[1]) / 5.0
    assert normal_curvature(p[0], p[1], p[2], towards_centre) == pytest.approx(1 / 5.0, rel=1e-12)
    assert normal_curvature(p[0], p[1], p[2], -towards_centre) == pytest.approx(-1 / 5.0, rel=1e-12)
    assert normal_curvature(p[0], p[1], p[2], np.array([0, 0, 1.0])) == pytest.approx(0.0, abs=1e-15)
    line = np.array([[0, 0, 0], [1, 1, 1], [3, 3, 3.0]])
    assert normal_curvature(line[0], line[1], line[2], np.array([0, 0, 1.0])) == 0.0


def test_deployed_at_interpolates_inside_and_is_nan_outside():
    sh, X = _cylinder()
    # at the vertices: the vertices; the normal of the cylinder there
    Xq, Nq = deployed_at(sh.points, sh.triangles, X, sh.points[[5, 100, 700]])
    assert np.allclose(Xq, X[[5, 100, 700]], atol=1e-12)
    v = sh.points[[5, 100, 700], 1]
    assert np.allclose(Nq, np.column_stack([0 * v, np.sin(v / R), np.cos(v / R)]), atol=2e-3)
    Xo, _ = deployed_at(sh.points, sh.triangles, X, [[-1.0, 5.0]])
    assert np.isnan(Xo).all()


def test_cylinder_curves_along_are_straight_and_across_are_the_circle():
    sh, X = _cylinder()                                                # rows every 0.5 mm around
    along = np.column_stack([np.linspace(1.0, 29.0, 15), np.full(15, 7.3)])
    assert np.allclose(curve_curvatures(sh.points, sh.triangles, X, along), 0.0, atol=1e-12)
    across = np.column_stack([np.full(10, 12.3), np.linspace(1.0, 19.0, 10)])    # on the rows: exact points
    assert np.allclose(curve_curvatures(sh.points, sh.triangles, X, across), -1 / R, rtol=1e-4)
    across_off = np.column_stack([np.full(9, 12.3), np.linspace(1.1, 18.7, 9)])  # between the rows: chords
    # interpolated points lie on the 0.5 mm chords (sagitta 0.5^2 / (8 R) = 0.004 mm): 1.3 % at 2.2 mm spacing
    assert np.allclose(curve_curvatures(sh.points, sh.triangles, X, across_off), -1 / R, rtol=1.5e-2)


def test_ribbon_curvatures_on_a_cylinder():
    sh, X = _cylinder()
    lines = [np.array([[2.0, y], [28.0, y]]) for y in np.arange(2.0, 19.0, 2.0)]
    r = ribbon_curvatures(sh.points, sh.triangles, X, lines, step=2.0)
    assert r["along"] == pytest.approx(0.0, abs=1e-12)
    assert r["across"] == pytest.approx(-1 / R, rel=1e-4)
    assert r["n_along"] > 0 and r["n_across"] > 0


@pytest.mark.parametrize("angle", [0.0, 30.0])
def test_coarse_tensor_of_a_cylinder_has_principal_curvatures_1_over_R_and_0(angle):
    sh, X = _cylinder(width=40.0, height=40.0, nx=80, ny=80, angle_deg=angle)
    c = np.array([[20.0, 20.0], [15.0, 22.0], [24.0, 17.0]])
    S = coarse_curvature_tensor(sh.points, sh.triangles, X, c, step=5.0)
    ev, vec = np.linalg.eigh(S)
    # the diagonal samples fall between the rows (chords): 0.4 % of 1 / R
    assert np.allclose(ev[:, 0], -1 / R, rtol=4e-3) and np.allclose(ev[:, 1], 0.0, atol=4e-3 / R)
    a = np.radians(angle)
    around = np.array([-np.sin(a), np.cos(a)])
    assert np.allclose(np.abs(np.einsum('kd,d->k', vec[:, :, 0], around)), 1.0, atol=1e-4)   # the curved direction is around the axis


def test_sphere_every_normal_curvature_is_minus_1_over_R():
    Rs = 30.0
    sh, X = _cap(Rs)
    c = np.array([[0.0, 0.0], [3.0, -2.0], [-4.0, 4.5]])
    S = coarse_curvature_tensor(sh.points, sh.triangles, X, c, step=4.0)
    assert np.allclose(S, -np.eye(2) / Rs, atol=2e-3 / Rs)
    K = np.linalg.det(S)
    assert np.allclose(K, 1 / Rs ** 2, rtol=4e-3)
    curve = np.column_stack([np.linspace(-8, 8, 9), np.linspace(-3, 5, 9)])
    assert np.allclose(curve_curvatures(sh.points, sh.triangles, X, curve), -1 / Rs, rtol=1e-3)


def test_line_contractions_of_a_planar_stretch_and_of_concentric_arcs():
    sh = Sheet.rectangle(30.0, 20.0, 15, 10)
    X = np.column_stack([0.8 * sh.points[:, 0], 0.6 * sh.points[:, 1], np.zeros(sh.n_vertices)])
    lines = [np.array([[2.0, y], [28.0, y]]) for y in (3.0, 7.0, 12.5, 17.0)]
    c = line_contractions(sh.points, sh.triangles, X, lines)
    assert np.allclose(c["along"], 0.8, rtol=1e-12) and np.allclose(c["across"], 0.6, rtol=1e-12)
    # arcs around (15, 0) on a sheet mapped r -> r0 + 0.5 (r - r0) (radially halved about r0 = 10):
    # the arc of radius r keeps its angle, so along = (r0 + 0.5 (r - r0)) / r, across = 0.5 (the map is not
    # linear: to the interpolation's error on a 0.25 mm mesh)
    fine = Sheet.rectangle(30.0, 20.0, 120, 80)
    Pf = fine.points - [15.0, 0.0]
    rf, tf = np.linalg.norm(Pf, axis=1), np.arctan2(Pf[:, 1], Pf[:, 0])
    Xf = np.column_stack([(10.0 + 0.5 * (rf - 10.0)) * np.cos(tf), (10.0 + 0.5 * (rf - 10.0)) * np.sin(tf),
                          np.zeros(fine.n_vertices)])
    arcs = [np.column_stack([15 + rr * np.cos(a), rr * np.sin(a)]) for rr in (8.0, 11.0, 14.0)
            for a in [np.linspace(0.2, np.pi - 0.2, 400)]]
    c = line_contractions(fine.points, fine.triangles, Xf, arcs)
    rr = np.array([8.0, 11.0, 14.0])
    assert np.allclose(c["along"], (10.0 + 0.5 * (rr - 10.0)) / rr, rtol=2e-3)
    assert np.allclose(c["across"], 0.5, rtol=2e-3)


def test_sampled_centre_quadric_of_a_sphere_and_a_cylinder():
    Rs = 30.0
    sh, X = _cap(Rs)
    q = sampled_centre_quadric(sh.points, sh.triangles, X)
    assert q["gauss_centre_fit"] == pytest.approx(1 / Rs ** 2, rel=1e-2)
    assert q["mean_curv_centre_fit"] == pytest.approx(1 / Rs, rel=5e-3)
    Rc = 40.0                        # a quadric over +-0.2 rad of the circle (disc radius 0.3 x 28.3 mm)
    sh, X = _cylinder(width=40.0, height=40.0, nx=80, ny=80, R=Rc)
    q = sampled_centre_quadric(sh.points, sh.triangles, X)
    assert q["gauss_centre_fit"] == pytest.approx(0.0, abs=1e-3 / Rc ** 2)
    assert q["mean_curv_centre_fit"] == pytest.approx(1 / (2 * Rc), rel=1e-2)
