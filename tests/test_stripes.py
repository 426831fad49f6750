import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import eigsh
from scipy.spatial import Delaunay

import geometry.stripes as stripes
from geometry.meshops import mesh_edges
from geometry.stripes import isoline_set, isolines, stripe_field
from shellfem.errors import SelfshapeError


def grid_mesh(lx, ly, h, jitter=0.2, seed=0):
    """Delaunay mesh of a jittered grid on [0, lx] x [0, ly] (mm)."""
    x, y = np.meshgrid(np.linspace(0, lx, int(round(lx / h)) + 1), np.linspace(0, ly, int(round(ly / h)) + 1))
    P = np.column_stack([x.ravel(), y.ravel()])
    inner = (P[:, 0] > 0) & (P[:, 0] < lx) & (P[:, 1] > 0) & (P[:, 1] < ly)
    P[inner] += np.random.default_rng(seed).uniform(-jitter * h, jitter * h, (inner.sum(), 2))
    return P, Delaunay(P).simplices


def disk_mesh(r, h):
    """Delaunay mesh of a disk of radius r (hexagonal lattice + boundary ring)."""
    ys = np.arange(-r, r + h, h * np.sqrt(3) / 2)
    P = np.vstack([np.column_stack([np.arange(-r, r + h, h) + (0.5 * h if j % 2 else 0.0), np.full(
        len(np.arange(-r, r + h, h)), y)]) for j, y in enumerate(ys)])
    P = P[np.hypot(*P.T) < r - 0.5 * h]
    a = np.linspace(0, 2 * np.pi, int(np.ceil(2 * np.pi * r / h)), endpoint=False)
    P = np.vstack([P, r * np.column_stack([np.cos(a), np.sin(a)])])
    return P, Delaunay(P).simplices


def drop_faces(P, F, keep):
    F = F[keep]
    used = np.unique(F)
    remap = np.full(len(P), -1)
    remap[used] = np.arange(len(used))
    return P[used], remap[F]


@pytest.fixture(scope="module")
def square():
    return grid_mesh(40.0, 40.0, 0.5)


def test_plane_constant_field_exact_spacing_and_orientation(square):
    V, F = square
    ang = np.deg2rad(30.0)
    t = np.array([np.cos(ang), np.sin(ang)])
    nrm = np.array([-t[1], t[0]])
    fld = stripe_field(V, F, np.tile(t, (len(F), 1)), 4.0)
    assert not fld.singular.any()
    offs = {}
    for value in (0.0, np.pi):
        lines = isolines(V, F, fld, value)
        assert len(lines) >= 12
        o = []
        for p in lines:
            d = p @ nrm
            assert np.ptp(d) < 1e-6 * 40                  # straight ...
            u = p[-1] - p[0]
            assert abs(u @ t) / np.linalg.norm(u) > np.cos(np.deg2rad(0.01))   # ... along t
            o.append(d.mean())
        offs[value] = np.sort(o)
        np.testing.assert_allclose(np.diff(offs[value]), 4.0, rtol=0.02)
        np.testing.assert_allclose(np.diff(offs[value]), 4.0, rtol=1e-6)
    # the pi isolines sit halfway between the 0 isolines
    shift = (offs[np.pi][0] - offs[0.0][0]) % 4.0
    assert shift == pytest.approx(2.0, abs=1e-6)


def test_plane_linearly_varying_spacing(square):
    V, F = grid_mesh(60.0, 30.0, 0.5)
    lam = 3.0 + 0.05 * V[:, 0]                              # spacing grows along x
    fld = stripe_field(V, F, np.tile([0.0, 1.0], (len(F), 1)), lam)
    x = np.sort([p[:, 0].mean() for p in isolines(V, F, fld, 0.0)])
    assert len(x) >= 12
    mid = 0.5 * (x[1:] + x[:-1])
    np.testing.assert_allclose(np.diff(x), 3.0 + 0.05 * mid, rtol=0.05)
    np.testing.assert_allclose(np.diff(x), 3.0 + 0.05 * mid, rtol=0.002)


def test_sign_of_line_field_is_irrelevant(square):
    V, F = square
    t = np.array([np.cos(0.5), np.sin(0.5)])
    rng = np.random.default_rng(3)
    # random flips per face and per vertex: the field is a line field
    for d, on in ((rng.choice([-1.0, 1.0], len(F))[:, None] * t, "face"),
                  (rng.choice([-1.0, 1.0], len(V))[:, None] * t, "vertex")):
        fld = stripe_field(V, F, d, 3.0, direction_on=on)
        assert not fld.singular.any()
        lines = isolines(V, F, fld, 0.0)
        o = np.sort([(p @ [-t[1], t[0]]).mean() for p in lines])
        assert max(np.ptp(p @ [-t[1], t[0]]) for p in lines) < 1e-6
        np.testing.assert_allclose(np.diff(o), 3.0, rtol=1e-6)
    fld = stripe_field(V, F, rng.choice([-1.0, 1.0], len(V))[:, None] * t, 3.0, direction_on="vertex")
    assert (fld.sheet < 0).any()                            # sheet changes were really exercised


def test_sphere_cap_geodesic_spacing():
    R = 50.0
    P2, F = disk_mesh(R * np.pi / 4, 0.8)                   # cap of half-angle 45 degrees
    rho = np.hypot(*P2.T) / R
    az = np.arctan2(P2[:, 1], P2[:, 0])
    V = R * np.column_stack([np.sin(rho) * np.cos(az), np.sin(rho) * np.sin(az), np.cos(rho)])
    # isolines = geodesic circles about the equator point p (outside the cap): smooth field
    p = np.array([1.0, 0.0, 0.0])
    x = V / R
    grad = -(p - (x @ p)[:, None] * x)
    fld = stripe_field(V, F, np.cross(x, grad), 5.0)
    assert not fld.singular.any()
    dist = [R * np.arccos(np.clip(q @ p / R, -1, 1)) for q in isolines(V, F, fld, 0.0)]
    assert max(np.ptp(d) for d in dist) < 0.02              # each isoline is a geodesic circle
    mean = np.sort([d.mean() for d in dist])
    assert len(mean) >= 14
    np.testing.assert_allclose(np.diff(mean), 5.0, rtol=0.05)
    np.testing.assert_allclose(np.diff(mean), 5.0, rtol=0.002)


def test_closed_isolines_on_an_annulus():
    P, F = disk_mesh(30.0, 0.6)
    c = P[F].mean(axis=1)
    P, F = drop_faces(P, F, np.hypot(*c.T) > 8.0)
    d = np.column_stack([-P[:, 1], P[:, 0]])                # tangential: concentric stripes
    fld = stripe_field(P, F, d, 3.0, direction_on="vertex")
    S = isoline_set(P, F, fld, np.pi)
    # the field's global phase is set by a reference, not by the geometry, so a level may fall
    # within a triangle of the inner rim (r ~ 7.7) and leave open 2-point pieces there: only
    # isolines clear of both rims must be closed circles
    rmin = np.array([np.hypot(*q.T).min() for q in S.polylines()])
    rmax = np.array([np.hypot(*q.T).max() for q in S.polylines()])
    inner = (rmin > 8.0 + 0.6) & (rmax < 30.0 - 0.6)
    assert S.closed[inner].all() and inner.sum() >= 6
    assert np.all((rmin[~inner] < 8.6) | (rmax[~inner] > 29.4))
    radii = []
    for q in (q for q, keep in zip(S.polylines(), inner) if keep):
        r = np.hypot(*q.T)
        assert np.allclose(q[0], q[-1]) and np.ptp(r) < 0.02
        radii.append(r.mean())
    np.testing.assert_allclose(np.diff(np.sort(radii)), 3.0, rtol=0.005)
    # every segment's face contains both of its end points' edges
    E, fe, _ = mesh_edges(F, len(P))
    for j in np.flatnonzero(inner):
        sl = slice(S.offsets[j], S.offsets[j + 1])
        faces = S.seg_face[sl]
        e0 = S.edge[sl]
        e1 = np.roll(e0, -1, axis=0)
        for f, a, b in zip(faces, e0, e1):
            assert set(a) <= set(F[f]) and set(b) <= set(F[f])


def test_half_integer_singularities_are_marked_and_isolines_stop_there():
    P, F = disk_mesh(30.0, 0.7)
    c = P[F].mean(axis=1)
    th = 0.5 * np.arctan2(c[:, 1], c[:, 0] - 10.0) - 0.5 * np.arctan2(c[:, 1], c[:, 0] + 10.0)
    fld = stripe_field(P, F, np.column_stack([np.cos(th), np.sin(th)]), 4.0)
    # one branch face at each of the +-1/2 singularities (10, 0) and (-10, 0)
    assert fld.branch.sum() == 2
    bc = np.sort(c[fld.branch][:, 0])
    np.testing.assert_allclose(bc, [-10.0, 10.0], atol=1.0)
    S = isoline_set(P, F, fld, 0.0)
    E, fe, _ = mesh_edges(F, len(P))
    boundary_edge = np.bincount(fe.ravel(), minlength=len(E)) == 1
    edge_id = {tuple(e): i for i, e in enumerate(E)}
    sing_vertices = set(F[fld.singular].ravel())
    for j in np.nonzero(~S.closed)[0]:
        for end in (S.offsets[j], S.offsets[j + 1] - 1):
            a, b = S.edge[end]
            on_boundary = boundary_edge[edge_id[(a, b)]]
            at_singular = a in sing_vertices and b in sing_vertices
            assert on_boundary or at_singular
    # no isoline segment lies in a singular face
    sf = S.seg_face[S.seg_face >= 0]
    assert not fld.singular[sf].any()


def test_deterministic_for_a_seed(square):
    V, F = square
    d = np.tile([1.0, 0.2], (len(F), 1))
    a = stripe_field(V, F, d, 5.0, seed=7)
    b = stripe_field(V, F, d, 5.0, seed=7)
    np.testing.assert_array_equal(a.psi, b.psi)


# planar rectangles with a constant isoline direction: the line field is orientable, so the
# energy is invariant under a global phase and its lowest eigenvalue is a pair. "exact": constant
# spacing, lambda_1 = 0; "fan": the spacing grows along the isolines, lambda_1 > 0
PHASE_CASES = {"exact": lambda V: 3.0, "fan": lambda V: 2.0 + 0.1 * V[:, 0]}


@pytest.fixture(scope="module")
def rectangle():
    return grid_mesh(20.0, 10.0, 0.5)


def _captured_system(monkeypatch):
    """Record (A, mass, V) of every stripe solve."""
    seen = []
    solve = stripes._smallest_stripe_mode

    def spy(A, mass, V, *args, **kwargs):
        seen.append((A, mass, V))
        return solve(A, mass, V, *args, **kwargs)

    monkeypatch.setattr(stripes, "_smallest_stripe_mode", spy)
    return seen


@pytest.mark.parametrize("case", PHASE_CASES)
def test_global_phase_does_not_depend_on_the_start_seed(rectangle, case):
    V, F = rectangle
    d = np.tile([np.cos(0.5), np.sin(0.5)], (len(F), 1))
    fields = [stripe_field(V, F, d, PHASE_CASES[case](V), seed=s) for s in (0, 1, 5)]
    for f in fields[1:]:
        np.testing.assert_allclose(f.psi, fields[0].psi, rtol=0, atol=1e-6)
        np.testing.assert_allclose(f.amplitude, fields[0].amplitude, rtol=0, atol=1e-6 * fields[0].amplitude.max())


@pytest.mark.parametrize("case", PHASE_CASES)
def test_phase_fixed_field_is_a_lowest_eigenvector(rectangle, case, monkeypatch):
    V, F = rectangle
    seen = _captured_system(monkeypatch)
    fld = stripe_field(V, F, np.tile([1.0, 0.0], (len(F), 1)), PHASE_CASES[case](V))
    A, mass, _ = seen[0]
    M = sp.diags(mass)
    scale = float(np.abs(A.diagonal()).mean() / mass.mean())
    lam_ref = np.sort(eigsh(A.tocsc(), k=4, M=M.tocsc(), sigma=-1e-3 * scale, which="LM")[0])
    assert lam_ref[1] - lam_ref[0] <= 1e-9 * scale       # a pair: the phase is free
    z = fld.amplitude * fld.psi
    x = np.column_stack([z.real, z.imag]).ravel()
    assert x @ (mass * x) == pytest.approx(1.0, rel=1e-10)
    rq = float(x @ (A @ x))
    assert rq == pytest.approx(lam_ref[0], rel=1e-8, abs=1e-12 * scale)
    assert fld.eigenvalue == pytest.approx(lam_ref[0], rel=1e-8, abs=1e-12 * scale)


def test_phase_is_the_one_the_reference_fixes_whatever_the_vertex_order(rectangle, monkeypatch):
    V, F = rectangle
    sp_ = PHASE_CASES["fan"]
    seen = _captured_system(monkeypatch)
    fld = stripe_field(V, F, np.tile([1.0, 0.0], (len(F), 1)), sp_(V))
    _, mass, V3 = seen[0]
    r = stripes._gauge_references(V3, mass)[0]
    # the reference (real, so sheet-free) keeps a good part of its M-norm in the eigenspace
    # spanned by psi and i psi (the pair): the first reference is the one in use
    z = fld.amplitude * fld.psi
    m = mass[0::2]
    rho = abs(np.sum(m * r[0::2] * z)) / np.sqrt(r @ (mass * r))
    assert rho >= 1e-3
    # the phase maximises <r, M Re(exp(i t) z)> over t: sum_a m_a r_a z_a is real and positive
    c = np.sum(m * r[0::2] * z)
    assert c.real > 0 and abs(c.imag) <= 1e-9 * abs(c)
    assert not (fld.sheet < 0).any()
    # relabelled vertices and faces (another start block, another fill-reducing ordering): the
    # same field
    rng = np.random.default_rng(11)
    perm = rng.permutation(len(V))                      # new vertex i is old vertex perm[i]
    inv = np.argsort(perm)
    F2 = inv[F][rng.permutation(len(F))]
    f2 = stripe_field(V[perm], F2, np.tile([1.0, 0.0], (len(F2), 1)), sp_(V[perm]))
    np.testing.assert_allclose(f2.psi[inv], fld.psi, rtol=0, atol=1e-6)


def test_gauge_fixing_projects_the_first_reference_that_reaches_the_eigenspace():
    rng = np.random.default_rng(2)
    mass = rng.uniform(0.5, 2.0, 40)
    Q = np.linalg.qr(np.sqrt(mass)[:, None] * rng.standard_normal((40, 2)))[0] / np.sqrt(mass)[:, None]
    r_far = rng.standard_normal(40)
    r_far -= Q @ (Q.T @ (mass * r_far))                 # M-orthogonal to span(Q): no projection
    r2 = rng.standard_normal(40)
    x = stripes._gauge_fixed(Q, mass, [r_far, r2])
    p = Q @ (Q.T @ (mass * r2))
    np.testing.assert_allclose(x, p / np.sqrt(p @ (mass * p)), atol=1e-12)
    # one vector: itself, with the sign that makes <r, M x> > 0
    x1 = stripes._gauge_fixed(-Q[:, :1] * 3.0, mass, [r2])
    s = np.sign(Q[:, 0] @ (mass * r2))
    np.testing.assert_allclose(x1, s * Q[:, 0], atol=1e-12)


def test_bad_input_is_an_error(square):
    V, F = square
    d = np.tile([1.0, 0.0], (len(F), 1))
    with pytest.raises(SelfshapeError, match="too coarse"):
        stripe_field(V, F, d, 0.6)                       # edges of 0.5 mm cannot carry 0.6 mm stripes
    with pytest.raises(SelfshapeError, match=r"spacing\[3\]"):
        sp = np.full(len(V), 4.0)
        sp[3] = -1.0
        stripe_field(V, F, d, sp)
    with pytest.raises(SelfshapeError, match="direction"):
        stripe_field(V, F, d[:10], 4.0)
    d0 = d.copy()
    d0[5] = 0.0
    with pytest.raises(SelfshapeError, match=r"direction\[5\]"):
        stripe_field(V, F, d0, 4.0)
    with pytest.raises(SelfshapeError, match="not used"):
        stripe_field(np.vstack([V, [[100.0, 100.0]]]), F, d, 4.0)
