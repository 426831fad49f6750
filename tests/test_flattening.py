import numpy as np
import pytest

from geometry.fields import curvature_line_field
from geometry.flattening import (_local_step, _Problem, flatten, flatten_surface, local_triangles,
                                 principal_stretches, stretch_bounds, tutte_embedding)
from geometry.target import cylinder_patch, plane_patch, sphere_cap
from shellfem.errors import SelfshapeError


def test_stretch_bounds_reproduce_the_seed():
    s1min, s1max, s2min, s2max = stretch_bounds(1.6, 15.0, 1.5)
    assert (s1min, s1max, s2min) == (1.0, pytest.approx(1.3), pytest.approx(1.3))
    assert s2max == pytest.approx(1.6 * 15 / (15 + 1.5 * 0.6))       # Eq. 5.15 with mu2 = l_r
    assert round(s2max, 2) == 1.51
    # Eq. 5.15 round trip: the spacing giving s2max is the requested maximum spacing
    assert 1.5 * (1.6 - 1) / (1.6 - s2max) * s2max == pytest.approx(15.0)
    assert stretch_bounds(1.6, 15, 1.5, max_transverse_spacing=6.0)[3] == pytest.approx(1.6 * 6 / 6.9)
    with pytest.raises(SelfshapeError, match="max_transverse_spacing"):
        stretch_bounds(1.6, 15, 1.5, max_transverse_spacing=3.0)
    with pytest.raises(SelfshapeError, match="stretch"):
        stretch_bounds(1.0)


@pytest.fixture(scope="module")
def cylinder():
    V, F = cylinder_patch(30.0, 60.0, 50.0, 24, 20)
    return V, F, curvature_line_field(V, F).face_dirs


def test_cylinder_isometric_along_k1_and_clamped_across(cylinder):
    V, F, d1 = cylinder
    res = flatten(V, F, d1)
    assert res.converged and res.flipped == 0
    np.testing.assert_allclose(res.sigma1, 1.0, atol=1e-3)
    np.testing.assert_allclose(res.sigma2, 1.3, atol=1e-3)     # isometry 1 < s2min: clamped
    assert res.residual_energy < 1e-8 and res.k1_deviation_deg < 0.01
    assert res.sigma_out_of_bounds_pct == [0.0, 0.0]
    # the flat patch is the unrolled 60 mm arc x (1.3 x 50 mm): extents along dir1 and across
    e1 = np.mean(res.dir1 * np.sign(res.dir1 @ res.dir1[0])[:, None], axis=0)
    e1 /= np.linalg.norm(e1)
    along, across = res.uv @ e1, res.uv @ [-e1[1], e1[0]]
    assert np.ptp(along) == pytest.approx(60.0, rel=2e-3)
    assert np.ptp(across) == pytest.approx(65.0, rel=2e-3)


def test_cylinder_isometry_kept_when_the_bounds_admit_it(cylinder):
    V, F, d1 = cylinder
    res = flatten(V, F, d1, bounds=(1.0, 1.3, 0.9, 1.5), anderson=0)
    np.testing.assert_allclose(res.sigma1, 1.0, atol=1e-3)
    np.testing.assert_allclose(res.sigma2, 1.0, atol=1e-3)
    res = flatten(V, F, d1, bounds=(1.1, 1.3, 1.4, 1.5))       # both clamped to their minima
    np.testing.assert_allclose(res.sigma1, 1.1, atol=1e-3)
    np.testing.assert_allclose(res.sigma2, 1.4, atol=1e-3)


def _cylinder_with_holes():
    """The cylinder fixture's mesh with two cells of faces cut out: a developable disk with 2 holes."""
    V, F = cylinder_patch(30.0, 60.0, 50.0, 24, 20)
    c = V[F].mean(axis=1)
    i = np.floor((30.0 * np.arcsin(c[:, 0] / 30.0) + 30.0) / 2.5).astype(int)   # the face's grid cell
    j = np.floor((c[:, 1] + 25.0) / 2.5).astype(int)
    cut = ((i >= 5) & (i < 9) & (j >= 4) & (j < 9)) | ((i >= 14) & (i < 19) & (j >= 10) & (j < 15))
    from geometry.meshops import remove_unreferenced
    W, G, _ = remove_unreferenced(V, F[~cut])          # the holes' inner grid vertices go
    return W, G, cut


def test_tutte_and_flattening_of_a_disk_with_holes():
    # a cylinder patch with two holes: Tutte closes the holes by fans and drops them again
    # (injective), and the flattening is the same unrolling as without the holes
    from geometry.meshops import boundary_loops, signed_areas
    V, F, cut = _cylinder_with_holes()
    assert cut.sum() == 2 * (20 + 25)
    uv = tutte_embedding(V, F)
    assert uv.shape == (len(V), 2) and (signed_areas(uv, F) > 0).all()
    loops = boundary_loops(V, F)
    assert len(loops) == 3 and np.isclose(np.linalg.norm(uv[loops[0]], axis=1), 1.0).all()
    d1 = curvature_line_field(V, F).face_dirs
    res = flatten(V, F, d1, bounds=(1.0, 1.3, 0.9, 1.5), anderson=0)
    assert res.converged and res.flipped == 0
    np.testing.assert_allclose(res.sigma1, 1.0, atol=1e-3)
    np.testing.assert_allclose(res.sigma2, 1.0, atol=1e-3)
    # the holes keep their shape: unrolled cells of 60 / 24 x 50 / 20 mm
    import shapely
    holes = sorted(shapely.Polygon(res.uv[loop]).area for loop in loops[1:])
    assert holes == pytest.approx([20 * 2.5 * 2.5, 25 * 2.5 * 2.5], rel=2e-3)


def test_plane_all_sigma_within_bounds():
    V, F = plane_patch(60.0, 40.0, 18, 12)
    res, lf, _ = flatten_surface(V, F)
    lo1, hi1, lo2, hi2 = res.bounds
    assert lf.smoothest and res.converged and res.flipped == 0
    assert np.all((res.sigma1 > lo1 - 1e-4) & (res.sigma1 < hi1 + 1e-4))
    assert np.all((res.sigma2 > lo2 - 1e-4) & (res.sigma2 < hi2 + 1e-4))
    assert max(res.sigma_bound_violation) < 1e-4


def test_sphere_cap_feasible_within_bounds_and_stop_rule():
    V, F = sphere_cap(60.0, 25.0, 8)
    res, _, _ = flatten_surface(V, F)
    assert res.converged and res.iterations < 2000 and res.flipped == 0
    assert max(res.sigma_bound_violation) < 3e-3     # measured 0.0020 (residual 1.7e-6: nearly feasible)
    assert res.residual_energy < 1e-5
    capped, _, _ = flatten_surface(V, F, max_iter=2)
    assert not capped.converged and capped.iterations == 2
    plain, _, _ = flatten_surface(V, F, anderson=0, stop="mean", max_iter=5)
    assert not plain.converged and len(plain.history) == 5


def test_local_step_matches_svd_procrustes_and_clamping():
    rng = np.random.default_rng(3)
    m = 200
    P0, P1 = rng.normal(size=(m, 2)), rng.normal(size=(m, 2))
    s1, s2 = rng.uniform(1, 1.3, m), rng.uniform(1.3, 1.5, m)
    bounds = (1.0, 1.3, 1.3, 1.51)
    c, s, n1, n2 = _local_step(P0, P1, s1, s2, bounds)
    for k in range(m):
        P = np.column_stack([P0[k], P1[k]])
        B = P @ np.diag([s1[k], s2[k]])       # argmax tr(R^T B) over SO(2) (Eq. 5.10-5.12)
        U, S, Vt = np.linalg.svd(B)
        D = np.diag([1.0, np.sign(np.linalg.det(U @ Vt))])
        R = U @ D @ Vt
        np.testing.assert_allclose([[c[k], -s[k]], [s[k], c[k]]], R, atol=1e-9)
        d = np.diag(P.T @ R)                  # Eq. 5.7
        assert n1[k] == pytest.approx(np.clip(d[0], 1.0, 1.3))
        assert n2[k] == pytest.approx(np.clip(d[1], 1.3, 1.51))


def test_global_step_minimises_eq_5_3():
    V, F = sphere_cap(40.0, 30.0, 5)
    d1 = curvature_line_field(V, F).face_dirs
    U, W, Dinv, X = local_triangles(V, F)
    k1 = np.column_stack([np.einsum("ij,ij->i", d1, U), np.einsum("ij,ij->i", d1, W)])
    prob = _Problem(V, F, k1, Dinv, X, (1.0, 1.3, 1.3, 1.5), 2)
    uv = V[:, :2] * 1.2
    st, _ = prob.local(uv, np.ones(len(F)), np.ones(len(F)))
    c, s, s1, s2 = st

    def energy(x):
        P = prob.B @ x
        P0, P1 = P[: len(F)], P[len(F):]
        r = (P0[:, 0] - c * s1) ** 2 + (P0[:, 1] - s * s1) ** 2 + (P1[:, 0] + s * s2) ** 2 + (P1[:, 1] - c * s2) ** 2
        return prob.area @ r

    g = prob.global_step(uv, st)
    assert energy(g) <= energy(uv)
    rng = np.random.default_rng(0)
    for _ in range(5):
        assert energy(g) <= energy(g + 1e-3 * rng.normal(size=g.shape))


def test_principal_stretches_of_known_jacobian():
    phi, psi = 0.4, -1.1
    Rt = np.array([[np.cos(phi), np.sin(phi)], [-np.sin(phi), np.cos(phi)]])   # k1 -> u-axis
    R = np.array([[np.cos(psi), -np.sin(psi)], [np.sin(psi), np.cos(psi)]])
    J = (R @ np.diag([1.05, 1.4]) @ Rt)[None]
    s1, s2, dev = principal_stretches(J, np.array([[np.cos(phi), np.sin(phi)]]))
    assert s1[0] == pytest.approx(1.05) and s2[0] == pytest.approx(1.4) and dev[0] < 1e-5


def test_tutte_is_injective_on_unit_circle():
    V, F = sphere_cap(40.0, 60.0, 6)
    uv = tutte_embedding(V, F)
    a, b = uv[F[:, 1]] - uv[F[:, 0]], uv[F[:, 2]] - uv[F[:, 0]]
    assert np.all(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0] > 0)
    r = np.linalg.norm(uv, axis=1)
    assert np.isclose(r.max(), 1.0) and np.sum(np.isclose(r, 1.0)) == 36   # the 36 boundary vertices


def test_bad_inputs():
    V, F = plane_patch(10, 10, 3, 3)
    d1 = np.tile([1.0, 0, 0], (len(F), 1))
    with pytest.raises(SelfshapeError, match="dir1"):
        flatten(V, F, d1[:-1])
    with pytest.raises(SelfshapeError, match="tangent"):
        flatten(V, F, np.tile([0, 0, 1.0], (len(F), 1)))
    with pytest.raises(SelfshapeError, match="bounds"):
        flatten(V, F, d1, bounds=(1.3, 1.0, 1.3, 1.5))
