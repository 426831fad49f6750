"""Layered Kirchhoff-Love shell energies of the fundamental forms (N, mm, MPa).

State per triangle: z = (a11, a12, a22, b11, b12, b22), the first and second fundamental
forms in the triangle's edge basis (see shellfem.kinematics for the convention), and the
third fundamental form c = b a^-1 b that follows from them.

Exact Kirchhoff-Love metric. A layer of Young's modulus E, Poisson's ratio nu occupies
z in [z0, z1] along the normal of the mesh surface. Under the Kirchhoff-Love hypotheses
(normals stay straight, normal and unstretched) the point x + z n has the in-plane metric

    g(z) = a - 2 z b + z^2 c,         c = b a^-1 b          (exact in z, no truncation)

and its rest state, the offset body of the layer's rest surface (rest metric abar, rest
curvature bbar), has gbar(z) = abar - 2 z bbar + z^2 cbar. The layer is St.Venant-Kirchhoff
in the Green strain of that rest body, eps(z) = 1/2 gbar(z)^-1 (g(z) - gbar(z)), in plane
stress (the elastic norm of seed Eq. 3.8),

    ||M||^2 = nu/(1-nu^2) tr(M)^2 + 1/(1+nu) tr(M^2),

and the energy is int (E/2) ||eps(z)||^2 mu(z) dz dA_rest with the rest volume element
mu(z) = sqrt(det gbar(z) / det abar) = 1 - 2 Hbar z + Kbar z^2 (Hbar, Kbar the rest mean and
Gaussian curvature). Choice: the norm uses gbar(z) and the volume element is kept, so this is
the 3D St.Venant-Kirchhoff energy of the Kirchhoff body integrated exactly through the
thickness: a free layer relaxes exactly to its rest shape (a = abar, b = bbar), and the energy
differs from the 3D model of the same hypotheses by nothing in z. For a flat rest state
(bbar = 0: the fabric, and the plastic without a set) gbar(z) = abar and mu = 1, so abar or
gbar(z) in the norm is no choice at all; with a rest curvature the alternative (abar in the
norm, mu = 1) would be off by O(kappabar h) relative.

With D0 = a - abar, D1 = b - bbar, D2 = c - cbar, g - gbar = D0 - 2 z D1 + z^2 D2, so

    W = 1/2 w^T Q9 w,   w = (D0, D1, D2),
    Q9 = E A/4 [[M0, -2 M1, M2], [-2 M1, 4 M2, -2 M3], [M2, -2 M3, M4]],
    M_k = int_z0^z1 z^k K(gbar(z)) mu(z) dz   (3 x 3; ||gbar^-1 S||^2 = s^T K(gbar) s),

with A the layer's rest area. The moments depend on the rest state only, so they are
precomputed per triangle: in closed form when bbar = 0 (M_k = K(abar) (z1^(k+1) - z0^(k+1))
/ (k+1)), else by Gauss-Legendre quadrature in z with N_GAUSS points (the integrand is
rational in z with poles at z = 1/kappabar_i, |kappabar z| < 0.1 in practice: the
quadrature error ~ (kappabar h / 2)^(2 N_GAUSS) is far below round-off). The state enters
only through the polynomial w, so the energy, gradient and Hessian in z are exact.

The part in (D0, D1) is the familiar quadratic E [m0/8 ||A||^2 - m1/2 <A, B> + m2/2 ||B||^2]
(A = abar^-1 a - I, B = abar^-1 (b - bbar), m_k = (z1^(k+1) - z0^(k+1)) / (k+1); for a layer
centred on the surface E [h/8 ||A||^2 + h^3/24 ||B||^2]). Dropping the D2 terms (the metric
a - 2 z b, :func:`layer_quadratic`) is the thin-shell truncation: for an off-centre layer the
neglected coupling D1^T M3 D2 is O(kappa h) relative to the bending energy, so a bilayer's
curvature comes out O(kappa h) off (1.9 % at s = 1.35 for 0.35 mm plastic on 0.8 mm fabric,
E ratio 3200, kappa h ~ 0.02; tests/test_thick.py measures it against an independent
through-thickness integration). :func:`layer_form` keeps the exact metric.
Mapping to the seed: its Eq. 3.9 equals 1/2 of the truncated energy written with b_seed = 2 b
for layers [0, h1] and [-h2, 0]; the seed's stencil "(n_j - n_i).(v_j - v_i)" is b/2, so its
formula only has the stated meaning with b_seed = 4 x stencil. The narrow-strip tests
(tests/test_strip.py) check that this energy gives Timoshenko's bilayer curvature.

Per triangle the layers are kept as a sum of per-layer terms (:class:`QuadraticForm`):
the quadratic part 1/2 (z - zbar)^T Q (z - zbar) and, for exact-metric layers, the rows
R = [Q20, Q21, Q22] of Q9 that carry D2. Fabric bending in bare fabric is the bending block
alone, D = k_B: 1/2 k_B [nu tr(B)^2 + (1 - nu) tr(B^2)] (a bending law of the fabric, not a
through-thickness integral: no D2 term). The bare fabric's membrane energy is not quadratic;
it is a membrane model of shellfem.materials.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

#: The symmetric 2x2 basis matrices of the components (11, 12, 22).
SYM_BASIS = np.array([[[1.0, 0.0], [0.0, 0.0]], [[0.0, 1.0], [1.0, 0.0]], [[0.0, 0.0], [0.0, 1.0]]])

#: Gauss-Legendre points per layer for the moments of a curved rest state.
N_GAUSS = 8


def sym_to_mat(s: np.ndarray) -> np.ndarray:
    """(…, 3) components (11, 12, 22) -> (…, 2, 2) symmetric matrices."""
    return np.stack([np.stack([s[..., 0], s[..., 1]], -1), np.stack([s[..., 1], s[..., 2]], -1)], -2)


def third_form(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """c = b a^-1 b (…, 3) of forms a, b (…, 3) (1/mm^2 x mm^2 in the edge basis)."""
    c = sym_to_mat(b) @ np.linalg.solve(sym_to_mat(a), sym_to_mat(b))
    return np.stack([c[..., 0, 0], 0.5 * (c[..., 0, 1] + c[..., 1, 0]), c[..., 1, 1]], -1)


def rest_area(abar: np.ndarray) -> np.ndarray:
    """Area (mm^2) of a triangle whose edge-basis metric is abar (m, 3)."""
    return 0.5 * np.sqrt(abar[:, 0] * abar[:, 2] - abar[:, 1] ** 2)


def elastic_norm_matrix(abar: np.ndarray, nu) -> np.ndarray:
    """K (m, 3, 3) with ||abar^-1 S||^2 = s^T K s for S with components s = (11, 12, 22)."""
    ainv = np.linalg.inv(sym_to_mat(abar))
    M = np.einsum("mij,kjl->mkil", ainv, SYM_BASIS)          # abar^-1 B_k
    t = np.einsum("mkii->mk", M)
    P = np.einsum("mjab,mkba->mjk", M, M)
    nu = np.broadcast_to(np.asarray(nu, float), (len(abar),))
    return (nu / (1 - nu ** 2))[:, None, None] * t[:, :, None] * t[:, None, :] + P / (1 + nu)[:, None, None]


def _moment_density(abar, bbar, cbar, nu, z):
    """z^k K(gbar(z)) mu(z) (m, 5, 3, 3), k = 0..4, at heights z (m,) (mm)."""
    gbar = abar - 2 * z[:, None] * bbar + (z * z)[:, None] * cbar
    S = np.linalg.solve(sym_to_mat(abar), sym_to_mat(bbar))          # rest shape operator
    mu = 1 - z * (S[:, 0, 0] + S[:, 1, 1]) + z * z * np.linalg.det(S)
    K = elastic_norm_matrix(gbar, nu) * mu[:, None, None]
    return (z[:, None] ** np.arange(5))[:, :, None, None] * K[:, None]


def layer_moments(abar, bbar, nu, z0, z1):
    """M_k = int_z0^z1 z^k K(gbar(z)) mu(z) dz (m, 5, 3, 3), k = 0..4 (mm^(k+1) x the elastic
    norm's units): closed form for flat rest states, Gauss-Legendre (N_GAUSS points) else."""
    m = len(abar)
    z0, z1 = (np.broadcast_to(np.asarray(v, float), (m,)) for v in (z0, z1))
    nu = np.broadcast_to(np.asarray(nu, float), (m,))
    k = np.arange(5)
    mk = (z1[:, None] ** (k + 1) - z0[:, None] ** (k + 1)) / (k + 1)
    M = mk[:, :, None, None] * elastic_norm_matrix(abar, nu)[:, None]
    curved = np.flatnonzero(np.any(bbar != 0, axis=1))
    if len(curved):
        ab, bb = abar[curved], bbar[curved]
        cb = third_form(ab, bb)
        xs, ws = np.polynomial.legendre.leggauss(N_GAUSS)
        lo, hi = z0[curved], z1[curved]
        Mc = np.zeros((len(curved), 5, 3, 3))
        for x, w in zip(xs, ws):                    # N_GAUSS vectorised evaluations over the faces
            Mc += (0.5 * w * (hi - lo))[:, None, None, None] * _moment_density(
                ab, bb, cb, nu[curved], 0.5 * (hi + lo) + 0.5 * (hi - lo) * x)
        M[curved] = Mc
    return M


def layer_moments_derivative(abar, bbar, nu, z0, z1, dz0, dz1):
    """dM_k/dp (m, 5, 3, 3) when the bounds move at rates dz0/dp, dz1/dp (fundamental theorem
    of calculus: the integrand at the bounds; exact, also for curved rest states)."""
    m = len(abar)
    z0, z1, dz0, dz1 = (np.broadcast_to(np.asarray(v, float), (m,)) for v in (z0, z1, dz0, dz1))
    nu = np.broadcast_to(np.asarray(nu, float), (m,))
    cbar = third_form(abar, bbar)
    return (_moment_density(abar, bbar, cbar, nu, z1) * dz1[:, None, None, None]
            - _moment_density(abar, bbar, cbar, nu, z0) * dz0[:, None, None, None])


def _form_from_moments(abar, bbar, E, M, area):
    """(Q (m,6,6), zbar (m,6), R (m,3,9), cbar (m,3)) of Q9 = E A/4 [[M0, -2M1, M2], [-2M1, 4M2,
    -2M3], [M2, -2M3, M4]]: Q its (D0, D1) block, R its D2 rows."""
    m = len(abar)
    A = rest_area(abar) if area is None else np.broadcast_to(np.asarray(area, float), (m,))
    w = (0.25 * A * np.broadcast_to(np.asarray(E, float), (m,)))[:, None, None]
    M0, M1, M2, M3, M4 = (w * M[:, k] for k in range(5))
    Q = np.zeros((m, 6, 6))
    Q[:, :3, :3] = M0
    Q[:, :3, 3:] = Q[:, 3:, :3] = -2 * M1
    Q[:, 3:, 3:] = 4 * M2
    R = np.concatenate([M2, -2 * M3, M4], 2)
    return Q, np.concatenate([abar, bbar], 1), R, third_form(abar, bbar)


def layer_form(abar, bbar, E, nu, z0, z1, area=None, exact_metric: bool = True):
    """One layer's term (Q, zbar, R, cbar, zspan) for QuadraticForm.add: the exact Kirchhoff-Love
    metric (module docstring), zspan (m, 2) = (z0, z1) its admissible-set bounds; exact_metric=False
    gives the truncated metric a - 2 z b (:func:`layer_quadratic`, R = cbar = zspan = None). abar, bbar (m, 3); E MPa; z0, z1 mm about the
    mesh surface; area: rest area (mm^2, default that of abar)."""
    if not exact_metric:
        return layer_quadratic(abar, bbar, E, nu, z0, z1, area) + (None, None, None)
    m = len(abar)
    zspan = np.stack([np.broadcast_to(np.asarray(z0, float), (m,)), np.broadcast_to(np.asarray(z1, float), (m,))], 1)
    return _form_from_moments(abar, bbar, E, layer_moments(abar, bbar, nu, z0, z1), area) + (zspan,)


def layer_form_derivative(abar, bbar, E, nu, z0, z1, dz0, dz1, area=None, exact_metric: bool = True):
    """dW/dp of one layer as a term (dQ, zbar, dR, cbar, None) for QuadraticForm.add, when its bounds
    move with a parameter p at rates dz0/dp, dz1/dp (mm per unit of p; a front plastic layer
    [hf/2, hf/2 + t] has dz0/dt = 0, dz1/dt = 1). Q9 is linear in the moments and w does not
    depend on p, so dW/dp = 1/2 w^T dQ9/dp w exactly."""
    if not exact_metric:
        return layer_quadratic_derivative(abar, bbar, E, nu, z0, z1, dz0, dz1, area) + (None, None, None)
    return _form_from_moments(abar, bbar, E, layer_moments_derivative(abar, bbar, nu, z0, z1, dz0, dz1),
                              area) + (None,)


def layer_quadratic(abar, bbar, E, nu, z0, z1, area=None):
    """Truncated metric a - 2 z b: Q (m,6,6), rest state zbar (m,6) of one layer with
    W = 1/2 (z - zbar)^T Q (z - zbar) (norm with abar, no volume factor). The thin-shell
    approximation of :func:`layer_form`, off by O(kappa h) for off-centre layers."""
    m = len(abar)
    E, z0, z1 = (np.broadcast_to(np.asarray(v, float), (m,)) for v in (E, z0, z1))
    m0, m1, m2 = z1 - z0, (z1 ** 2 - z0 ** 2) / 2, (z1 ** 3 - z0 ** 3) / 3
    return _moment_quadratic(abar, bbar, E, nu, m0, m1, m2, area)


def layer_quadratic_derivative(abar, bbar, E, nu, z0, z1, dz0, dz1, area=None):
    """dQ/dp (m,6,6) and zbar (m,6) of the truncated layer (:func:`layer_quadratic`) whose
    bounds move with a parameter p at rates dz0/dp, dz1/dp: Q is linear in the moments
    m_k = (z1^(k+1) - z0^(k+1)) / (k+1), so dQ/dp is the same expression with
    dm_k = z1^k dz1 - z0^k dz0, and dW/dp = 1/2 (z - zbar)^T dQ/dp (z - zbar) exactly."""
    m = len(abar)
    E, z0, z1, dz0, dz1 = (np.broadcast_to(np.asarray(v, float), (m,)) for v in (E, z0, z1, dz0, dz1))
    dm0, dm1, dm2 = dz1 - dz0, z1 * dz1 - z0 * dz0, z1 ** 2 * dz1 - z0 ** 2 * dz0
    return _moment_quadratic(abar, bbar, E, nu, dm0, dm1, dm2, area)


def _moment_quadratic(abar, bbar, E, nu, m0, m1, m2, area):
    """Q (m,6,6) = E A [[m0/4 K, -m1/2 K], [-m1/2 K, m2 K]] and zbar = (abar, bbar)."""
    m = len(abar)
    K = elastic_norm_matrix(abar, nu)
    A = rest_area(abar) if area is None else area
    w = (A * E)[:, None, None]
    Q = np.zeros((m, 6, 6))
    Q[:, :3, :3] = w * (m0 / 4)[:, None, None] * K
    Q[:, :3, 3:] = Q[:, 3:, :3] = -w * (m1 / 2)[:, None, None] * K
    Q[:, 3:, 3:] = w * m2[:, None, None] * K
    return Q, np.concatenate([abar, bbar], 1)


def bending_quadratic(abar, D, nu, area=None):
    """Q (m,6,6) of the pure bending energy 1/2 D [nu tr(B)^2 + (1-nu) tr(B^2)], bbar = 0."""
    m = len(abar)
    K = elastic_norm_matrix(abar, nu)
    A = rest_area(abar) if area is None else area
    nu = np.broadcast_to(np.asarray(nu, float), (m,))
    Q = np.zeros((m, 6, 6))
    Q[:, 3:, 3:] = (A * np.broadcast_to(D, (m,)) * (1 - nu ** 2))[:, None, None] * K
    return Q, np.concatenate([abar, np.zeros((m, 3))], 1)


_CHUNK = 512   # triangles per parallel task: scratch arrays are allocated once per chunk


@njit(cache=True)
def layer_scratch():
    """Scratch arrays of :func:`layer_terms` (allocate once per chunk of triangles, not per
    triangle: small allocations dominate the cost of the third-form terms otherwise)."""
    return (np.empty(6), np.empty(3), np.empty(3), np.empty(3), np.empty((3, 6)), np.empty((3, 9)),
            np.empty((3, 6)), np.empty((3, 6, 6)), np.empty(6), np.empty(6), np.empty((6, 6)))


#: The third-form terms are weighted by phi(rho), rho = zmax^2 (k1^2 + k2^2) with zmax the
#: largest |z| of a triangle's layers: phi = 1 for rho <= RHO_EXACT (every fibre within
#: |z k_i| <= 0.5 of the surface: the exact energy), a C2 quintic step down to 0 at
#: RHO_TRUNCATED (|z k_i| <= 0.9 still: no focal point inside any layer), the truncated
#: metric's quadratic energy beyond.
RHO_EXACT = 0.25
RHO_TRUNCATED = 0.81
#: Beyond RHO_TRUNCATED a printed triangle also carries the fold stop kappa x^3,
#: x = (rho - RHO_TRUNCATED) / (RHO_FOLDED - RHO_TRUNCATED), kappa = sum over its layers of
#: abar^T Q_aa abar = E A t / (2 (1 - nu)) (its membrane energy scale, N mm): the layers'
#: St.Venant-Kirchhoff energy stops growing as a fibre is compressed towards zero length (and
#: the fade removes the third-form stiffness), so without it a triangle past the fade bends on
#: at almost no cost (a 50 x 35 mm sheet of stars_tube's stars creased single edge triangles to
#: |k z| = 119 on a fine mesh). Real layers stiffen sharply there; the stop holds such a
#: triangle near |k z| = 0.9 (x of a few per cent) and makes RHO_FOLDED (|k z| = 1, a fibre at zero
#: length) unreachable but by forces of the order of the layers' membrane stiffness.
RHO_FOLDED = 1.0


@njit(cache=True, inline="always")
def curvature_square(z, order, ds, Hs):
    """s = tr((a^-1 b)^2) = k1^2 + k2^2 (1/mm^2) of one state z = (a, b) (6,), its gradient ds
    (6,) (order >= 1) and Hessian Hs (6, 6) (order 2), written into the given arrays.
    s = F / det(a)^2 with F = n^2 - 2 det(a) det(b), n = tr(adj(a) b)."""
    a0, a1, a2, b0, b1, b2 = z[0], z[1], z[2], z[3], z[4], z[5]
    da = a0 * a2 - a1 * a1
    db = b0 * b2 - b1 * b1
    n = a2 * b0 - 2.0 * a1 * b1 + a0 * b2
    F = n * n - 2.0 * da * db
    u = 1.0 / da
    s = F * u * u
    if order == 0:
        return s
    dn = (b2, -2.0 * b1, b0, a2, -2.0 * a1, a0)
    dda = (a2, -2.0 * a1, a0, 0.0, 0.0, 0.0)
    ddb = (0.0, 0.0, 0.0, b2, -2.0 * b1, b0)
    u2 = u * u
    for i in range(6):
        # ds = u^2 dF + 2 F u du,  dF = 2 n dn - 2 (db dda + da ddb),  du = -u^2 dda
        ds[i] = u2 * (2.0 * n * dn[i] - 2.0 * (db * dda[i] + da * ddb[i])) - 2.0 * F * u2 * u * dda[i]
    if order == 1:
        return s
    # second derivatives of n, det a, det b: nonzero pairs only
    for i in range(6):
        for j in range(6):
            Hs[i, j] = 0.0
    for i in range(6):
        dFi = 2.0 * n * dn[i] - 2.0 * (db * dda[i] + da * ddb[i])
        for j in range(i, 6):
            dFj = 2.0 * n * dn[j] - 2.0 * (db * dda[j] + da * ddb[j])
            hF = 2.0 * dn[i] * dn[j] - 2.0 * (ddb[i] * dda[j] + dda[i] * ddb[j])
            # Hs = u^2 HF + 2 u (dF du^T + du dF^T) + 2 F (du du^T + u Hu),
            # du = -u^2 dda, Hu = 2 u^3 dda dda^T - u^2 Hda
            Hs[i, j] = (u2 * hF - 2.0 * u2 * u * (dFi * dda[j] + dda[i] * dFj)
                        + 6.0 * F * u2 * u2 * dda[i] * dda[j])
    # the constant second derivatives: n (a0 b2, a1 b1, a2 b0), det a (a0 a2, a1 a1), det b (b0 b2, b1 b1)
    pairs_n = ((0, 5, 1.0), (1, 4, -2.0), (2, 3, 1.0))
    for i, j, v in pairs_n:
        Hs[i, j] += u2 * 2.0 * n * v
    for i, j, v in ((0, 2, 1.0), (1, 1, -2.0)):
        Hs[i, j] += u2 * (-2.0 * db * v) - 2.0 * F * u2 * u * v
    for i, j, v in ((3, 5, 1.0), (4, 4, -2.0)):
        Hs[i, j] += u2 * (-2.0 * da * v)
    for i in range(6):
        for j in range(i + 1, 6):
            Hs[j, i] = Hs[i, j]
    return s


@njit(cache=True, inline="always")
def third_form_derivatives(z, order, c, Jc, Hc):
    """c = b a^-1 b (3,) of one state z = (a, b) (6,), its Jacobian Jc (3, 6) (order >= 1) and
    Hessians Hc (3, 6, 6) (order 2), written into the given arrays. c = N / det(a) with
    N = b adj(a) b: linear in a, quadratic in b, written out component by component."""
    a0, a1, a2, b0, b1, b2 = z[0], z[1], z[2], z[3], z[4], z[5]
    u = 1.0 / (a0 * a2 - a1 * a1)
    N0 = a2 * b0 * b0 - 2.0 * a1 * b0 * b1 + a0 * b1 * b1
    N1 = a2 * b0 * b1 - a1 * (b0 * b2 + b1 * b1) + a0 * b1 * b2
    N2 = a2 * b1 * b1 - 2.0 * a1 * b1 * b2 + a0 * b2 * b2
    c[0], c[1], c[2] = N0 * u, N1 * u, N2 * u
    if order == 0:
        return
    # dN/dz (rows k, columns a0 a1 a2 b0 b1 b2)
    Jc[0, 0], Jc[0, 1], Jc[0, 2] = b1 * b1, -2.0 * b0 * b1, b0 * b0
    Jc[0, 3], Jc[0, 4], Jc[0, 5] = 2.0 * (a2 * b0 - a1 * b1), 2.0 * (a0 * b1 - a1 * b0), 0.0
    Jc[1, 0], Jc[1, 1], Jc[1, 2] = b1 * b2, -(b0 * b2 + b1 * b1), b0 * b1
    Jc[1, 3], Jc[1, 4], Jc[1, 5] = a2 * b1 - a1 * b2, a2 * b0 - 2.0 * a1 * b1 + a0 * b2, a0 * b1 - a1 * b0
    Jc[2, 0], Jc[2, 1], Jc[2, 2] = b2 * b2, -2.0 * b1 * b2, b1 * b1
    Jc[2, 3], Jc[2, 4], Jc[2, 5] = 0.0, 2.0 * (a2 * b1 - a1 * b2), 2.0 * (a0 * b2 - a1 * b1)
    # du/da = -u^2 ddet/da, ddet/da = (a2, -2 a1, a0); du/db = 0
    d0, d1, d2 = a2, -2.0 * a1, a0
    u2 = u * u
    du0, du1, du2 = -u2 * d0, -u2 * d1, -u2 * d2
    N = (N0, N1, N2)
    if order == 2:
        for k in range(3):
            for i in range(6):
                for j in range(6):
                    Hc[k, i, j] = 0.0
        # d2N: a-b blocks and b-b blocks (the a-a block is zero), times u
        Hc[0, 0, 4] = 2.0 * b1
        Hc[0, 1, 3], Hc[0, 1, 4] = -2.0 * b1, -2.0 * b0
        Hc[0, 2, 3] = 2.0 * b0
        Hc[0, 3, 3], Hc[0, 3, 4], Hc[0, 4, 4] = 2.0 * a2, -2.0 * a1, 2.0 * a0
        Hc[1, 0, 4], Hc[1, 0, 5] = b2, b1
        Hc[1, 1, 3], Hc[1, 1, 4], Hc[1, 1, 5] = -b2, -2.0 * b1, -b0
        Hc[1, 2, 3], Hc[1, 2, 4] = b1, b0
        Hc[1, 3, 4], Hc[1, 3, 5], Hc[1, 4, 4], Hc[1, 4, 5] = a2, -a1, -2.0 * a1, a0
        Hc[2, 0, 5] = 2.0 * b2
        Hc[2, 1, 4], Hc[2, 1, 5] = -2.0 * b2, -2.0 * b1
        Hc[2, 2, 4] = 2.0 * b1
        Hc[2, 4, 4], Hc[2, 4, 5], Hc[2, 5, 5] = 2.0 * a2, -2.0 * a1, 2.0 * a0
        u3 = u2 * u
        dd = (d0, d1, d2)
        du = (du0, du1, du2)
        for k in range(3):       # Hc = u d2N + dN (x) du + du (x) dN + N d2u (upper triangle, then mirrored)
            for i in range(6):
                for j in range(i, 6):
                    v = Hc[k, i, j] * u
                    if i < 3:
                        v += du[i] * Jc[k, j]
                    if j < 3:
                        v += Jc[k, i] * du[j] + N[k] * 2.0 * u3 * dd[i] * dd[j]
                    Hc[k, i, j] = v
            Hc[k, 0, 2] -= N[k] * u2          # d2det/da0 da2 = 1, d2det/da1^2 = -2
            Hc[k, 1, 1] += 2.0 * N[k] * u2
            for i in range(6):
                for j in range(i + 1, 6):
                    Hc[k, j, i] = Hc[k, i, j]
    # Jc = dN u + N du
    for k in range(3):
        for i in range(6):
            Jc[k, i] *= u
        Jc[k, 0] += N[k] * du0
        Jc[k, 1] += N[k] * du1
        Jc[k, 2] += N[k] * du2


@njit(cache=True, inline="always")
def _fold_stop(z, t0, t1, Qs, zbars, zm2, rho, order, Wz, Z, ds, Hs):
    """The fold stop kappa x^3 of one triangle past the fade (RHO_FOLDED), N mm; adds its gradient
    to Wz and its Hessian to Z (6, 6) like layer_terms. ds, Hs: scratch for the derivatives of
    s = rho / zm2."""
    kappa = 0.0
    for t in range(t0, t1):
        for k in range(3):
            for l in range(3):
                kappa += zbars[t, k] * Qs[t, k, l] * zbars[t, l]
    width = RHO_FOLDED - RHO_TRUNCATED
    x = (rho - RHO_TRUNCATED) / width
    w = kappa * x * x * x
    if order == 0:
        return w
    curvature_square(z, order, ds, Hs)
    b1 = 3.0 * kappa * x * x * zm2 / width          # dW/ds
    for i in range(6):
        Wz[i] += b1 * ds[i]
    if order == 2:
        b2 = 6.0 * kappa * x * zm2 * zm2 / (width * width)   # d2W/ds2
        for i in range(6):
            for j in range(6):
                Z[i, j] += b2 * ds[i] * ds[j] + b1 * Hs[i, j]
    return w


@njit(cache=True, inline="always")
def layer_terms(z, t0, t1, Qs, zbars, Rs, cbars, thick, zlo, zhi, order, Wz, Z, work):
    """Energy of one triangle's layer terms t0..t1-1 at z (6,); adds the gradient to Wz (6,)
    (order >= 1) and, for exact-metric terms, the state-dependent part of the Hessian to Z
    (6, 6) (order 2; Z holds the constant quadratic part on entry). work: :func:`layer_scratch`.
    The third-form (exact-metric) terms carry the weight phi(rho), rho = zmax^2 (k1^2 + k2^2),
    zmax = max(|zlo|, |zhi|) (:data:`RHO_EXACT`, :data:`RHO_TRUNCATED`): 1 wherever every fibre
    of the layers is within |z k_i| <= 0.5, a C2 step to 0 before any fibre reaches a focal
    point (1 - z k_i = 0), where the Kirchhoff body folds and the third-form terms have spurious
    wells (a fibre at z k = 2 has its length back). Beyond, the truncated metric's quadratic
    (coercive) energy is kept, so the interpolated meshes' sharp starting kinks stay admissible,
    and the energy stays twice differentiable throughout (the equilibria of the shipped laws,
    |k z| <= 0.25, sit where phi = 1). Each term is evaluated from its own differences
    w = (z - zbar, c - cbar), never expanded (no cancellation)."""
    w = 0.0
    d, c, r, D2, Jc, Rsum, RJ, Hc, g3, ds, Hs = work
    for t in range(t0, t1):                       # quadratic part, layer by layer
        for k in range(6):
            d[k] = z[k] - zbars[t, k]
        for k in range(6):
            qd = 0.0
            for l in range(6):
                qd += Qs[t, k, l] * d[l]
            w += 0.5 * d[k] * qd
            if order >= 1:
                Wz[k] += qd
    if not thick:
        return w
    zm2 = max(zlo * zlo, zhi * zhi)
    rho = zm2 * curvature_square(z, 0, ds, Hs)
    if not rho < RHO_TRUNCATED:                   # (also NaN: a degenerate metric)
        if rho > RHO_TRUNCATED:
            w += _fold_stop(z, t0, t1, Qs, zbars, zm2, rho, order, Wz, Z, ds, Hs)
        return w
    phi, phi1, phi2 = 1.0, 0.0, 0.0               # phi and its derivatives in rho
    if rho > RHO_EXACT:
        width = RHO_TRUNCATED - RHO_EXACT
        x = (rho - RHO_EXACT) / width
        phi = 1.0 - x * x * x * (10.0 + x * (-15.0 + 6.0 * x))
        phi1 = -30.0 * x * x * (1.0 - x) * (1.0 - x) / width
        phi2 = -60.0 * x * (1.0 - x) * (1.0 - 2.0 * x) / (width * width)
        if order >= 1:
            curvature_square(z, order, ds, Hs)
    third_form_derivatives(z, order, c, Jc, Hc)
    for k in range(3):
        r[k] = 0.0
        for l in range(9):
            Rsum[k, l] = 0.0
    for l in range(6):
        g3[l] = 0.0
    w3 = 0.0
    for t in range(t0, t1):
        for k in range(6):
            d[k] = z[k] - zbars[t, k]
        for k in range(3):
            D2[k] = c[k] - cbars[t, k]
        for k in range(3):
            p = 0.0
            for l in range(6):
                p += Rs[t, k, l] * d[l]
            q = 0.0
            for l in range(3):
                q += Rs[t, k, 6 + l] * D2[l]
            w3 += D2[k] * (p + 0.5 * q)
            r[k] += p + q
        if order >= 1:
            for l in range(6):
                g3[l] += Rs[t, 0, l] * D2[0] + Rs[t, 1, l] * D2[1] + Rs[t, 2, l] * D2[2]
        if order == 2:
            for k in range(3):
                for l in range(9):
                    Rsum[k, l] += Rs[t, k, l]
    w += phi * w3
    if order == 0:
        return w
    for l in range(6):
        g3[l] += Jc[0, l] * r[0] + Jc[1, l] * r[1] + Jc[2, l] * r[2]
    b1 = phi1 * zm2                                # d phi / dz = b1 ds (ds computed where phi < 1)
    for l in range(6):
        Wz[l] += phi * g3[l]
        if phi < 1.0:
            Wz[l] += w3 * b1 * ds[l]
    if order == 1:
        return w
    # phi (Jc^T R6 + R6^T Jc + Jc^T R22 Jc + sum_k r_k Hc_k) + the terms of phi's derivatives
    for k in range(3):
        for l in range(6):
            RJ[k, l] = Rsum[k, 6] * Jc[0, l] + Rsum[k, 7] * Jc[1, l] + Rsum[k, 8] * Jc[2, l]
    b2 = phi2 * zm2 * zm2
    for i in range(6):
        for j in range(i, 6):
            h = 0.0
            for k in range(3):
                h += (Jc[k, i] * (Rsum[k, j] + 0.5 * RJ[k, j]) + (Rsum[k, i] + 0.5 * RJ[k, i]) * Jc[k, j]
                      + r[k] * Hc[k, i, j])
            h *= phi
            if phi < 1.0:
                h += (b1 * (ds[i] * g3[j] + g3[i] * ds[j])
                      + w3 * (b2 * ds[i] * ds[j] + b1 * Hs[i, j]))
            Z[i, j] += h
            if j > i:
                Z[j, i] += h
    return w


@njit(cache=True, parallel=True)
def _evaluate_kernel(z, faces, ptr, Qs, zbars, Rs, cbars, thick, zspan, Qtot, order, W, g, H):
    n = faces.shape[0]
    for chunk in prange((n + _CHUNK - 1) // _CHUNK):
        Wz = np.empty(6)
        Z = np.empty((6, 6))
        work = layer_scratch()
        for i in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            f = faces[i]
            Wz[:] = 0.0
            if order == 2:
                for k in range(6):
                    for l in range(6):
                        Z[k, l] = Qtot[f, k, l]
            W[i] = layer_terms(z[f], ptr[f], ptr[f + 1], Qs, zbars, Rs, cbars, thick[f], zspan[f, 0], zspan[f, 1],
                               order, Wz, Z, work)
            if order >= 1:
                for k in range(6):
                    g[i, k] = Wz[k]
            if order == 2:
                for k in range(6):
                    for l in range(6):
                        H[i, k, l] = Z[k, l]


class QuadraticForm:
    """Sum of layer terms per triangle: W(z) = sum_l 1/2 (z - zbar_l)^T Q_l (z - zbar_l)
    [+ D2_l^T R_l[:, :6] (z - zbar_l) + 1/2 D2_l^T R_l[:, 6:] D2_l for exact-metric layers,
    D2_l = c(z) - cbar_l, c = b a^-1 b]: quadratic in z = (a, b) apart from the third
    fundamental form (module docstring).

    Kept as a sum of per-layer terms, each evaluated from its own differences: expanding it
    into 1/2 z^T Q z - q^T z + c cancels catastrophically (terms ~ E h ~ 10^3 N/mm against
    equilibrium energies many orders smaller) and would stall Newton at round-off."""

    def __init__(self, m: int):
        self.m = m
        self.Q = np.zeros((m, 6, 6))   # Hessian of the quadratic part (constant)
        self.thick = np.zeros(m, bool)  # triangles with exact-metric (non-quadratic) terms
        self.zspan = np.zeros((m, 2))   # the union of their layers' [z0, z1] (mm): admissible |k z| < 1
        self._terms = []               # (index array, Q_l, zbar_l, R_l, cbar_l, zspan_l; None if quadratic)
        self._packed = None

    def add(self, Q, zbar, R=None, cbar=None, zspan=None, *, mask=None):
        """Add one term per triangle (where mask): Q (m,6,6), zbar (m,6) and, for an
        exact-metric layer, R (m,3,9), cbar (m,3) and optionally zspan (m,2), the layer's
        [z0, z1], whose union per triangle bounds the admissible curvatures
        (shellfem.layers.layer_form)."""
        idx = np.arange(self.m) if mask is None else np.flatnonzero(mask)
        if len(idx) == 0:
            return
        self.Q[idx] += Q[idx]
        if R is not None:
            self.thick[idx] = True
            R, cbar = R[idx], cbar[idx]
        if zspan is not None:
            zspan = zspan[idx]
            self.zspan[idx, 0] = np.minimum(self.zspan[idx, 0], zspan[:, 0])
            self.zspan[idx, 1] = np.maximum(self.zspan[idx, 1], zspan[:, 1])
        self._terms.append((idx, Q[idx], zbar[idx], R, cbar, zspan))
        self._packed = None

    def add_form(self, other: "QuadraticForm", mask=None):
        """Add the terms of another form over the same triangles (where mask)."""
        keep = np.ones(self.m, bool) if mask is None else np.asarray(mask, bool)
        for idx, *arrays in other._terms:
            sel = keep[idx]
            if not sel.any():
                continue
            full = np.zeros(self.m, bool)
            full[idx[sel]] = True
            self.add(*(None if v is None else _expand(v[sel], idx[sel], self.m) for v in arrays), mask=full)

    def packed(self):
        """The terms grouped by triangle, in the order added: (ptr (m+1,), Q (K, 6, 6),
        zbar (K, 6), R (K, 3, 9), cbar (K, 3), thick (m,), zspan (m, 2)); triangle f's terms are
        ptr[f]:ptr[f+1], R = 0 for quadratic terms (for compiled kernels)."""
        if self._packed is None:
            if self._terms:
                idx = np.concatenate([t[0] for t in self._terms])
                order = np.argsort(idx, kind="stable")
                Q = np.ascontiguousarray(np.concatenate([t[1] for t in self._terms])[order])
                zbar = np.ascontiguousarray(np.concatenate([t[2] for t in self._terms])[order])
                R = np.ascontiguousarray(np.concatenate(
                    [np.zeros((len(t[0]), 3, 9)) if t[3] is None else t[3] for t in self._terms])[order])
                cbar = np.ascontiguousarray(np.concatenate(
                    [np.zeros((len(t[0]), 3)) if t[4] is None else t[4] for t in self._terms])[order])
                counts = np.bincount(idx, minlength=self.m)
            else:
                Q, zbar, counts = np.zeros((0, 6, 6)), np.zeros((0, 6)), np.zeros(self.m, np.int64)
                R, cbar = np.zeros((0, 3, 9)), np.zeros((0, 3))
            self._packed = (np.concatenate([[0], np.cumsum(counts)]).astype(np.int64), Q, zbar, R, cbar,
                            self.thick.astype(np.bool_), np.ascontiguousarray(self.zspan))
        return self._packed

    def evaluate(self, z, order: int = 2, faces=None):
        """W, dW/dz (·, 6), d2W/dz2 (·, 6, 6) (exact; None where not asked) at z (m, 6), for all
        triangles or for the triangles ``faces`` (an index array; rows in that order)."""
        ptr, Qs, zbars, Rs, cbars, thick, zspan = self.packed()
        faces = np.arange(self.m) if faces is None else np.asarray(faces, np.int64)
        n = len(faces)
        W = np.empty(n)
        g = np.empty((n if order >= 1 else 0, 6))
        H = np.empty((n if order >= 2 else 0, 6, 6))
        _evaluate_kernel(np.ascontiguousarray(z, dtype=float), faces, ptr, Qs, zbars, Rs, cbars, thick, zspan,
                         self.Q, order, W, g, H)
        return W, (g if order >= 1 else None), (H if order >= 2 else None)

    def minimiser(self, keep=None, tol: float = 1e-13, max_iterations: int = 50):
        """Per-triangle minimiser z* of W over the components ``keep`` (others held at 0):
        one linear solve for the quadratic part, then Newton with the exact Hessian on the
        exact-metric triangles (damped by halving if a step increases W beyond round-off),
        each triangle until its step is below tol of |z| (then the step is taken and the
        triangle is done: only the unfinished ones are evaluated again)."""
        keep = np.arange(6) if keep is None else np.asarray(keep)
        q = np.zeros((self.m, 6))
        for idx, Q, zbar, *_ in self._terms:
            q[idx] += (Q @ zbar[:, :, None])[:, :, 0]
        z = np.zeros((self.m, 6))
        z[:, keep] = np.linalg.solve(self.Q[:, keep][:, :, keep], q[:, keep, None])[..., 0]
        active = np.flatnonzero(self.thick)
        if not len(active):
            return z
        W, g, H = self.evaluate(z, faces=active)            # rows of the active triangles
        for _ in range(max_iterations):
            step = np.zeros((len(active), 6))
            step[:, keep] = -np.linalg.solve(H[:, keep][:, :, keep], g[:, keep, None])[..., 0]
            done = np.all(np.abs(step) <= tol * np.abs(z[active]).max(1, keepdims=True), axis=1)
            z[active[done]] += step[done]
            active, step, W = active[~done], step[~done], W[~done]
            if not len(active):
                break
            t = np.ones(len(active))
            zt = z.copy()
            for _ in range(30):
                zt[active] = z[active] + t[:, None] * step
                Wt = self.evaluate(zt, order=0, faces=active)[0]
                bad = ~(Wt <= W + 1e-14 * np.abs(W))
                if not bad.any():
                    break
                t = np.where(bad, 0.5 * t, t)
            z[active] += t[:, None] * step
            W, g, H = self.evaluate(z, faces=active)
        return z


def _expand(v, idx, m):
    """Rows v at triangles idx of an array over all m triangles (zeros elsewhere)."""
    out = np.zeros((m,) + v.shape[1:])
    out[idx] = v
    return out
