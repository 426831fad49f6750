"""Discrete elastic rods (shellfem.rods): exact derivatives, DER's exact cases, the
effective monolayer against the layered strip model and Timoshenko."""
import numpy as np
import pytest

from fd import central_difference
from shellfem.rods import ad
from shellfem.rods.energy import bend_measures, build_network, rest_turning_curvature
from shellfem.rods.monolayer import arm_section, monolayer_bending_stiffness, monolayer_curvature
from shellfem.strip import strip_curvature, timoshenko_curvature


# --- derivatives ------------------------------------------------------------------------------
@pytest.mark.parametrize("frame", ["surface", "up"])
@pytest.mark.parametrize("which", [0, 1, 2])
def test_bend_measures_derivatives_match_central_differences(frame, which):
    rng = np.random.default_rng(3 + which)
    v = rng.normal(size=(5, 12))
    J = bend_measures(v, frame)[which]
    for k in range(len(v)):
        g = central_difference(lambda z: bend_measures(z[None], frame)[which].v[0], v[k].copy())
        H = central_difference(lambda z: bend_measures(z[None], frame)[which].g[0], v[k].copy())
        assert np.allclose(J.g[k], g, atol=1e-7 * max(1, np.abs(g).max()))
        assert np.allclose(J.h[k], H, atol=1e-6 * max(1, np.abs(H).max()))


def test_jet_rules_on_a_known_function():
    # f = atan2(y, x) * sqrt(x^2 + y^2) / x at (x, y) = (1.3, -0.4): value, gradient, Hessian by hand-free FD
    def f(z):
        x, y = ad.Jet.inputs(np.asarray(z, float)[None])
        return ad.atan2(y, x) * (x * x + y * y).sqrt() / x
    z0 = np.array([1.3, -0.4])
    J = f(z0)
    assert J.v[0] == pytest.approx(np.arctan2(-0.4, 1.3) * np.hypot(1.3, -0.4) / 1.3, rel=1e-14)
    assert np.allclose(J.g[0], central_difference(lambda z: f(z).v[0], z0), atol=1e-8)
    assert np.allclose(J.h[0], central_difference(lambda z: f(z).g[0], z0), atol=1e-7)


def _strip_mesh(n_edges, length, half_width):
    """Three rows of vertices (y = -w, 0, +w) with the rod on the middle row; two
    triangles per cell side. Returns points (n, 2), triangles, rod vertex ids."""
    xs = np.linspace(0, length, n_edges + 1)
    P = np.concatenate([np.stack([xs, np.full_like(xs, y)], 1) for y in (-half_width, 0.0, half_width)])
    k = n_edges + 1
    tris = []
    for r in range(2):
        for i in range(n_edges):
            a, b, c, d = r * k + i, r * k + i + 1, (r + 1) * k + i, (r + 1) * k + i + 1
            tris += [(a, b, d), (a, d, c)]
    return P, np.array(tris), np.arange(k, 2 * k)


def _random_surface_network(seed=0):
    P, tris, rod = _strip_mesh(5, 10.0, 1.0)
    edges = np.stack([rod[:-1], rod[1:]], 1)
    rng = np.random.default_rng(seed)
    net = build_network(P, edges, EA=rng.uniform(1, 3, len(edges)), B1=2.0, B2=5.0, T=0.7, triangles=tris,
                        normal_rest_curvature=0.05)
    X = np.concatenate([P, np.zeros((len(P), 1))], 1)
    x = X + 0.3 * rng.normal(size=X.shape)
    return net, x


@pytest.mark.parametrize("part", ["stretch", "B1", "B2", "T"])
def test_network_energy_derivatives_match_central_differences(part):
    net, x = _random_surface_network(1)
    for name in ("EA", "B1", "B2", "T"):
        if name != {"stretch": "EA"}.get(part, part):
            setattr(net, name, np.zeros_like(getattr(net, name)))
    E, g, _, _ = net.evaluate(x)
    assert E > 0
    assert np.allclose(g, central_difference(lambda z: net.energy(z), x.ravel()), rtol=1e-6, atol=1e-7 * np.abs(g).max())
    H = net.hessian(x).toarray()
    Hfd = central_difference(lambda z: net.gradient(z), x.ravel())
    assert np.abs(H - H.T).max() < 1e-10 * np.abs(H).max()
    assert np.allclose(H, Hfd, atol=2e-6 * np.abs(H).max())


def test_offset_term_derivatives_and_its_closed_form():
    # the offset's stretch-bend coupling (shellfem.rods.energy): FD gradient and Hessian on a
    # random state, and on a uniform arc (up frame) the exact value
    #   sum_stencils EA [ -e g (k1 - r) + e^2 (k1 - r)^2 / (l0 + l1) ]  (g the Green strain)
    # and, stretched hard in compression and kinked, it stays above zero (bounded below)
    net, x = _random_surface_network(3)
    for name in ("B1", "B2", "T"):
        setattr(net, name, np.zeros_like(getattr(net, name)))
    off = build_network(_strip_mesh(5, 10.0, 1.0)[0], net.edges, EA=net.EA, B1=0.0, B2=0.0, T=0.0,
                        triangles=_strip_mesh(5, 10.0, 1.0)[1], normal_rest_curvature=0.05, offset=0.55)
    assert off.offset is not None and np.allclose(off.offset, 0.55)
    E, g, _, _ = off.evaluate(x)
    assert E != pytest.approx(net.evaluate(x)[0])                      # the term is there
    assert np.allclose(g, central_difference(lambda z: off.energy(z), x.ravel()), rtol=1e-6,
                       atol=1e-7 * np.abs(g).max())
    H = off.hessian(x).toarray()
    assert np.allclose(H, central_difference(lambda z: off.gradient(z), x.ravel()), atol=2e-6 * np.abs(H).max())
    # a regular polygon arc: n edges of chord c, turning phi per vertex, stretched by (1 + eps0)
    n, c, phi, eps0, e, EA = 6, 1.0, 0.1, -0.01, 0.4, 100.0
    ang = np.concatenate([[0.0], np.cumsum(np.full(n - 1, phi))])
    P = np.concatenate([[[0.0, 0.0]], np.cumsum(c * np.stack([np.cos(ang), np.sin(ang)], 1), 0)])
    edges = np.stack([np.arange(n), np.arange(1, n + 1)], 1)
    flat = np.stack([np.arange(n + 1) * c, np.zeros(n + 1)], 1)
    rod = build_network(flat, edges, EA=EA, B1=0.0, B2=0.0, T=0.0, up=[0.0, 0.0, 1.0], offset=e)
    X = np.concatenate([P * (1 + eps0), np.zeros((n + 1, 1))], 1)[:, [0, 2, 1]]   # the arc in the x-z plane
    k1 = rod.measures(X)[:, 0]
    assert np.allclose(np.abs(k1), 2 * np.tan(phi / 2))
    stretch = n * EA / 8 * ((c * (1 + eps0)) ** 2 - c ** 2) ** 2 / c ** 3
    g = ((1 + eps0) ** 2 - 1) / 2
    expect = stretch + np.sum(EA * (-e * g * k1 + e * e * k1 ** 2 / (2 * c)))
    assert rod.energy(X) == pytest.approx(expect, rel=1e-12)
    rng = np.random.default_rng(4)
    for squeeze in (0.2, 0.5, 0.9):          # edges shortened to 1 - squeeze, random kinks: never below 0
        Y = X.copy()
        Y[:, 0] *= 1 - squeeze
        Y[1:-1, 2] += 0.3 * rng.normal(size=n - 1)
        assert off.energy(x * (1 - squeeze)) > 0 and rod.energy(Y) > 0


def test_energy_is_invariant_under_rigid_motions_and_zero_when_printed():
    net, x = _random_surface_network(2)
    P3 = np.concatenate([_strip_mesh(5, 10.0, 1.0)[0], np.zeros((18, 1))], 1)
    net.rest[:, 0] = 0.0                                 # flat rest: the printed state is stress free
    assert net.energy(P3) == pytest.approx(0.0, abs=1e-20)
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    assert net.energy(x @ R.T + [3.0, -1.0, 2.0]) == pytest.approx(net.energy(x), rel=1e-12)


# --- a small dense Newton for the rod-only cases ---------------------------------------------
def _minimise(energy_grad_hess, x0, free, iters=500):
    """Minimise over the free coordinates with SciPy's exact trust region (dense Hessian)."""
    from scipy.optimize import minimize
    x = x0.copy().ravel()

    def full(z):
        y = x.copy()
        y[free] = z
        return energy_grad_hess(y)
    res = minimize(lambda z: full(z)[0], x[free], jac=lambda z: full(z)[1][free],
                   hess=lambda z: full(z)[2][np.ix_(free, free)], method="trust-exact",
                   options=dict(gtol=1e-11, maxiter=iters))
    x[free] = res.x
    return x.reshape(-1, 3), np.linalg.norm(energy_grad_hess(x)[1][free])


def _rod_only(net, extra=None):
    def f(x):
        E, g, _, _ = net.evaluate(x.reshape(-1, 3))
        H = net.hessian(x.reshape(-1, 3)).toarray()
        if extra is not None:
            e2, g2, h2 = extra(x)
            E, g, H = E + e2, g + g2, H + h2
        return E, g, H
    return f


def test_ring_with_natural_curvature_relaxes_to_its_circle():
    # closed rod printed as a circle of radius R (rest curvature 1/R), started as a wavy ellipse
    N, R = 24, 10.0
    phi = 2 * np.pi * np.arange(N) / N
    P = R * np.stack([np.cos(phi), np.sin(phi)], 1)
    edges = np.stack([np.arange(N), (np.arange(N) + 1) % N], 1)
    net = build_network(P, edges, EA=100.0, B1=1.0, B2=1.0, T=0.5, up=[0, 0, 1])
    assert np.allclose(np.abs(net.rest[:, 1]), 2 * np.tan(np.pi / N))          # |kb| of the rest polygon
    assert np.allclose(np.abs(net.rest[:, 1]), rest_turning_curvature(1 / R, net.rest_length[0], net.rest_length[0]))
    x0 = np.stack([1.3 * R * np.cos(phi), 0.8 * R * np.sin(phi) + 0.5 * np.sin(3 * phi), np.zeros(N)], 1)
    free = np.ones(3 * N, bool)
    free[[0, 1, 2, 5]] = False                  # vertex 0 and y of vertex 1: no rigid motion in the plane
    free[2::3] = False                          # planar
    x, gn = _minimise(_rod_only(net), x0, free)
    assert gn < 1e-9
    c = x[:, :2].mean(0)
    r = np.linalg.norm(x[:, :2] - c, axis=1)
    assert np.allclose(r, R, rtol=1e-9)
    assert net.energy(x) < 1e-18


def test_free_rod_with_normal_rest_curvature_relaxes_to_the_arc():
    # straight print, rest curvature 1/R about the width axis: a quarter circle of radius R, zero energy
    N, R = 20, 8.0
    L = R * np.pi / 2
    P = np.stack([np.linspace(0, L, N + 1), np.zeros(N + 1)], 1)
    edges = np.stack([np.arange(N), np.arange(1, N + 1)], 1)
    net = build_network(P, edges, EA=50.0, B1=1.0, B2=30.0, T=0.5, up=[0, 0, 1], normal_rest_curvature=1 / R)
    x0 = np.concatenate([P, np.zeros((N + 1, 1))], 1)
    free = np.ones(3 * (N + 1), bool)
    free[[0, 1, 2, 4, 5]] = False               # vertex 0, y and z of vertex 1: first edge along x
    free[1::3] = False                          # stays in the x-z plane
    x, gn = _minimise(_rod_only(net), x0, free)
    assert gn < 1e-9 and net.energy(x) < 1e-16
    # the vertices lie on a circle of radius R through the origin, centre at (0, 0, R) side (+z = up = d1)
    centre = np.array([0.0, 0.0, R]) if x[-1, 2] > 0 else np.array([0.0, 0.0, -R])
    assert x[-1, 2] > 0                         # k1 > 0 bends towards +d1
    # vertex 0 and the first edge's direction fix the circle only up to the first chord; use a fit
    A = np.stack([2 * x[:, 0], 2 * x[:, 2], np.ones(N + 1)], 1)
    cx, cz, k = np.linalg.lstsq(A, x[:, 0] ** 2 + x[:, 2] ** 2, rcond=None)[0]
    rad = np.sqrt(k + cx * cx + cz * cz)
    assert rad == pytest.approx(R, rel=1e-9)
    assert np.allclose(np.hypot(x[:, 0] - cx, x[:, 2] - cz), R, rtol=1e-9)
    del centre


def test_straight_rod_with_imposed_twist_has_the_exact_twist_energy():
    # the side points of every edge rotated about the axis by theta_j = Phi j / (N - 1) (held):
    # twist Phi between the first and the last edge; DER: E = T Phi^2 / (2 L'), L' = (N - 1) l,
    # exactly (the angle, not its sine: Phi / (N - 1) = 0.33 rad here)
    N, L, w, T, Phi = 10, 20.0, 1.0, 0.8, 3.0
    P, tris, rod = _strip_mesh(N, L, w)
    edges = np.stack([rod[:-1], rod[1:]], 1)
    net = build_network(P, edges, EA=40.0, B1=40.0, B2=40.0, T=T, triangles=tris)   # stiff: no twist buckling
    k, l = N + 1, L / N
    # edge j's left point is top-row vertex j + 1, its right point bottom-row vertex j
    assert np.array_equal(net.points[:, 3], 2 * k + np.arange(1, N)) and np.array_equal(net.points[:, 4], np.arange(N - 1))
    theta = Phi * np.arange(N) / (N - 1)
    x = np.concatenate([P, np.zeros((len(P), 1))], 1)
    top, bottom = 2 * k + np.arange(1, k), np.arange(N)
    x[top, 1], x[top, 2] = w * np.cos(theta), w * np.sin(theta)
    x[bottom, 1], x[bottom, 2] = -w * np.cos(theta), -w * np.sin(theta)
    assert np.allclose(net.measures(x)[:, 2], Phi / (N - 1), rtol=1e-12)
    free = np.zeros(3 * len(P), bool)
    free[3 * rod[2]:3 * rod[-2]] = True                   # the centre line, its end edges clamped
    xr, gn = _minimise(_rod_only(net), x, free)
    tau = net.measures(xr)[:, 2]
    assert gn < 1e-9
    assert np.allclose(xr[rod, 1:], 0.0, atol=1e-9)       # stays straight on the axis
    assert np.allclose(tau, Phi / (N - 1), rtol=1e-9)
    assert net.energy(xr) == pytest.approx(T * Phi ** 2 / (2 * (N - 1) * l), rel=1e-9)


def test_cantilever_under_end_moment_is_the_elastica_arc():
    # clamped at x = 0, a dead couple M at the free end (potential -M x angle of the last edge):
    # Euler's elastica is the circular arc of curvature M / B; the discrete rod converges as (l k)^2
    N, L, B, M = 60, 30.0, 2.0, 0.1
    P = np.stack([np.linspace(0, L, N + 1), np.zeros(N + 1)], 1)
    edges = np.stack([np.arange(N), np.arange(1, N + 1)], 1)
    net = build_network(P, edges, EA=1e3, B1=50 * B, B2=B, T=1.0, up=[0, 0, 1])

    def couple(x):
        x = x.reshape(-1, 3)
        j = ad.Jet.inputs((x[N] - x[N - 1])[None, :2])
        a = ad.atan2(j[1], j[0])
        g, H = np.zeros(3 * (N + 1)), np.zeros((3 * (N + 1),) * 2)
        idx = np.array([3 * (N - 1), 3 * (N - 1) + 1, 3 * N, 3 * N + 1])
        sel = np.array([[-1, 0], [0, -1], [1, 0], [0, 1]], float)
        g[idx] = -M * sel @ a.g[0]
        H[np.ix_(idx, idx)] = -M * sel @ a.h[0] @ sel.T
        return -M * a.v[0], g, H
    free = np.ones(3 * (N + 1), bool)
    free[:6] = False
    free[2::3] = False
    x, gn = _minimise(_rod_only(net, couple), np.concatenate([P, np.zeros((N + 1, 1))], 1), free)
    assert gn < 1e-8
    # continuum: the arc of curvature M / B from the clamped edge's midpoint (tangent along x)
    k, l = M / B, L / N
    arc = (N - 0.5) * l
    tip = np.array([l / 2 + np.sin(k * arc) / k, (1 - np.cos(k * arc)) / k])
    assert np.linalg.norm(x[-1, :2] - tip) < 5e-4 * L
    # discrete: every stencil carries M, B / l kb dkb/dphi = M with kb = 2 tan(phi / 2): a regular polygon
    from scipy.optimize import brentq
    phi = brentq(lambda p: B / l * 2 * np.tan(p / 2) / np.cos(p / 2) ** 2 - M, 0, 1)
    i = np.arange(N)
    assert np.allclose(x[-1, :2], l * np.stack([np.cos(i * phi), np.sin(i * phi)], 1).sum(0), atol=1e-7 * L)
    kk = np.abs(net.measures(x)[:, 1]) / l
    assert np.allclose(kk, k, rtol=1e-3)


# --- effective monolayer -------------------------------------------------------------------------
@pytest.mark.parametrize("h1,ratio", [(0.3, 3200.0), (0.45, 3200.0), (0.3, 69.0), (0.6, 20.0)])
def test_monolayer_curvature_is_timoshenko_and_the_strip_model_at_small_misfit(h1, ratio):
    h2, s = 0.8, 1.001
    k = monolayer_curvature(h1, h2, ratio, 1.0, s)
    # Timoshenko with the misfit strain of the metric difference, (1 - 1/s^2) / 2
    assert k == pytest.approx(timoshenko_curvature(h1, h2, ratio, 0.5 * (1 - 1 / s ** 2)), rel=1e-12)
    ref = strip_curvature(h1, h2, s, ratio, plastic_poisson=0.3, fabric_poisson=0.3)
    assert k == pytest.approx(ref, rel=0.02)
    assert abs(k / ref - 1) < 0.005


def test_monolayer_limits_and_plastic_set():
    h1, h2, s = 0.3, 0.8, 1.35
    # E1 >> E2: the seed's Eq. 3.17 (halved: b = 2 kappa)
    n = 1e9
    k = monolayer_curvature(h1, h2, n, 1.0, s)
    assert k == pytest.approx(0.5 * 6 * h2 * (h1 + h2) / (h1 ** 3 * n) * (1 - 1 / s ** 2), rel=1e-5)
    assert monolayer_curvature(h1, h2, 3200.0, 1.0, s, plastic_set=0.01) == pytest.approx(
        monolayer_curvature(h1, h2, 3200.0, 1.0, s) + 0.01, rel=1e-14)
    # the bending stiffness is the Schur complement of Eq. 3.10's bracket (the energy per area,
    # b = 2 kappa): min over A of M A^2 + Bq b^2 + C A b = (4 Bq - C^2 / M) kappa^2 = EI kappa^2 / 2
    E1, E2 = 3200.0, 1.0
    M, Bq, C = (E1 * h1 + E2 * h2) / 8, (E1 * h1 ** 3 + E2 * h2 ** 3) / 24, (E1 * h1 ** 2 - E2 * h2 ** 2) / 8
    assert monolayer_bending_stiffness(h1, h2, E1, E2) == pytest.approx(2 * (4 * Bq - C * C / M), rel=1e-12)
    # unequal Poisson ratios in a wide strip: the beam value differs (documented in the module)
    k_def = strip_curvature(h1, h2, 1.001, 3200.0)
    assert monolayer_curvature(h1, h2, 3200.0, 1.0, 1.001) / k_def - 1 == pytest.approx(0.38, abs=0.02)
    sec = arm_section(h1, 1.5, h2, E1, E2, s)
    assert sec.B1 == pytest.approx(1.5 * monolayer_bending_stiffness(h1, h2, E1, E2))
    assert sec.EA == pytest.approx(1.5 * (E1 * h1 + E2 * h2))


# --- rods on the fabric shell, one Newton solve ----------------------------------------------------
def _strip_with_rod(s, L=40.0, W=2.0, nx=40, ratio=3200.0):
    from shellfem.materials import Fabric, Plastic
    from shellfem.rods.coupled import rod_shell_model
    from shellfem.sheet import Sheet
    sh = Sheet.rectangle(L, W, nx, 2)
    P = sh.points
    mid = np.flatnonzero(np.abs(P[:, 1] - W / 2) < 1e-9)
    mid = mid[np.argsort(P[mid, 0])]
    M = rod_shell_model(sh, Fabric(stretch=s, young_modulus=1.0), Plastic(young_modulus=ratio, poisson=0.3),
                        np.stack([mid[:-1], mid[1:]], 1), 0.3, W, gravity=False)
    return sh, M, mid


def test_coupled_model_derivatives_and_assembly():
    from shellfem.assembly import BlockScatter
    sh, M, mid = _strip_with_rod(1.2, L=6.0, W=2.0, nx=3)
    rng = np.random.default_rng(5)
    q = M.initial_state()
    q[:3 * M.n_vertices] += 0.05 * rng.normal(size=3 * M.n_vertices)
    q[3 * M.n_vertices:] += 0.05 * rng.normal(size=M.n_edges)
    E, g, (Hf, Hh) = M.hessian_blocks(q)
    assert E == pytest.approx(M.energy(q), rel=1e-13)
    assert np.allclose(g, M.gradient(q), rtol=1e-12, atol=1e-14)
    gfd = central_difference(M.energy, q)
    assert np.allclose(g, gfd, atol=1e-6 * np.abs(g).max())
    free = np.ones(M.n_dofs, bool)
    U = BlockScatter([M.face_dofs, M.hinge_dofs], M.n_dofs, free, upper=True).matrix([Hf, Hh]).toarray()
    H = U + U.T - np.diag(np.diag(U))
    Hfd = central_difference(M.gradient, q)
    assert np.allclose(H, Hfd, atol=2e-6 * np.abs(H).max())
    # the rods are part of it: their energy is what the shell alone lacks
    assert E - M.shell.energy(q) == pytest.approx(M.rods.energy(M.split(q)[0]), rel=1e-12)
    # reusing the solver's buffers gives the same blocks
    out = M.block_buffers()
    E2, g2, (Hf2, Hh2) = M.hessian_blocks(q, out=out)
    assert Hf2 is out[0] and np.array_equal(Hf2, Hf) and np.array_equal(g2, g)


def _released_strip_curvature(M, sh, mid):
    """Release the strip model M (sheet sh) from flat with a seeded bump; returns the Newton
    result and the curvature (1/mm) of the circle fitted to its centre line ``mid`` (vertex
    indices along x) between x = 10 and 30 mm."""
    from shellfem.boundary import gauge_dofs, smooth_perturbation
    from shellfem.newton import newton
    q = M.initial_state()
    x, _ = M.split(q)
    x[:, 2] += smooth_perturbation(sh.points, 0, 0.4)
    free = np.ones(M.n_dofs, bool)
    free[gauge_dofs(x, np.zeros(0, int))] = False
    r = newton(M, q, free, max_iterations=100)
    assert r.converged, r.reason
    xm = M.split(r.q)[0][mid]
    pts = xm[(sh.points[mid, 0] > 10) & (sh.points[mid, 0] < 30)]
    c = pts.mean(0)
    pl = (pts - c) @ np.linalg.svd(pts - c)[2][:2].T
    a, b, kk = np.linalg.lstsq(np.stack([2 * pl[:, 0], 2 * pl[:, 1], np.ones(len(pl))], 1), (pl ** 2).sum(1),
                               rcond=None)[0]
    return r, 1 / np.sqrt(kk + a * a + b * b)


def test_free_arm_on_fabric_bends_to_the_bilayer_closed_form():
    # a 40 x 2 mm fabric strip, a rod (h1 0.3, width 2, E1/E2 3200) on its centre line, released from
    # s = 1.001: the centre line's curvature is the effective monolayer's / Timoshenko's and the
    # layered strip model's (equal Poisson ratios) within 2 %
    s = 1.001
    sh, M, mid = _strip_with_rod(s)
    r, kappa = _released_strip_curvature(M, sh, mid)
    mono = monolayer_curvature(0.3, 0.8, 3200.0, 1.0, s)
    assert kappa == pytest.approx(mono, rel=0.005)          # measured 0.23 % (the fabric's own k_B)
    assert kappa < mono
    assert kappa == pytest.approx(strip_curvature(0.3, 0.8, s, 3200.0, plastic_poisson=0.3, fabric_poisson=0.3),
                                  rel=0.02)
    # front plastic: the arm bends towards -z (centre of curvature on the fabric side)
    k1 = M.rod_measures(r.q)[:, 0]
    assert np.all(k1 < 0)


def test_offset_rod_on_fabric_is_timoshenkos_bilayer():
    # the arm printed ON the fabric (coupled.arm_rods offset=True): the plastic's rod (h1 0.3, width 2,
    # E1/E2 3200, no rest curvature) 0.55 mm above the mid-surface of a 40 x 2 mm fabric strip,
    # released from s = 1.001: the bilayer effect now comes from the mesh's fabric pulling at the
    # mid-surface, and the curvature is Timoshenko's for these two layers (the rod: EA, B1; the
    # fabric: E2 h2 W and its k_B W; distance between their centre lines e):
    #   kappa = delta / (e + (B1 + D_f) (1 / Y_f + 1 / EA) / e),  delta = 1 - 1/s
    from shellfem.materials import Fabric, Plastic
    from shellfem.rods.coupled import rod_shell_model
    from shellfem.sheet import Sheet
    s, L, W = 1.001, 40.0, 2.0
    sh = Sheet.rectangle(L, W, 40, 2)
    P = sh.points
    mid = np.flatnonzero(np.abs(P[:, 1] - W / 2) < 1e-9)
    mid = mid[np.argsort(P[mid, 0])]
    fab, pla = Fabric(stretch=s, young_modulus=1.0), Plastic(young_modulus=3200.0, poisson=0.3)
    M = rod_shell_model(sh, fab, pla, np.stack([mid[:-1], mid[1:]], 1), 0.3, W, gravity=False, offset=True)
    assert np.allclose(M.rods.offset, 0.55) and np.all(M.rods.rest[:, 0] == 0.0)
    r, kappa = _released_strip_curvature(M, sh, mid)
    EA, B1, e = 3200.0 * 0.3 * W, 3200.0 * 0.3 ** 3 * W / 12, 0.55
    Yf, Df = 1.0 * 0.8 * W, fab.bending_stiffness * W
    closed = (1 - 1 / s) / (e + (B1 + Df) * (1 / Yf + 1 / EA) / e)
    assert kappa == pytest.approx(closed, rel=0.01)                # measured -0.70 %
    # and the seed's monolayer of the same arm (rods in the fabric) within a few per cent: the same bilayer
    assert kappa == pytest.approx(monolayer_curvature(0.3, 0.8, 3200.0, 1.0, s), rel=0.01)   # -0.34 %
    assert np.all(M.rod_measures(r.q)[:, 0] < 0)                 # front: towards -z, as the bilayer


# --- [solver] model = "rods" ----------------------------------------------------------------------
def _star_pattern(**solver):
    return {"fabric": {"rectangle": [30.0, 26.0], "stretch": 1.35, "thickness_mm": 0.8},
            "stars": {"spacing_mm": 10.0, "arm_length": 0.6, "thickness_mm": 0.3, "arm_width_mm": 0.8},
            "mesh": {"size_mm": 2.0}, "solver": dict(solver)}


def test_rods_model_key_is_validated():
    from geometry.patterns import parse_pattern
    from shellfem.errors import SelfshapeError
    assert parse_pattern(_star_pattern()).solver_model == "shell"
    assert parse_pattern(_star_pattern(model="rods")).solver_model == "rods"
    with pytest.raises(SelfshapeError, match=r"^p.toml: \[solver\]: model must be one of 'shell', 'rods', got 'rod'$"):
        parse_pattern(_star_pattern(model="rod"), "p.toml")
    raw = _star_pattern(model="rods")
    raw["region"] = [{"polygon": [[2.0, 2.0], [8.0, 2.0], [8.0, 8.0], [2.0, 8.0]], "thickness_mm": 0.4}]
    with pytest.raises(SelfshapeError) as e:
        parse_pattern(raw, "p.toml")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith('p.toml: [solver] model = "rods" supports [stars] and [[ribbon]]')
    assert "region" in msg
    raw = _star_pattern(model="rods")
    raw["ribbon"] = [{"path": [[2.0, 25.0], [28.0, 25.0]], "width_mm": 1.5, "thickness_mm": 0.4}]
    assert len(parse_pattern(raw).elements[0].centrelines) == 1


def test_rods_mesh_has_the_arm_centre_lines_as_edges():
    from shapely.geometry import LineString
    from geometry.centrelines import mesh_pattern_rods, pattern_centrelines
    from geometry.patterns import parse_pattern
    p = parse_pattern(_star_pattern(model="rods"))
    rm = mesh_pattern_rods(p)
    P = rm.sheet.points
    lines = pattern_centrelines(p)
    inner = p.outline.buffer(-0.25 * 2.0)
    for i, (path, h, w, side) in enumerate(lines):
        mine = rm.line == i
        seg = LineString(path).intersection(inner)
        if not mine.any():
            assert seg.length < 0.5 * 2.0                               # dropped: shorter than half a segment
            continue
        L = np.linalg.norm(P[rm.edges[mine, 1]] - P[rm.edges[mine, 0]], axis=1)
        assert L.sum() == pytest.approx(seg.length, rel=1e-9)          # the edges cover the (clipped) arm
        assert np.all(L <= min(2.0, seg.length / 4) * (1 + 1e-9))
        d = np.array([LineString(path).distance(__import__("shapely").points(v)) for v in P[np.unique(rm.edges[mine])]])
        assert d.max() < 1e-9                                           # on the arm
    assert np.all(rm.thickness == 0.3) and np.all(rm.width == 0.8) and np.all(rm.side == 1)
    # stars are joined: the three arms of an inner star share their centre vertex
    deg = np.bincount(rm.edges.ravel(), minlength=rm.sheet.n_vertices)
    assert (deg == 3).sum() >= 4


def test_rods_model_simulates_a_star_sheet():
    from forward.simulate import simulate
    from geometry.patterns import parse_pattern
    sim = simulate(parse_pattern(_star_pattern(model="rods")))
    s = sim.summary()
    assert s["model"] == "rods" and s["converged"], s["reason"]
    assert s["n_rod_edges"] == len(sim.model.rods.edges) > 0
    # the arms bend towards the fabric side (front print: k1 < 0) and the fabric contracts
    k1 = sim.model.rod_measures(sim.result.q)[:, 0]
    w = sim.model.rods.weight > 0.9 / (sim.model.rods.rest_length.max() * 2)        # ordinary arm stencils
    assert np.median(k1[w]) < 0
    assert s["bbox_mm"][0] < 30.0 / 1.05
    # the shell model says so too (a small printed strip, the default model)
    from forward.simulate import simulate_sheet
    from shellfem.materials import Fabric, Plastic
    from shellfem.sheet import Sheet
    sh = Sheet.rectangle(10.0, 2.0, 10, 2)
    sh = Sheet(sh.points, sh.triangles, thickness_front=np.full(sh.n_triangles, 0.3))
    assert simulate_sheet(sh, Fabric(stretch=1.1), Plastic()).summary()["model"] == "shell"


def test_arm_rods_take_the_misfit_along_each_edge_and_the_side():
    from shellfem.materials import Fabric, Plastic
    from shellfem.rods.coupled import arm_rods
    from shellfem.sheet import Sheet
    sh = Sheet.rectangle(8.0, 8.0, 4, 4)
    P = sh.points
    row = np.flatnonzero(np.abs(P[:, 1] - 4.0) < 1e-9)
    row = row[np.argsort(P[row, 0])]
    col = np.flatnonzero(np.abs(P[:, 0] - 4.0) < 1e-9)
    col = col[np.argsort(P[col, 1])]
    fab, pla = Fabric(stretch=(1.35, 1.0), young_modulus=1.0), Plastic(young_modulus=3200.0)
    for path, s in ((row, 1.35), (col, 1.0)):
        edges = np.stack([path[:-1], path[1:]], 1)
        l = 2.0
        k = monolayer_curvature(0.3, 0.8, 3200.0, 1.0, s)
        front = arm_rods(sh, edges, 0.3, 0.8, fab, pla, side="front")
        back = arm_rods(sh, edges, 0.3, 0.8, fab, pla, side=-np.ones(len(edges)))
        assert np.allclose(front.rest[:, 0], -rest_turning_curvature(k, l, l), atol=1e-15)
        assert np.allclose(back.rest[:, 0], rest_turning_curvature(k, l, l), atol=1e-15)
    with pytest.raises(ValueError):
        arm_rods(sh, edges, 0.3, 0.8, fab, pla, side="top")


def test_rods_model_writes_the_simulate_outputs(tmp_path):
    # `selfshape simulate` on a rods pattern: every output written, summary.json says "rods"
    import json
    from forward.simulate import simulate_pattern_file
    from geometry.patterns import write_pattern
    path = tmp_path / "stars.toml"
    write_pattern(str(path), _star_pattern(model="rods"))
    s = simulate_pattern_file(str(path), str(tmp_path / "out"))
    assert s["model"] == "rods" and s["converged"]
    on_disk = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert on_disk["model"] == "rods" and on_disk["n_rod_edges"] == s["n_rod_edges"]
    for name in ("deployed.vtu", "deployed.png", "index.html"):
        assert (tmp_path / "out" / name).stat().st_size > 0


def test_three_armed_junction_is_the_seeds_pairwise_split():
    # Fig. 3.3: a star centre joins every pair of its three arms, each pair with half weight;
    # the printed 120 degree angle is the pairs' rest (|kb| = 2 tan(30 deg)), so the print is stress free
    L, n = 6.0, 3
    th = np.radians([0.0, 120.0, 240.0])
    pts = [np.zeros(2)] + [np.array([np.cos(a), np.sin(a)]) * L * (j + 1) / n for a in th for j in range(n)]
    P = np.array(pts)
    edges = []
    for a in range(3):
        ids = [0] + [1 + a * n + j for j in range(n)]
        edges += list(zip(ids[:-1], ids[1:]))
    net = build_network(P, np.array(edges), EA=10.0, B1=1.0, B2=3.0, T=0.5, up=[0, 0, 1])
    at_centre = net.points[:, 1] == 0
    l = L / n
    assert at_centre.sum() == 3
    assert np.allclose(net.weight[at_centre], 0.5 / (2 * l)) and np.allclose(net.weight[~at_centre], 1 / (2 * l))
    assert np.allclose(np.abs(net.rest[at_centre, 1]), 2 * np.tan(np.radians(30.0)))
    X = np.concatenate([P, np.zeros((len(P), 1))], 1)
    assert net.energy(X) == pytest.approx(0.0, abs=1e-24)
    # turning one arm rigidly in the plane by d about the centre: its two pairs change their in-plane
    # turning by +-d, each pair costs (1/2) B2 (2 tan((60 +- d)/2) - 2 tan(30))^2 / (2 l)
    d = np.radians(2.0)
    x = X.copy()
    c, s = np.cos(d), np.sin(d)
    arm = np.arange(1, n + 1)
    x[arm, :2] = x[arm, :2] @ np.array([[c, s], [-s, c]])
    kb0 = 2 * np.tan(np.radians(30.0))
    expect = sum(0.5 * 3.0 * (2 * np.tan((np.radians(60.0) + sg * d) / 2) - kb0) ** 2 / (2 * l) for sg in (1, -1))
    assert net.energy(x) == pytest.approx(expect, rel=1e-9)


def test_selfshape_simulate_refuses_rods_on_a_region_in_one_line(tmp_path, capsys):
    # `selfshape simulate` on a model = "rods" pattern with a [[region]] (no centre line): status 2,
    # one line on stderr naming the file and the element, nothing written
    from geometry.patterns import write_pattern
    from selfshape.cli import main
    raw = _star_pattern(model="rods")
    raw["region"] = [{"polygon": [[2.0, 2.0], [8.0, 2.0], [8.0, 8.0], [2.0, 8.0]], "thickness_mm": 0.4}]
    path = tmp_path / "p.toml"
    write_pattern(str(path), raw)
    assert main(["simulate", str(path), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("selfshape simulate: error: ")
    assert '[solver] model = "rods" supports [stars] and [[ribbon]]' in err and "p.toml" in err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
