"""Contact (shellfem.contact): barrier derivatives, the rolled spiral, the ground, the step filter,
the pattern keys and the outputs (mm, N)."""
import json

import numpy as np
import pytest
from scipy.optimize import minimize_scalar
from scipy.spatial import cKDTree

from fd import central_difference
from forward.simulate import make_contact, simulate, simulate_sheet, support_plane
from geometry.meshing import mesh_pattern
from geometry.patterns import load_pattern, parse_pattern
from shellfem.contact import Contact, _ipctk, ground_barrier
from shellfem.errors import SelfshapeError

# ----------------------------------------------------------------------------- helpers


def _strip(L=50.0, W=4.0, size=0.8, stretch=(1.2, 1.0), fabric_t=0.25, plastic_t=0.1, contact=True, **extra):
    """A bilayer strip pre-stretched along its length only: it rolls about its width (y)."""
    raw = {"fabric": {"rectangle": [L, W], "stretch": list(stretch), "thickness_mm": fabric_t, "model": "neo-hookean",
                      "young_modulus_mpa": 1.05, "poisson": 0.3, "bending_stiffness_nmm": 0.0192},
           "plastic": {"young_modulus_mpa": 72.3, "poisson": 0.5},
           "region": [{"polygon": [[0, 0], [L, 0], [L, W], [0, W]], "thickness_mm": plastic_t, "side": "front"}],
           "mesh": {"size_mm": size}, "solver": {"seed": 0, "coarse_levels": 0}, "contact": {"enabled": contact}}
    raw.update(extra)
    return parse_pattern(raw)


def _rolled(points, r0, pitch, s=1.2):
    """Positions of a printed strip (points (n, 2)) wound on an Archimedean spiral r = r0 +
    pitch phi / 2 pi about the y axis (released length x / s along the spiral)."""
    arc = points[:, 0] / s
    a = pitch / (4 * np.pi)
    phi = (-r0 + np.sqrt(r0 ** 2 + 4 * a * arc)) / (2 * a)
    r = r0 + pitch * phi / (2 * np.pi)
    return np.column_stack([r * np.sin(phi), points[:, 1], r * np.cos(phi) - r0])     # curling to -z (front plastic)


def _point_triangle(p, a, b, c):
    """Distances (k,) from points p to triangles (a, b, c) (each (k, 3)), vectorised: the
    distance to the plane where the projection falls inside, else the nearest edge."""
    ab, ac, ap = b - a, c - a, p - a
    n = np.cross(ab, ac)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    h = np.einsum("ij,ij->i", ap, n)
    g11, g12, g22 = (np.einsum("ij,ij->i", ab, ab), np.einsum("ij,ij->i", ab, ac), np.einsum("ij,ij->i", ac, ac))
    r1, r2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    det = g11 * g22 - g12 * g12
    v, w = (g22 * r1 - g12 * r2) / det, (g11 * r2 - g12 * r1) / det
    inside = (v >= 0) & (w >= 0) & (v + w <= 1)

    def seg(x0, x1):
        e = x1 - x0
        t = np.clip(np.einsum("ij,ij->i", p - x0, e) / np.einsum("ij,ij->i", e, e), 0, 1)
        return np.linalg.norm(p - (x0 + t[:, None] * e), axis=1)
    edges = np.minimum(np.minimum(seg(a, b), seg(b, c)), seg(c, a))
    return np.where(inside, np.abs(h), edges)


def _segment_segment(p1, q1, p2, q2):
    """Distances (k,) between segments p1q1 and p2q2 (Ericson 5.1.9), vectorised."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e = np.einsum("ij,ij->i", d1, d1), np.einsum("ij,ij->i", d2, d2)
    f, c, b = np.einsum("ij,ij->i", d2, r), np.einsum("ij,ij->i", d1, r), np.einsum("ij,ij->i", d1, d2)
    denom = a * e - b * b
    s = np.where(denom > 1e-14 * a * e, np.clip((b * f - c * e) / np.where(denom > 0, denom, 1), 0, 1), 0.0)
    t = (b * s + f) / e
    s = np.where(t < 0, np.clip(-c / a, 0, 1), np.where(t > 1, np.clip((b - c) / a, 0, 1), s))
    t = np.clip(t, 0, 1)
    return np.linalg.norm(p1 + s[:, None] * d1 - (p2 + t[:, None] * d2), axis=1)


def _segment_crosses(p, q, a, b, c):
    """True where segment pq crosses triangle abc (Moller-Trumbore on the segment), vectorised."""
    e1, e2, d = b - a, c - a, q - p
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > 1e-14
    inv = 1.0 / np.where(ok, det, 1.0)
    s = p - a
    u = inv * np.einsum("ij,ij->i", s, h)
    qv = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, qv)
    t = inv * np.einsum("ij,ij->i", e2, qv)
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def triangle_distances(x, tri, pairs):
    """Exact distances (k,) between the triangle pairs (k, 2) of a surface (x (n, 3), tri (m, 3)):
    min over the 6 point-triangle and 9 edge-edge distances, 0 where an edge crosses the other
    triangle. Independent of ipctk (the engine's contact library)."""
    A, B = x[tri[pairs[:, 0]]], x[tri[pairs[:, 1]]]
    d = np.full(len(pairs), np.inf)
    for i in range(3):
        d = np.minimum(d, _point_triangle(A[:, i], B[:, 0], B[:, 1], B[:, 2]))
        d = np.minimum(d, _point_triangle(B[:, i], A[:, 0], A[:, 1], A[:, 2]))
        for j in range(3):
            d = np.minimum(d, _segment_segment(A[:, i], A[:, (i + 1) % 3], B[:, j], B[:, (j + 1) % 3]))
        cross = (_segment_crosses(A[:, i], A[:, (i + 1) % 3], B[:, 0], B[:, 1], B[:, 2])
                 | _segment_crosses(B[:, i], B[:, (i + 1) % 3], A[:, 0], A[:, 1], A[:, 2]))
        d = np.where(cross, 0.0, d)
    return d


def _pairs_within(points, reach, chunk=2_000):
    """Yield (k, 2) arrays of the index pairs i < j of ``points`` (m, 3) within ``reach``, a
    chunk of first indices at a time: memory bounded by the chunk's neighbours, not by all pairs
    (a tight roll passing through itself has thousands of centroids within reach of each)."""
    tree = cKDTree(points)
    for s in range(0, len(points), chunk):
        idx = np.arange(s, min(s + chunk, len(points)))
        m = cKDTree(points[idx]).sparse_distance_matrix(tree, reach, output_type="ndarray")
        i, j = idx[m["i"]], m["j"].astype(np.int64)
        keep = j > i
        if keep.any():
            yield np.column_stack([i[keep], j[keep]])


def intersecting_pairs(x, tri, chunk=200_000):
    """(k, 2) the pairs of triangles of a surface (x (n, 3) mm, tri (m, 3)) that share no vertex
    and cross each other (an edge of one through the other: :func:`triangle_distances` 0), over
    ALL such pairs: two triangles can only meet if their centroids are within the sum of their
    circumradii about the centroid, so a KD-tree query at twice the largest of those radii is
    exhaustive. Independent of ipctk and of the engine's printed-distance exclusion."""
    P = x[tri]
    c = P.mean(1)
    reach = 2.0 * float(np.linalg.norm(P - c[:, None], axis=2).max())
    hit = []
    for pairs in _pairs_within(c, reach):
        share = (tri[pairs[:, 0]][:, :, None] == tri[pairs[:, 1]][:, None, :]).any(axis=(1, 2))
        pairs = pairs[~share]
        hit += [pairs[i:i + chunk][triangle_distances(x, tri, pairs[i:i + chunk]) == 0.0]
                for i in range(0, len(pairs), chunk)]
    return np.concatenate(hit) if hit else np.zeros((0, 2), np.int64)


def far_pairs_min_distance(sheet, x, printed_apart, reach, chunk=200_000):
    """Smallest exact distance (mm) between triangles at least ``printed_apart`` mm apart in the
    printed sheet (centroids), over all such pairs whose deformed centroids are within
    ``reach`` (a KD-tree on the centroids; ``reach`` >= the distance tested + 2 x the longest
    edge makes it exhaustive); inf if no pair is that close. Pairs are taken a chunk of
    triangles at a time and their distances ``chunk`` pairs at a time (bounded memory); a 0
    (two far triangles crossing) ends the search."""
    tri = sheet.triangles
    cd = x[tri].mean(1)
    cp = sheet.points[tri].mean(1)
    best = np.inf
    for pairs in _pairs_within(cd, reach):
        pairs = pairs[np.linalg.norm(cp[pairs[:, 0]] - cp[pairs[:, 1]], axis=1) >= printed_apart]
        for k in range(0, len(pairs), chunk):
            best = min(best, float(triangle_distances(x, tri, pairs[k:k + chunk]).min()))
            if best == 0.0:
                return 0.0
    return best


def centreline_turns(sheet, x, bin_mm=0.5):
    """(turns, inner radius, outer radius) of a strip rolled about y: the centreline (vertex
    positions averaged per printed-x bin of bin_mm) in the x-z plane; turns = its tangent's total
    turning angle / 2 pi, radii = 1 / curvature of its first and last turn."""
    cols = np.floor(sheet.points[:, 0] / bin_mm).astype(int)          # printed-x bins
    count = np.bincount(cols)
    keep = count > 0
    c = np.stack([np.bincount(cols, weights=x[:, k])[keep] / count[keep] for k in (0, 2)], 1)
    t = np.diff(c, axis=0)
    ang = np.unwrap(np.arctan2(t[:, 1], t[:, 0]))
    ds = np.linalg.norm(t, axis=1)
    s = np.concatenate([[0], np.cumsum(ds)])[:-1] + ds / 2
    turn = abs(ang[-1] - ang[0]) / (2 * np.pi)
    kappa = np.abs(np.gradient(ang, s))
    per_turn = 2 * np.pi / np.median(kappa)          # arc length of about a turn
    ends = [s < s[0] + per_turn / 2, s > s[-1] - per_turn / 2]
    radii = sorted(1.0 / np.median(kappa[e]) for e in ends)
    return turn, radii[0], radii[1]


def hand_spiral(length, kappa0, pitch):
    """A strip of released length ``length`` (mm) with natural curvature kappa0 (1/mm), wound as an
    Archimedean spiral r = r_in + pitch phi / 2 pi with its turns in contact: r_in minimises
    the bending measure int (1/r - kappa0)^2 ds (r taken as the local radius of curvature).
    Returns (turns, r_in, r_out)."""
    b = pitch / (2 * np.pi)

    def phi_end(r_in):            # length = int r dphi = r_in phi + b phi^2 / 2
        return (-r_in + np.sqrt(r_in ** 2 + 2 * b * length)) / b

    def energy(r_in):
        phi = np.linspace(0, phi_end(r_in), 4001)
        r = r_in + b * phi
        f = (1 / r - kappa0) ** 2 * r
        return float(np.sum((f[1:] + f[:-1]) / 2 * np.diff(phi)))

    r_in = minimize_scalar(energy, bounds=(0.2 / kappa0, 2.0 / kappa0), method="bounded").x
    phi = phi_end(r_in)
    return phi / (2 * np.pi), r_in, r_in + b * phi


# ----------------------------------------------------------------------------- derivatives


def _near_contact_state(seed):
    pat = _strip(L=30.0, W=2.0, size=1.0)
    sheet = mesh_pattern(pat)
    c = Contact(sheet.points, sheet.triangles, offset=0.35, stretch_max=1.2)
    c.set_stiffness(np.ones(3))
    rng = np.random.default_rng(seed)
    x = _rolled(sheet.points, 3.0, 0.35 + 0.9 * c.dhat) + 0.005 * rng.standard_normal((sheet.n_vertices, 3))
    return c, x


@pytest.mark.parametrize("seed", [0, 1])
def test_self_contact_gradient_and_hessian_match_differences(seed):
    """The barrier's gradient and exact Hessian against central differences on a randomly
    perturbed near-contact spiral (many pairs inside the band)."""
    c, x = _near_contact_state(seed)
    E, g, H = c.evaluate(x, order=2)
    assert np.isfinite(E) and E > 0 and c.report(x)["active_pairs"] > 20
    q = x.ravel()
    g_fd = central_difference(lambda v: c.evaluate(v.reshape(-1, 3))[0], q, eps=1e-6)
    assert np.linalg.norm(g - g_fd) <= 1e-6 * np.linalg.norm(g)
    active = np.flatnonzero(np.abs(g) > 0)[:60]                 # columns of active vertices
    cols = []
    for k in active:
        qp, qm = q.copy(), q.copy()
        qp[k] += 1e-6
        qm[k] -= 1e-6
        cols.append((c.evaluate(qp.reshape(-1, 3), order=1)[1] - c.evaluate(qm.reshape(-1, 3), order=1)[1]) / 2e-6)
    H_fd = np.stack(cols, 1)
    Hd = H.toarray()[:, active]
    assert np.linalg.norm(Hd - H_fd) <= 1e-5 * np.linalg.norm(Hd)
    # the projected Hessian is positive semi-definite
    Hp = c.projected_hessian().toarray()
    assert np.linalg.eigvalsh((Hp + Hp.T) / 2).min() >= -1e-8 * np.abs(Hp).max()
    assert c.indefinite_part                                    # the solver may try the projection


def test_ground_barrier_derivatives():
    h = np.linspace(0.01, 0.2, 37)
    b, b1, b2 = ground_barrier(h, 0.1)
    eps = 1e-7
    bp, bm = ground_barrier(h + eps, 0.1)[0], ground_barrier(h - eps, 0.1)[0]
    inside = np.abs(h - 0.1) > 2 * eps
    assert np.allclose(b1[inside], ((bp - bm) / (2 * eps))[inside], rtol=1e-6, atol=1e-9)
    b1p, b1m = ground_barrier(h + eps, 0.1)[1], ground_barrier(h - eps, 0.1)[1]
    assert np.allclose(b2[inside], ((b1p - b1m) / (2 * eps))[inside], rtol=1e-5, atol=1e-7)
    assert np.all(b[h >= 0.1] == 0) and np.all(b[h < 0.1] > 0)
    assert ground_barrier(np.array([0.0, -1.0]), 0.1)[0].tolist() == [np.inf, np.inf]
    assert np.all(b2[h < 0.1] > 0)              # convex in the band: the ground's Hessian is PSD
    # so a ground alone has nothing to project (the solver skips the projected retry)
    pat = _strip(L=30.0, W=2.0, size=1.0)
    sheet = mesh_pattern(pat)
    c = Contact(sheet.points, sheet.triangles, offset=0.35, self_contact=False, ground=0.0)
    c.set_stiffness(np.ones(3))
    x = np.column_stack([sheet.points, np.linspace(0.01, 0.2, sheet.n_vertices)])
    E, g, H = c.evaluate(x, order=2)
    assert E > 0 and H.nnz > 0 and H.diagonal().min() >= 0 and not c.indefinite_part


def test_intersection_check_finds_crossing_triangles_only():
    """The independent check: two triangles through each other are found; the same two 0.01 mm
    apart, and two triangles sharing a vertex, are not."""
    tri = np.array([[0, 1, 2], [3, 4, 5]])
    a = np.array([[0.0, 0, 0], [2, 0, 0], [0, 2, 0]])
    b = np.array([[0.5, 0.5, -1], [0.5, 0.5, 1], [3, 3, 0.2]])
    assert intersecting_pairs(np.vstack([a, b]), tri).tolist() == [[0, 1]]
    assert len(intersecting_pairs(np.vstack([a, a + [0, 0, 0.01]]), tri)) == 0
    assert len(intersecting_pairs(np.vstack([a, b]), np.array([[0, 1, 2], [0, 4, 5]]))) == 0


def test_step_filter_stops_a_move_through_the_other_layer():
    """CCD: a move that pushes the spiral's turns through each other is cut before the offset;
    the skip test passes a flat sheet without any collision build."""
    pat = _strip(L=30.0, W=2.0, size=1.0)
    sheet = mesh_pattern(pat)
    c = Contact(sheet.points, sheet.triangles, offset=0.35, stretch_max=1.2)
    x0 = _rolled(sheet.points, 1.5, 0.6)
    x1 = _rolled(sheet.points, 1.5, 1e-3)           # all turns on one circle: through each other
    t = c.step_fraction(x0, x1)
    assert 0 < t < 1
    xt = x0 + t * (x1 - x0)
    assert c.minimum_distance(xt) > c.offset and not c.intersects(xt)
    assert c.intersects(x1) or c.minimum_distance(x1) < c.offset
    flat = np.column_stack([sheet.points / [1.2, 1.0], np.zeros(sheet.n_vertices)])
    assert not c.maybe_close(flat)
    builds = c.builds
    c.set_stiffness(np.ones(3))
    assert c.evaluate(flat, order=2)[0] == 0.0 and c.builds == builds    # skipped: nothing built
    assert c.step_fraction(flat, flat + [0, 0, 0.5]) == 1.0


def test_step_filter_checks_a_long_move_in_pieces_of_half_the_exclusion(monkeypatch):
    """A move longer than g/2 (half the exclusion) goes to ipctk's CCD in pieces of at most g/2
    of travel (its broad phase's memory grows with the square of the travel), at most
    MAX_CCD_PIECES of them: a long move that touches nothing is allowed the fraction checked,
    and one through the other layer is cut before the offset, as the whole move's CCD cuts it."""
    import shellfem.contact as sc
    pat = _strip(L=30.0, W=2.0, size=1.0)
    sheet = mesh_pattern(pat)
    c = Contact(sheet.points, sheet.triangles, offset=0.35, stretch_max=1.2)
    half = 0.5 * c.exclusion_mm
    ipctk = _ipctk()
    travels = []
    ccd = ipctk.compute_collision_free_stepsize

    def recording(mesh, a, b, **kw):
        travels.append(float(np.linalg.norm(np.asarray(b) - np.asarray(a), axis=1).max()))
        return ccd(mesh, a, b, **kw)
    monkeypatch.setattr(ipctk, "compute_collision_free_stepsize", recording)
    x0 = _rolled(sheet.points, 1.5, 0.6)
    far = x0 + [10.0 * half, 0.0, 0.0]                   # a rigid move of 10 g/2: no contact on it
    assert c.step_fraction(x0, far) == pytest.approx(sc.MAX_CCD_PIECES / 10)
    assert travels and max(travels) <= half * (1 + 1e-12) and len(travels) <= sc.MAX_CCD_PIECES
    # through the other layer, stretched to 6 g/2 of travel: cut inside the first pieces, admissible
    x1 = _rolled(sheet.points, 1.5, 1e-3)
    through = x0 + 6.0 * half / np.linalg.norm(x1 - x0, axis=1).max() * (x1 - x0)
    travels.clear()
    t = c.step_fraction(x0, through)
    xt = x0 + t * (through - x0)
    assert 0 < t < 1 and max(travels) <= half * (1 + 1e-12)
    assert c.minimum_distance(xt) > c.offset and not c.intersects(xt)
    whole = float(ccd(c._collision_mesh(), np.asfortranarray(x0), np.asfortranarray(through),
                      min_distance=c.offset, narrow_phase_ccd=ipctk.AdditiveCCD()))
    assert t == pytest.approx(whole, rel=0.05, abs=0.01)     # conservative CCD: close to the whole move's
    # two squares far apart in the printed state, one stacked 3 g/2 above the other and moved down
    # by 6 g/2: the contact is in the third piece, and the fraction is the whole move's
    g = np.stack(np.meshgrid(np.arange(6.0), np.arange(6.0), indexing="ij"), -1).reshape(-1, 2)
    quads = np.array([[i * 6 + j, (i + 1) * 6 + j, (i + 1) * 6 + j + 1, i * 6 + j + 1]
                      for i in range(5) for j in range(5)])
    tri = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    pts = np.vstack([g, g + [100.0, 0.0]])
    c2 = Contact(pts, np.vstack([tri, tri + 36]), offset=0.35, stretch_max=1.2)
    half2 = 0.5 * c2.exclusion_mm
    y0 = np.vstack([np.column_stack([g, np.zeros(36)]), np.column_stack([g + 0.3, np.full(36, 3 * half2)])])
    y1 = y0 - np.r_[np.zeros(36), np.full(36, 6 * half2)][:, None] * [0, 0, 1]
    travels.clear()
    t = c2.step_fraction(y0, y1)
    assert len(travels) == 3 and max(travels) <= half2 * (1 + 1e-12)
    exact = (3 * half2 - c2.offset) / (6 * half2)       # where the layers would be the offset apart
    assert 2 / 6 < 0.9 * exact < t < exact               # conservative (Additive CCD), in the third piece
    yt = y0 + t * (y1 - y0)
    assert c2.minimum_distance(yt) > c2.offset
    # a short move is one piece, as before
    travels.clear()
    c.step_fraction(x0, x0 + [0.5 * half, 0.0, 0.0])
    assert len(travels) <= 1


def test_a_move_shorter_than_half_the_certified_gap_needs_no_ccd(monkeypatch):
    """Once a state is evaluated, its closest non-excluded pair bounds every pair's distance; a move
    in which no vertex travels half of (that distance - offset) passes the step filter without CCD
    (two points approach by at most the sum of their travels) and ends farther than the offset; a
    longer move, or one from a state not evaluated, goes to the CCD."""
    c, x = _near_contact_state(0)                   # turns 0.9 dhat above the offset
    ipctk = _ipctk()
    calls = []
    ccd = ipctk.compute_collision_free_stepsize
    monkeypatch.setattr(ipctk, "compute_collision_free_stepsize",
                        lambda *a, **kw: (calls.append(1), ccd(*a, **kw))[1])
    assert c._certified_gap(x) is None
    c.evaluate(x, order=0)
    gap = c._certified_gap(x)
    assert 0 < gap < c.dhat and gap == pytest.approx(c.minimum_distance(x) - c.offset, rel=1e-9)
    # the outer half of the roll pulled in towards the axis (the turns approach each other)
    r = np.linalg.norm(x[:, [0, 2]] - np.median(x[:, [0, 2]], 0), axis=1)
    outer = r > np.median(r)
    radial = np.zeros_like(x)
    radial[:, [0, 2]] = -(x[:, [0, 2]] - np.median(x[:, [0, 2]], 0)) / r[:, None]
    radial[~outer] = 0.0
    short = x + 0.49 * gap * radial
    assert c.step_fraction(x, short) == 1.0 and not calls and c.certified_moves == 1
    assert c.minimum_distance(short) > c.offset
    long = x + 0.51 * gap * radial
    c.step_fraction(x, long)
    assert len(calls) == 1                           # beyond the bound: the CCD decides
    calls.clear()
    c.step_fraction(x + 1e-9, x + 1e-9 + 0.1 * gap * radial)
    assert len(calls) == 1                           # a state never evaluated: the CCD decides


def test_an_energy_judged_against_a_bound_builds_no_collisions_it_does_not_need():
    """ShellModel.energy / trial_energy with ``below``: exact when the total can be below the
    bound; when the energy without the barriers (>= 0) is already above it, that lower bound is
    returned and no collision is built nor any CCD run (the solver rejects such trials either way)."""
    sim = simulate(load_pattern("examples/strip_narrow.toml"))        # its ends touch: in contact
    M, q = sim.model, sim.result.q
    c, n = M.contact, M.n_vertices
    rng = np.random.default_rng(0)
    states = [q + 1e-6 * rng.standard_normal(q.shape) for _ in range(3)]
    barrier = [c.evaluate(y[:3 * n].reshape(n, 3))[0] for y in states]
    assert min(barrier) > 0
    total = [M.energy(y) for y in states]
    assert M.energy(states[0], below=total[0] + 1.0) == total[0]          # exact: may be below
    builds = c.builds
    lower = M.energy(states[1], below=total[1] - 2 * barrier[1])
    assert lower == pytest.approx(total[1] - barrier[1], rel=1e-12) and c.builds == builds
    checks = []
    step_fraction = c.step_fraction
    c.step_fraction = lambda *a: (checks.append(1), step_fraction(*a))[1]
    t = M.trial_energy(q, states[2], below=total[2] - 2 * barrier[2])
    assert t == pytest.approx(total[2] - barrier[2], rel=1e-12) and c.builds == builds and not checks
    assert M.trial_energy(q, states[2], below=total[2] + 1.0) == pytest.approx(total[2], rel=1e-12)
    assert len(checks) == 1


# ----------------------------------------------------------------------------- the spiral


def test_rolled_strip_is_a_spiral_whose_layers_keep_the_thickness():
    """A free bilayer strip (0.25 mm fabric + 0.1 mm plastic, pre-stretched 1.1 along its 70 mm)
    rolls 2.9 turns without contact, through itself. With contact, started from a loose spiral
    (the branch of a single roll; from flat it rolls from both ends), it ends as a spiral whose
    turns are at least the thickness apart over all pairs of triangles printed more than half a
    turn apart (exact distances, independent of ipctk), with an energy above the contact-free
    one, and with the turns and radii of a hand calculation: an Archimedean spiral of the strip's
    natural curvature (measured on the contact-free roll) with its turns in contact, pitch
    between the offset and the top of the barrier's band (measured 2.83 turns, radii 3.21 /
    4.21 mm; hand 2.76-2.78 turns, 3.07-3.15 / 4.13-4.28 mm)."""
    s, L = 1.1, 70.0
    pat = _strip(L=L, size=1.0, stretch=(s, 1.0))
    sheet = mesh_pattern(pat)
    free = simulate_sheet(sheet, pat.fabric, pat.plastic, contact=False)
    assert free.result.converged
    kappa0 = float(np.median(np.abs(free.model.curvatures(free.result.q)[0]).max(1)))
    assert centreline_turns(sheet, free.positions)[0] > 2.5            # misfit enough for > 2 turns
    start = _rolled(sheet.points, 1.0 / kappa0, 0.7, s)
    sim = simulate_sheet(sheet, pat.fabric, pat.plastic, contact=True, start=start)
    assert sim.result.converged, sim.result.reason
    offset, band = sim.model.contact.offset, sim.model.contact.dhat
    assert offset == pytest.approx(0.35)
    apart = 0.5 * 2 * np.pi / kappa0 * s
    edge = float(np.linalg.norm(np.diff(sheet.points[sheet.triangles][:, [0, 1, 2, 0]], axis=1), axis=2).max())
    assert far_pairs_min_distance(sheet, free.positions, apart, offset + 2 * edge) < 0.5 * offset
    assert far_pairs_min_distance(sheet, sim.positions, apart, offset + 2 * edge) >= offset
    assert len(intersecting_pairs(free.positions, sheet.triangles)) > 0                # through itself
    assert len(intersecting_pairs(sim.positions, sheet.triangles)) == 0                # over all pairs
    assert sim.result.energy > free.result.energy
    turns, r_in, r_out = centreline_turns(sheet, sim.positions)
    assert turns > 2.0
    lo, hi = hand_spiral(L / s, kappa0, offset), hand_spiral(L / s, kappa0, offset + band)
    assert min(lo[0], hi[0]) * 0.95 <= turns <= max(lo[0], hi[0]) * 1.05
    assert min(lo[1], hi[1]) * 0.93 <= r_in <= max(lo[1], hi[1]) * 1.07
    assert min(lo[2], hi[2]) * 0.93 <= r_out <= max(lo[2], hi[2]) * 1.07
    rep = sim.summary()["contact"]
    assert rep["active_pairs"] > 0 and offset < rep["min_distance_mm"] < offset + band


def test_coarse_level_with_the_finest_exclusion_hands_on_a_roll_that_does_not_intersect():
    """Nested iteration on a roll: a coarse mesh (2 mm) has a larger printed-state exclusion than
    the fine one (1 mm), larger than a turn of this spiral, so with its own the coarse roll
    passes through itself and the interpolated fine start intersects (the fine level restarted
    from flat). With the finest level's exclusion (Contact(exclusion_mm=...), as simulate_sheet
    gives its coarse levels) it converges without a crossing (all pairs, exact test) and hands
    the fine mesh an admissible start. A smaller exclusion than a mesh's neighbours need is
    raised to their minimum, and its skip test then still holds (every pair within patch_reach
    cells is excluded)."""
    from shellfem.multilevel import prolongate
    s = 1.1
    coarse, fine = (_strip(L=70.0, size=h, stretch=(s, 1.0)) for h in (2.0, 1.0))
    shc, shf = mesh_pattern(coarse), mesh_pattern(fine)
    cf = make_contact(shf, fine.fabric, np.zeros(0, np.int64), True, None)
    start = _rolled(shc.points, 3.2, 0.7, s)
    own = simulate_sheet(shc, coarse.fabric, coarse.plastic, contact=True, start=start)
    assert own.model.contact.exclusion_mm > 2 * cf.exclusion_mm
    x_own = prolongate(shc.points, shc.triangles, own.positions, shf.points)
    assert len(intersecting_pairs(x_own, shf.triangles)) > 0 and cf.check_start(x_own) is not None
    sim = own                                   # its model, gauge and start again, with the finest exclusion
    c = make_contact(shc, coarse.fabric, np.zeros(0, np.int64), True, None, exclusion_mm=cf.exclusion_mm)
    assert c.exclusion_mm == cf.exclusion_mm and c.patch_reach >= 0
    sim.model.contact = c
    from shellfem.newton import newton
    free = np.ones(sim.model.n_dofs, bool)
    free[sim.gauge] = False
    q0 = sim.model.initial_state()
    q0[:3 * shc.n_vertices] = start.ravel()
    r = newton(sim.model, q0, free, max_iterations=300)
    assert r.converged, r.reason
    xc = sim.model.split(r.q)[0]
    assert len(intersecting_pairs(xc, shc.triangles)) == 0
    xf = prolongate(shc.points, shc.triangles, xc, shf.points)
    assert cf.check_start(xf) is None and len(intersecting_pairs(xf, shf.triangles)) == 0
    tiny = make_contact(shc, coarse.fabric, np.zeros(0, np.int64), True, None, exclusion_mm=0.1)
    L = float(np.linalg.norm(shc.points[tiny.edges[:, 1]] - shc.points[tiny.edges[:, 0]], axis=1).max())
    assert tiny.exclusion_mm == pytest.approx(2 * (1.3 * 1.1 * (tiny.offset + tiny.dhat) + 2 * L))
    assert (tiny.patch_reach + 1) * L + 4 / 3 * L <= tiny.exclusion_mm / 2 + 1e-12
    flat = np.column_stack([shc.points / [s, 1.0], np.zeros(shc.n_vertices)])
    tiny.set_stiffness(np.ones(3))
    assert tiny.evaluate(flat, order=1)[0] == 0.0                   # its neighbours are not in contact


# ----------------------------------------------------------------------------- the ground


def _draping(ground=None, **extra):
    raw = {"fabric": {"rectangle": [20.0, 20.0], "stretch": 1.2, "thickness_mm": 0.8, "areal_weight_n_per_mm2": 1e-5},
           "support": [{"points": [[10.0, 10.0], [8.0, 10.0], [12.0, 10.0], [10.0, 8.0], [10.0, 12.0]], "fix": "z"}],
           "mesh": {"size_mm": 2.0}, "solver": {"coarse_levels": 0}}
    if ground is not None:
        raw["ground"] = {"enabled": ground}
    raw.update(extra)
    return parse_pattern(raw)


def _held_z(sim):
    """(n,) bool: the vertices whose z a support holds."""
    held = np.zeros(sim.sheet.n_vertices, bool)
    held[sim.fixed[sim.fixed % 3 == 2] // 3] = True
    return held


def test_bare_sheet_under_gravity_rests_on_the_ground():
    """A bare fabric sheet held at its centre (five points, fix = "z") under gravity: the ground
    is on by default; with [ground] enabled = false its rim hangs below the table; with the
    ground no point is below the plane, the supports stand at the top of the barrier's band and
    the rim rests in the band (the barrier's distance tolerance)."""
    hanging = simulate(_draping(ground=False))
    assert hanging.model.contact.ground is None
    assert hanging.result.converged and hanging.positions[:, 2].min() < -0.3
    pat = _draping()
    assert pat.ground == 0.0                                    # on by default: a "z" support and gravity
    sim = simulate(pat)
    assert sim.result.converged, sim.result.reason
    z = sim.positions[:, 2]
    c = sim.model.contact
    held = _held_z(sim)
    assert np.all(z[held] == support_plane(sim.sheet, pat.fabric, 0.0)) and c.dhat == support_plane(sim.sheet, pat.fabric, 0.0)
    assert z.min() > 0.0                                        # nothing below the plane
    assert z[~held].min() < c.dhat and z.max() < 2 * c.dhat     # resting on it
    rep = sim.summary()["contact"]
    assert rep["ground"] == 0.0 and 0 < rep["ground_min_height_mm"] < c.dhat


def _curling(ground=None):
    raw = {"fabric": {"rectangle": [30.0, 8.0], "stretch": 1.35, "thickness_mm": 0.8},
           "region": [{"polygon": [[0, 0], [30, 0], [30, 8], [0, 8]], "thickness_mm": 0.3, "side": "front"}],
           "support": [{"points": [[13.0, 2.0], [17.0, 2.0], [13.0, 6.0], [17.0, 6.0]], "fix": "z"}],
           "mesh": {"size_mm": 1.5}, "solver": {"coarse_levels": 0}}
    if ground is not None:
        raw["ground"] = {"enabled": ground}
    return parse_pattern(raw)


def test_printed_sheet_on_its_support_has_its_lowest_point_at_the_plane():
    """Front plastic curls the sheet towards -z: held at four points of its centre on the table
    (fix = "z", no gravity), its ends go below the plane with [ground] enabled = false; with the
    ground (on by default) its lowest point is at the plane, within the barrier's band above it,
    and nothing is below it."""
    below = simulate(_curling(ground=False))
    assert below.result.converged and below.positions[:, 2].min() < -1.0
    pat = _curling()
    assert pat.ground == 0.0
    sim = simulate(pat)
    assert sim.result.converged, sim.result.reason
    z = sim.positions[:, 2]
    c = sim.model.contact
    held = _held_z(sim)
    assert np.all(z[held] == c.dhat)                            # the supports at the band's top
    assert 0.0 < z.min() < c.dhat                               # the lowest point at the plane
    assert sim.result.energy > below.result.energy


def _small_dome(ground=None):
    """The gallery dome (examples/gallery/dome.toml) at 15 mm: stars whose arms shorten towards
    the rim, the rim held on the table (boundary, fix = "z")."""
    raw = {"fabric": {"hexagon": 15.0, "stretch": 1.35, "thickness_mm": 0.8},
           "plastic": {"young_modulus_mpa": 3360.0, "poisson": 0.5},
           "stars": {"spacing_mm": 6.0, "arm_length": "clip(0.75 - 0.45 * r / 15, 0.2, 0.75)", "thickness_mm": 0.3,
                     "arm_width_mm": 0.8, "side": "front"},
           "support": [{"boundary": True, "fix": "z"}], "mesh": {"size_mm": 2.0, "across": 1.0},
           "solver": {"coarse_levels": 0}}
    if ground is not None:
        raw["ground"] = {"enabled": ground}
    return parse_pattern(raw)


def test_held_rim_dome_on_the_ground_is_the_dome_without_it():
    """A dome held on its rim rises from the table (the solution without the ground dips 0.015 mm
    below its supports): the ground, on by default, leaves it as it is - the same energy to 1e-4
    and the same largest fibre bend - with nothing below the plane. With the supports held on
    the plane itself (where the barrier is infinite) and a lifted start snapped down to them, the
    rim's neighbours were pushed up by most of the band within one edge: the energy 5 % higher
    here, and at 18 mm a folded state (|k z| 78, not converged)."""
    off = simulate(_small_dome(ground=False))
    pat = _small_dome()
    assert pat.ground == 0.0
    on = simulate(pat)
    assert off.result.converged and on.result.converged, on.result.reason
    assert off.positions[~_held_z(off), 2].min() < 0.0          # it would dip below its supports
    assert on.result.energy == pytest.approx(off.result.energy, rel=1e-4)
    assert on.summary()["max_fibre_kz"] == pytest.approx(off.summary()["max_fibre_kz"], rel=1e-3)
    assert on.positions[:, 2].min() > 0.0


def test_lifted_start_is_smooth_and_above_the_plane():
    """The ground's start (shellfem.boundary.lifted_perturbation): 0 at the held vertices,
    positive elsewhere, with no step at the supports (no neighbour of a held vertex farther above
    it than the slope of the bubble allows), seeded; a sheet without held vertices is lifted whole."""
    from shellfem.boundary import lifted_perturbation
    sheet = mesh_pattern(_small_dome())
    tri = sheet.triangles
    e = np.unique(np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1), axis=0)
    r = np.linalg.norm(sheet.points - sheet.points.mean(0), axis=1)
    held = r > r.max() - 1e-6
    z = lifted_perturbation(sheet.points, tri, e, held, 0, 0.3, 0.1)
    assert np.all(z[held] == 0.0) and z[~held].min() > 0.0 and z.max() <= 0.45 + 1e-12
    length = np.linalg.norm(sheet.points[e[:, 0]] - sheet.points[e[:, 1]], axis=1)
    slope = np.abs(z[e[:, 0]] - z[e[:, 1]]) / length
    assert slope.max() < 0.3                                    # 0.45 mm over a 15 mm radius: no step
    assert not np.array_equal(z, lifted_perturbation(sheet.points, tri, e, held, 1, 0.3, 0.1))
    free = lifted_perturbation(sheet.points, tri, e, np.zeros(len(z), bool), 0, 0.3, 0.1)
    assert free.min() == pytest.approx(0.1) and 0.1 + 0.3 <= free.max() <= 0.1 + 0.6 + 1e-12


def test_support_below_the_ground_is_a_reason_not_a_converged_state():
    """A post (fix = "xyz") held below a raised ground forces penetration: a reason, not a
    converged state; "z" supports stand on the ground wherever it is (at the band's top)."""
    raw = {"fabric": {"rectangle": [20.0, 8.0], "stretch": 1.35, "thickness_mm": 0.8},
           "region": [{"polygon": [[0, 0], [20, 0], [20, 8], [0, 8]], "thickness_mm": 0.3, "side": "front"}],
           "support": [{"points": [[10.0, 4.0]], "fix": "xyz", "position": [[7.4, 3.0, 0.0]]}],
           "mesh": {"size_mm": 2.0}, "solver": {"coarse_levels": 0}, "ground": {"enabled": True, "height_mm": 1.0}}
    # a stated position below the ground is the pattern's contradiction: the reader says so
    # (issue 19; with coarse levels the solve ended in non-finite numbers instead of the reason)
    with pytest.raises(SelfshapeError, match=r"\[\[support\]\] #1 position 1 is at z = 0 mm, below the \[ground\]"):
        parse_pattern(raw)
    pattern = parse_pattern({**raw, "ground": {"enabled": True, "height_mm": 0.0}})
    pattern.ground = 1.0                    # a Python caller's pattern: the solver's own check
    sim = simulate(pattern)
    assert not sim.result.converged and "forces penetration" in sim.result.reason
    raw["support"] = [{"points": [[10.0, 4.0], [9.0, 4.0], [11.0, 4.0]], "fix": "z"}]
    sim = simulate(parse_pattern(raw))
    assert sim.result.converged, sim.result.reason
    held = _held_z(sim)
    assert np.all(sim.positions[held, 2] == 1.0 + sim.model.contact.dhat) and sim.positions[:, 2].min() > 1.0


def test_intersecting_start_is_a_reason_not_a_converged_state():
    pat = _strip(L=30.0, W=2.0, size=1.0)
    sheet = mesh_pattern(pat)
    start = _rolled(sheet.points, 1.5, 0.1, 1.2)          # turns 0.1 mm apart: through the 0.35 mm offset
    sim = simulate_sheet(sheet, pat.fabric, pat.plastic, contact=True, start=start)
    assert not sim.result.converged
    assert "intersects itself" in sim.result.reason or "closer than the thickness offset" in sim.result.reason


# ----------------------------------------------------------------------------- keys, defaults, outputs


def test_contact_disabled_gives_the_answer_without_contact():
    """[contact] enabled = false is the engine without contact, bit for bit (the README's
    strip_narrow numbers without contact: 27 iterations, 4.40077 N mm); with contact the strip's ends, which
    pass through each other without it, are held apart."""
    pat = load_pattern("examples/strip_narrow.toml")
    assert pat.contact is True and pat.ground is None
    pat.contact = False
    off = simulate(pat)
    sheet = off.sheet
    plain = simulate_sheet(sheet, pat.fabric, pat.plastic, seed=pat.seed, coarse=(), contact=False)
    assert off.model.contact is None and off.result.iterations == 27
    assert off.result.energy == pytest.approx(4.40077, abs=5e-6)
    ref = simulate_sheet(off.sheet, pat.fabric, pat.plastic, contact=False)
    assert np.array_equal(plain.result.q, ref.result.q)
    c = make_contact(sheet, pat.fabric, off.fixed, True, None)
    assert c.intersects(off.positions)                          # the contact-free strip passes through itself
    pat.contact = True
    on = simulate(pat)
    assert on.result.converged and not on.model.contact.intersects(on.positions)
    assert on.model.contact.minimum_distance(on.positions) > on.model.contact.offset
    assert on.result.energy > off.result.energy


@pytest.mark.parametrize("table, message", [
    ({"contact": {"enabled": 1}}, "[contact]: enabled must be true or false"),
    ({"contact": {"enable": True}}, "[contact]: unknown key 'enable' (did you mean 'enabled'?)"),
    ({"ground": {"enabled": "yes"}}, "[ground]: enabled must be true or false"),
    ({"ground": {"height_mm": "0"}}, "[ground]: height_mm must be a number"),
    ({"ground": {"height_mm": float("nan")}}, "[ground]: height_mm must be a finite number"),
    ({"ground": {"hight_mm": 0.0}}, "did you mean 'height_mm'?"),
    ({"ground": 3}, "[ground] must be a table"),
    ({"contact": {"exclusion_mm": -1.0}}, "[contact]: exclusion_mm"),
    ({"contact": {"exclusion_mm": "min"}}, "[contact]: exclusion_mm must be a number"),
    ({"contact": {"exclusion": 0.0}}, "did you mean 'exclusion_mm'?"),
])
def test_contact_keys_bad_input_is_one_line(table, message):
    raw = {"fabric": {"rectangle": [20.0, 8.0]},
           "region": [{"polygon": [[0, 0], [20, 0], [20, 8], [0, 8]], "thickness_mm": 0.3}], **table}
    with pytest.raises(SelfshapeError) as e:
        parse_pattern(raw, src="p.toml")
    assert message in str(e.value) and "\n" not in str(e.value)


def test_exclusion_key_sets_the_exclusion_raised_to_its_minimum_on_every_level():
    """[contact] exclusion_mm: 0 asks for the mesh's minimum 2 (1.3 s_max (offset + band) + 2 L),
    a value between that and the mesh's own is taken as it is, a larger one too (more excluded);
    absent: the mesh's own. Coarse levels of nested iteration take the same value."""
    pat = _strip(L=30.0, W=4.0, size=1.0)
    sheet = mesh_pattern(pat)
    own = make_contact(sheet, pat.fabric, np.zeros(0, np.int64), True, None)
    c0 = make_contact(sheet, pat.fabric, np.zeros(0, np.int64), True, None, 0.0)
    L = float(np.linalg.norm(np.diff(sheet.points[own.edges], axis=1)[:, 0], axis=1).max())
    assert c0.exclusion_mm == pytest.approx(2 * (1.3 * 1.2 * (c0.offset + c0.dhat) + 2 * L))
    assert c0.exclusion_mm < own.exclusion_mm
    mid = 0.5 * (c0.exclusion_mm + own.exclusion_mm)
    assert make_contact(sheet, pat.fabric, np.zeros(0, np.int64), True, None, mid).exclusion_mm == mid
    big = make_contact(sheet, pat.fabric, np.zeros(0, np.int64), True, None, 3 * own.exclusion_mm)
    assert big.exclusion_mm == 3 * own.exclusion_mm and big.patch_reach == own.patch_reach
    raw = {"fabric": {"rectangle": [20.0, 8.0]}, "contact": {"exclusion_mm": 0.0},
           "region": [{"polygon": [[0, 0], [20, 0], [20, 8], [0, 8]], "thickness_mm": 0.3}]}
    assert parse_pattern(raw).contact_exclusion == 0.0
    assert parse_pattern({**raw, "contact": {}}).contact_exclusion is None
    small = load_pattern("examples/stars_tube_small.toml")        # the recipe the README row measures
    assert (small.contact_exclusion, small.metric_predictor, small.release_steps, small.contact) == (0.0, False, 8, True)


def test_contact_key_defaults():
    """Self-contact on by default; the ground on by default where a support stands the sheet on
    the table: a "z" support, or under gravity an "xyz" support at its relaxed position (z = 0);
    not for a free sheet nor for posts at stated positions (a jig, a frame in the air), gravity
    or not; [ground] enabled overrides either way."""
    base = {"fabric": {"rectangle": [20.0, 8.0]},
            "region": [{"polygon": [[0, 0], [20, 0], [20, 8], [0, 8]], "thickness_mm": 0.3}]}
    heavy = {"rectangle": [20.0, 8.0], "areal_weight_n_per_mm2": 1e-5}
    p = parse_pattern(dict(base))
    assert p.contact is True and p.ground is None                     # free sheet: no ground
    p = parse_pattern({**base, "support": [{"points": [[10.0, 4.0]], "fix": "z"}]})
    assert p.ground == 0.0                                              # on the table
    p = parse_pattern({**base, "fabric": heavy, "support": [{"points": [[10.0, 4.0]], "fix": "xyz"}]})
    assert p.ground == 0.0                                              # pinned to the table, gravity
    p = parse_pattern({**base, "support": [{"points": [[10.0, 4.0]], "fix": "xyz"}]})
    assert p.ground is None                                             # pinned, no gravity
    post = {"points": [[10.0, 4.0]], "fix": "xyz", "position": [[7.4, 3.0, 20.0]]}
    p = parse_pattern({**base, "fabric": heavy, "support": [post]})
    assert p.ground is None                                             # hung from a post in the air
    p = parse_pattern({**base, "fabric": heavy, "support": [post], "ground": {"enabled": True}})
    assert p.ground == 0.0
    p = parse_pattern({**base, "support": [{"points": [[10.0, 4.0]], "fix": "z"}],
                       "ground": {"enabled": False}, "contact": {"enabled": False}})
    assert p.ground is None and p.contact is False
    p = parse_pattern({**base, "support": [post], "ground": {"enabled": True, "height_mm": -2.5}})
    assert p.ground == -2.5
    with pytest.raises(SelfshapeError, match=r"\[ground\] enabled = true needs a \[\[support\]\]"):
        parse_pattern({**base, "ground": {"enabled": True, "height_mm": -2.5}})   # nothing holds it there


def test_outputs_report_contact(tmp_path):
    """summary.json has the contact entry and deployed.vtu the in_contact cell field."""
    import meshio

    from forward.simulate import simulate_pattern_file
    path = tmp_path / "curl.toml"
    path.write_text(open("examples/strip_narrow.toml").read())
    summary = simulate_pattern_file(str(path), str(tmp_path / "out"), render=False)
    saved = json.loads((tmp_path / "out" / "summary.json").read_text())
    c = saved["contact"]
    assert c["enabled"] is True and c["active_pairs"] > 0 and c["min_distance_mm"] > c["offset_mm"] == 1.1
    assert summary["contact"] == c
    m = meshio.read(tmp_path / "out" / "deployed.vtu")
    flag = m.cell_data["in_contact"][0]
    assert set(np.unique(flag)) == {0, 1} and 0 < flag.sum() < len(flag)


def test_skip_test_settles_a_coarse_level_that_does_not_touch_itself_and_never_skips_a_contact():
    """The skip test's triangle stage: on a coarse mesh (2 mm) with the finest level's exclusion
    (1 mm mesh), the patches next to each other are outside its reach, and their spheres always
    come within offset + dhat, so the patch stage alone built the collisions at every evaluation
    of a sheet that never comes near itself (less than a turn of a wide roll). The triangles'
    spheres settle it. Sound: wherever the test skips, ipctk finds no pair in the band at either
    end of a move and the move is free of collisions (rolls of random radius and pitch, many
    tight enough to touch)."""
    rng = np.random.default_rng(0)
    fine = mesh_pattern(_strip(L=70.0, W=20.0, size=1.0, stretch=(1.1, 1.0)))
    cf = Contact(fine.points, fine.triangles, 0.35, 1.1)
    sh = mesh_pattern(_strip(L=70.0, W=20.0, size=2.0, stretch=(1.1, 1.0)))
    c = Contact(sh.points, sh.triangles, 0.35, 1.1, exclusion_mm=cf.exclusion_mm)
    assert c.patch_reach == 0
    for _ in range(5):
        x = _rolled(sh.points, rng.uniform(11.0, 20.0), 1e-9, 1.1) + 0.05 * rng.standard_normal((sh.n_vertices, 3))
        x1 = x + 0.1 * rng.standard_normal(x.shape)
        assert not c.maybe_close(x, x1)
        c._triangles_close = lambda *a: True          # the patch stage alone
        assert c.maybe_close(x, x1)
        del c._triangles_close
    skipped, touching = _skips_are_sound(c, sh, rng, 60, (2.0, 20.0), (0.3, 1.2), 0.2, 0.5)
    assert skipped > 10 and touching > 10, (skipped, touching)


def _skips_are_sound(c, sh, rng, n, radius, pitch, noise, move):
    """Random rolls of the mesh sh (radius and pitch drawn from the ranges, mm; position noise and a
    random move up to the given sizes, mm): wherever the skip test of Contact c skips, ipctk finds no
    pair in the band at either end and the move is free of collisions. Returns (skipped, touching)."""
    ipctk = _ipctk()
    mesh = c._collision_mesh()
    skipped = touching = 0
    for k in range(n):
        x = _rolled(sh.points, rng.uniform(*radius), rng.uniform(*pitch), 1.1) \
            + rng.uniform(0, noise) * rng.standard_normal((sh.n_vertices, 3))
        x1 = x + rng.uniform(0, move) * rng.standard_normal(x.shape)
        if c.maybe_close(x, x1):
            touching += 1
            continue
        skipped += 1
        for y in (x, x1):
            col = ipctk.NormalCollisions()
            col.build(mesh, np.asfortranarray(y), c.dhat, dmin=c.offset)
            assert len(col) == 0
        assert ipctk.compute_collision_free_stepsize(mesh, np.asfortranarray(x), np.asfortranarray(x1),
                                                     min_distance=c.offset, narrow_phase_ccd=ipctk.AdditiveCCD()) == 1.0
    return skipped, touching


def test_skip_test_measures_layers_just_beyond_the_band_exactly(monkeypatch):
    """The skip test's exact stage: layers of a roll 0.75 mm apart (offset 0.35 + band 0.0875 mm)
    on a 1.5 mm mesh have triangle spheres (about 0.9 mm) that overlap across the gap, so the
    sphere stages build the collisions; the exact distances of those pairs, less the corners'
    largest moves, prove them apart. Sound: where it skips, ipctk finds no pair in the band at
    either end and the move is free of collisions; moves that close the gap are never skipped."""
    from shellfem import contact as contact_module
    sh = mesh_pattern(_strip(L=60.0, W=6.0, size=1.5, stretch=(1.1, 1.0)))
    c = Contact(sh.points, sh.triangles, 0.35, 1.1)
    rng = np.random.default_rng(2)
    x = _rolled(sh.points, 4.0, 0.75, 1.1)
    x1 = x + 0.02 * rng.standard_normal(x.shape)
    assert not c.maybe_close(x) and not c.maybe_close(x, x1)
    monkeypatch.setattr(contact_module, "EXACT_STAGE_PAIRS", 0)      # the sphere stages alone
    assert c.maybe_close(x) and c.maybe_close(x, x1)
    monkeypatch.undo()
    skipped, touching = _skips_are_sound(c, sh, rng, 40, (3.0, 8.0), (0.45, 1.0), 0.05, 0.15)
    assert skipped > 5 and touching > 5, (skipped, touching)


def test_witness_pairs_decide_a_sheet_in_contact_at_once_and_change_nothing(monkeypatch):
    """The skip test's witnesses (the closest pairs its exact stage found within reach, measured
    first at the next call) only shortcut a test that would fail: the strip_narrow example, whose
    ends touch, takes the same iterations, energy, collision builds and skips with and without
    them, and the witnesses decide most of the calls that build."""
    from shellfem import contact as contact_module

    def run():
        pat = load_pattern("examples/strip_narrow.toml")
        pat.contact = True
        sim = simulate(pat)
        c = sim.model.contact
        return sim.result.iterations, sim.result.energy, c.builds, c.skips, c.witness_hits

    with_w = run()
    monkeypatch.setattr(contact_module, "WITNESS_PAIRS", 0)
    without = run()
    assert with_w[:4] == without[:4] and without[4] == 0
    assert with_w[4] > with_w[2] / 2, with_w


def test_a_witness_that_moved_apart_is_dropped_and_the_stages_decide():
    """A roll whose layers touch (0.4 mm apart: inside offset 0.35 + band 0.0875 mm) is close by
    the exact stage, which keeps witnesses; the same call again is decided by them; once the
    layers are 0.75 mm apart the witnesses fail, are dropped, and the stages prove it apart."""
    sh = mesh_pattern(_strip(L=60.0, W=6.0, size=1.5, stretch=(1.1, 1.0)))
    c = Contact(sh.points, sh.triangles, 0.35, 1.1)
    touching = _rolled(sh.points, 4.0, 0.4, 1.1)
    assert c.maybe_close(touching) and c._witness is not None and len(c._witness) > 0
    assert c.witness_hits == 0
    assert c.maybe_close(touching) and c.witness_hits == 1
    apart = _rolled(sh.points, 4.0, 0.75, 1.1)
    assert not c.maybe_close(apart) and c._witness is None and c.witness_hits == 1


def test_a_contact_solve_creeping_against_the_collision_filter_stops_stalled():
    """A contact solve whose accepted iterations each had a trial cut by the collision filter and
    together moved the sheet by less than 1 % of the offset over STALL_ITERATIONS iterations stops,
    not converged, with the reason (stars_tube's coarse level crept like that for 290 iterations);
    one that moved or was not cut goes on."""
    from shellfem.newton import STALL_ITERATIONS, NewtonOptions, _Newton
    sim = simulate(load_pattern("examples/strip_narrow.toml"))
    free = np.ones(sim.model.n_dofs, bool)
    free[np.concatenate([sim.fixed, sim.gauge]).astype(int)] = False

    def run(cut_per_iteration, move_mm):
        state = _Newton(sim.model, sim.result.q, free, NewtonOptions())
        state.timings["contact_cuts"] = 0
        for k in range(STALL_ITERATIONS + 1):
            state.q = state.q.copy()
            state.q[0] += move_mm                      # one coordinate of one vertex moves
            state.timings["contact_cuts"] += cut_per_iteration
            if state._stalled():
                return k, state.reason
        return None, state.reason

    offset = sim.model.contact.offset
    k, reason = run(2, 1e-3 * offset / STALL_ITERATIONS)
    assert k == STALL_ITERATIONS and reason.startswith("stalled against contact") and "60 steps cut" in reason
    assert run(2, 0.02 * offset / STALL_ITERATIONS)[0] is None           # it moves: not stalled
    assert run(0, 0.0)[0] is None                                          # nothing cut: not this stall
