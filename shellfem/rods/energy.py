"""Discrete elastic rods collocated with the vertices of a sheet (seed Eq. 3.3, Fig. 3.3).

A rod network is a graph over the sheet's vertices (its edges are mesh edges, e.g. the
centre lines of the star arms). Its energy (N mm; x in mm) is the seed's Eq. 3.3:

    W = sum_edges  EA / 8 (|e|^2 - l^2)^2 / l^3                                  (stretching)
      + sum_stencils  w / (l_0 + l_1) [ B1 (k1 - k1_rest)^2 + B2 (k2 - k2_rest)^2
                                        + T (tau - tau_rest)^2 ]                (bending, twist)

with l the rest (printed) edge lengths, EA the axial stiffness (N), B1 = E I_1 the
bending stiffness about the width axis (normal bending; N mm^2), B2 = E I_2 about the
normal (in-plane bending), T the torsional stiffness (N mm^2; the seed's mu (I1 + I2) / 2).
(EA/8 (|e|^2 - l^2)^2 / l^3 = EA/2 (|e| - l)^2 / l to second order; the prefactor 1/(l0+l1)
is DER's 1/(2 x Voronoi length), so a uniform bend k of a rod of length L costs
B1 k^2 L / 2.)

Curvatures at a stencil (a, c, b), tangents t0 = unit(x_c - x_a), t1 = unit(x_b - x_c):

    kb = 2 t0 x t1 / (1 + t0 . t1)        (curvature binormal, |kb| = 2 tan(turning / 2))
    k1 = kb . (d2_0 + d2_1) / 2,   k2 = -kb . (d1_0 + d1_1) / 2     (Bergou et al. 2010)

and tau the twist: the signed angle about t1 from the parallel transport of d1_0 (along
the rotation taking t0 to t1, R = I + [k] + [k]^2 / (1 + t0.t1), k = t0 x t1) to d1_1.

Material frame: the fabric's surface normal (the formulation this module uses). DER
(Bergou et al. 2008) gives each edge a twist angle relative to a parallel-transported
reference frame. A rod collocated with a shell has no material freedom to twist relative
to the surface it is bonded to, so here d1 of each edge IS the surface normal there and
d2 = t x d1: the twist angle is not a degree of freedom, the frame (and with it k1, k2
and tau) is a function of the positions alone, and the energy needs no reference frame
updated between Newton iterations. tau is then the surface's geodesic torsion along the
rod, resisted with the rod's torsional stiffness. The edge normal is

    d1 = unit(e x (x_L - x_R))

with x_L, x_R the third vertices of the triangles left and right of the directed edge in
the printed plane (x_L or x_R is the edge's start point on a sheet boundary). e x (x_L -
x_R) is exactly normal to e, is +z in the flat printed state, and for a folded hinge lies
between the two triangles' normals (their bisector when the hinge is symmetric). A
bending stencil thus involves 7 points (a, c, b and the left/right points of its two
edges): 21 position DOFs, the width of the shell's face blocks, so the stencil blocks go
into the same BlockScatter as the shell's (shellfem.rods.coupled).

For standalone rods (tests, no surface) the frame source can instead be a fixed "up"
vector u per stencil: d1 = unit(e x (u x e)), the part of u normal to the edge (not
invariant under rotations that move u relative to the rod: for planar tests only).

Junctions (seed Fig. 3.3): at a vertex where d >= 2 rod edges meet, every pair of the
edges forms a bending/twist stencil with weight w = 1 / (d - 1): an ordinary interior rod
vertex (d = 2) has one stencil of weight 1, the centre of a three-armed star (d = 3) the
seed's three pairwise stencils of weight 1/2 (each arm split into two half-section copies,
each copy bonded to one copy of each other arm). The rest curvatures of every stencil are
its printed (flat) values plus the bilayer's normal rest curvature in k1 (see
:func:`build_network`), so a junction's in-plane angle is its rest state.

Offset (optional, ``offset`` in build_network; shellfem.rods.coupled with offset=True): the
rod's vertices are the fabric's mid-surface, where the fabric's membrane forces act; a printed
arm's neutral axis lies e above it (front plastic: e = (h1 + h2) / 2 along +d1). A beam whose
reference line is e below its neutral axis has the energy density EA/2 (eps - e kappa)^2 +
B1/2 kappa^2 (eps the reference line's strain, kappa the curvature about the width axis, B1
about the neutral axis): an axial force N carried at the reference line bends the rod with
the moment N e. The seed's collocation puts the rods IN the fabric (e = 0: Eq. 3.3 has no
such term) and carries the bilayer by the rest curvature of a fabric strip as wide as the
arm only. With the offset the stencil adds, over its Voronoi length (l0 + l1) / 2,

    w EA [ -e g (k1 - k1_rest) + e^2 (k1 - k1_rest)^2 / (l0 + l1) ],
    g = (l0 g0 + l1 g1) / (l0 + l1),   g_j = (|e_j|^2 / l_j^2 - 1) / 2,

the cross and square terms of EA/2 (g - e kappa)^2 (kappa = (k1 - k1_rest) / Voronoi
length) with g the length-weighted mean of the two edges' Green strains, the strain of the
stretching term above (EA/8 (|e|^2 - l^2)^2 / l^3 = EA l g^2 / 2). That choice keeps the energy
bounded below: by Jensen, (l0 + l1)/2 g^2 <= (l0 g0^2 + l1 g1^2) / 2, and the stencils' weights
at a vertex sum to at most 1 per edge end, so the edges' EA l g^2 / 2 cover every stencil's
EA (l0 + l1)/4 g^2 and the total is a sum of squares plus a positive remainder. (With the
engineering strain |e|/l - 1 instead, whose square the stretching term does not bound in
strong compression, a 30 x 21 mm star sheet found a collapse at -287 N mm.)

Derivatives: per stencil, the energy is a function of 12 inputs v = (e0, e1, s0, s1)
(edge vectors and frame source vectors), each LINEAR in the stencil's 21 coordinates,
v = G x_local with a constant G (12 x 21) per stencil; W_v and W_vv come exact from the
second-order forward differentiation of shellfem.rods.ad, and W_x = G^T W_v,
W_xx = G^T W_vv G. Vectorised over stencils (numpy, no loop over rods or vertices).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shellfem.rods import ad


def bend_measures(v: np.ndarray, frame: str = "surface", order: int = 2, lengths: bool = False):
    """(k1, k2, tau) of stencils from inputs v (k, 12) = (e0, e1, s0, s1) as Jets.

    frame "surface": d1_j = unit(e_j x s_j) (s_j = x_L - x_R); "up": s_j is the up vector
    u and d1_j = unit(e_j x (u x e_j)). order 0: plain arrays (values only, the same
    formulas: the line search's energy evaluations skip the derivatives). lengths: also
    |e0|, |e1| (the offset term's strains)."""
    J = ad.Jet.inputs(v) if order > 0 else [np.ascontiguousarray(v[:, i]) for i in range(v.shape[1])]
    e0, e1, s0, s1 = tuple(J[0:3]), tuple(J[3:6]), tuple(J[6:9]), tuple(J[9:12])
    t0, n_e0 = ad.unit(e0)
    t1, n_e1 = ad.unit(e1)
    if frame == "surface":
        n0, _ = ad.unit(ad.cross(e0, s0))
        n1, _ = ad.unit(ad.cross(e1, s1))
    elif frame == "up":
        n0, _ = ad.unit(ad.cross(e0, ad.cross(s0, e0)))
        n1, _ = ad.unit(ad.cross(e1, ad.cross(s1, e1)))
    else:
        raise ValueError(f"frame must be 'surface' or 'up', got {frame!r}")
    chi = ad.dot(t0, t1) + 1.0
    rchi = ad.recip(chi)
    kvec = ad.cross(t0, t1)
    kb = ad.scale(kvec, rchi * 2.0)
    m0, m1 = ad.cross(t0, n0), ad.cross(t1, n1)          # d2 = t x d1
    k1 = ad.dot(kb, ad.add(m0, m1)) * 0.5
    k2 = ad.dot(kb, ad.add(n0, n1)) * -0.5
    # parallel transport of n0 from t0 to t1: R n0 = n0 + k x n0 + k x (k x n0) / chi
    kn = ad.cross(kvec, n0)
    pn0 = ad.add(ad.add(n0, kn), ad.scale(ad.cross(kvec, kn), rchi))
    tau = ad.atan2(ad.dot(t1, ad.cross(pn0, n1)), ad.dot(pn0, n1))
    if lengths:
        return k1, k2, tau, n_e0, n_e1
    return k1, k2, tau


def rest_turning_curvature(k, l0, l1):
    """Integrated rest curvature |kb| of a stencil on a circle of curvature k (1/mm) with
    chords l0, l1 (mm): the turning angle is asin(k l0 / 2) + asin(k l1 / 2) and
    |kb| = 2 tan(turning / 2), so a polygon inscribed in the circle is exactly at rest."""
    k, l0, l1 = np.broadcast_arrays(*(np.asarray(a, float) for a in (k, l0, l1)))
    turn = np.arcsin(np.clip(k * l0 / 2, -1, 1)) + np.arcsin(np.clip(k * l1 / 2, -1, 1))
    return 2 * np.tan(turn / 2)


@dataclass
class RodNetwork:
    """Stencils and stiffnesses of a rod network over the vertices of a point set.

    edges (ne, 2), rest_length (ne,) mm, EA (ne,) N: stretching.
    points (nb, 7): vertex ids of each bending stencil (a, c, b, L0, R0, L1, R1; for the
    "up" frame the last four are c and unused); G (nb, 12, 21) the linear map from the
    stencil's 21 coordinates to v = (e0, e1, s0, s1); up (nb, 3) the up vectors ("up"
    frame, added to s as constants); weight (nb,) = w / (l0 + l1) (1/mm);
    B1, B2, T (nb,) N mm^2; rest (nb, 3) the rest (k1, k2, tau) (dimensionless).
    offset (nb,) mm or None: the height of the rods' neutral axis above their vertices along
    d1 (module docstring), with stencil_EA (nb,) N and stencil_length (nb, 2) = (l0, l1) mm.
    """
    n_vertices: int
    edges: np.ndarray
    rest_length: np.ndarray
    EA: np.ndarray
    points: np.ndarray
    G: np.ndarray
    up: np.ndarray
    weight: np.ndarray
    B1: np.ndarray
    B2: np.ndarray
    T: np.ndarray
    rest: np.ndarray
    frame: str = "surface"
    offset: np.ndarray | None = None
    stencil_EA: np.ndarray | None = None
    stencil_length: np.ndarray | None = None

    def _offset_energy(self, k1, n0, n1):
        """The offset's stencil terms (module docstring) of Jets or arrays k1, |e0|, |e1|."""
        l0, l1 = self.stencil_length[:, 0], self.stencil_length[:, 1]
        d = k1 - self.rest[:, 0]
        # g = (l0 g0 + l1 g1) / (l0 + l1), g_j = (|e_j|^2 / l_j^2 - 1) / 2
        g = (n0 * n0) * (0.5 / (l0 * (l0 + l1))) + (n1 * n1) * (0.5 / (l1 * (l0 + l1))) - 0.5
        a = -self.weight * (l0 + l1) * self.stencil_EA * self.offset          # the cross term's factor
        b = self.weight * self.stencil_EA * self.offset ** 2
        return (d * g) * a + (d * d) * b

    @property
    def stretch_dofs(self) -> np.ndarray:
        return (3 * self.edges[:, :, None] + np.arange(3)).reshape(-1, 6)

    @property
    def bend_dofs(self) -> np.ndarray:
        return (3 * self.points[:, :, None] + np.arange(3)).reshape(-1, 21)

    def stencil_inputs(self, x: np.ndarray) -> np.ndarray:
        """v (nb, 12) at positions x (n, 3)."""
        X = x[self.points].reshape(-1, 21)
        v = np.einsum("kij,kj->ki", self.G, X)
        if self.frame == "up":
            v[:, 6:9] += self.up
            v[:, 9:12] += self.up
        return v

    def measures(self, x: np.ndarray) -> np.ndarray:
        """(k1, k2, tau) (nb, 3) at positions x (n, 3)."""
        return np.stack(bend_measures(self.stencil_inputs(x), self.frame, order=0), 1)

    def evaluate(self, x: np.ndarray, order: int = 2):
        """(E, gradient over the 3n positions, stretch blocks (ne, 6, 6), bend blocks
        (nb, 21, 21)) at positions x (n, 3): N mm, N, N/mm; None where not asked."""
        x = np.asarray(x, float).reshape(-1, 3)
        # stretching, closed form: f = c (s - l^2)^2, s = |e|^2, c = EA / (8 l^3)
        p, q = self.edges[:, 0], self.edges[:, 1]
        e = x[q] - x[p]
        s = np.einsum("ij,ij->i", e, e)
        l2 = self.rest_length ** 2
        c = self.EA / (8 * self.rest_length ** 3)
        E = float(np.sum(c * (s - l2) ** 2))
        # bending and twist (and the offset's coupling)
        off = self.offset is not None
        k1, k2, tau, *lens = bend_measures(self.stencil_inputs(x), self.frame, order=order, lengths=off)
        if order == 0:
            for m, B, r in ((k1, self.B1, self.rest[:, 0]), (k2, self.B2, self.rest[:, 1]), (tau, self.T, self.rest[:, 2])):
                E += float(np.sum(B * self.weight * (m - r) ** 2))
            if off:
                E += float(np.sum(self._offset_energy(k1, *lens)))
            return E, None, None, None
        W = None
        for jet, B, r in ((k1, self.B1, self.rest[:, 0]), (k2, self.B2, self.rest[:, 1]), (tau, self.T, self.rest[:, 2])):
            d = (jet - r).square() * (B * self.weight)
            W = d if W is None else W + d
        if off:
            W = W + self._offset_energy(k1, *lens)
        if len(self.weight):
            E += float(W.v.sum())
        n = len(x)
        ge = 4 * c[:, None] * (s - l2)[:, None] * e                     # df/de
        grad = np.zeros(3 * n)
        g_s = np.concatenate([-ge, ge], 1)
        np.add.at(grad, self.stretch_dofs, g_s)
        if len(self.weight):
            gb = np.einsum("kij,ki->kj", self.G, W.g)
            np.add.at(grad, self.bend_dofs, gb)
        if order == 1:
            return E, grad, None, None
        He = (8 * c)[:, None, None] * e[:, :, None] * e[:, None, :] + (4 * c * (s - l2))[:, None, None] * np.eye(3)
        Hs = np.block([[He, -He], [-He, He]]) if len(He) else np.zeros((0, 6, 6))
        if len(self.weight):
            Hb = np.einsum("kia,kij,kjb->kab", self.G, ad.zero_hessian(W), self.G, optimize=True)
        else:
            Hb = np.zeros((0, 21, 21))
        return E, grad, Hs, Hb

    def energy(self, x) -> float:
        return self.evaluate(x, order=0)[0]

    def gradient(self, x) -> np.ndarray:
        return self.evaluate(x, order=1)[1]

    def hessian(self, x):
        """Sparse (3n, 3n) Hessian (for tests and small problems)."""
        import scipy.sparse as sp
        _, _, Hs, Hb = self.evaluate(x, order=2)
        rows, cols, vals = [], [], []
        for dofs, B in ((self.stretch_dofs, Hs), (self.bend_dofs, Hb)):
            d = dofs.shape[1]
            rows.append(np.repeat(dofs, d, axis=1).ravel())
            cols.append(np.tile(dofs, (1, d)).ravel())
            vals.append(B.ravel())
        n = 3 * self.n_vertices
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))


def _as_edge_array(v, ne):
    return np.broadcast_to(np.asarray(v, float), (ne,)).astype(float)


def build_network(points: np.ndarray, edges, *, EA, B1, B2, T, triangles=None, up=None,
                  normal_rest_curvature=0.0, offset=0.0) -> RodNetwork:
    """A rod network over the vertices ``points`` (printed positions (n, 2) or (n, 3), mm).

    edges: (ne, 2) vertex ids, the rods' edges (mesh edges when ``triangles`` is given).
    EA (N), B1, B2, T (N mm^2): per edge (arrays (ne,)) or scalars; a stencil takes the
    mean of its two edges'. triangles (m, 3): the sheet the rods are collocated with
    (frame from its surface normal); without it, ``up`` (3,) gives the "up" frame.
    normal_rest_curvature: rest curvature k (1/mm) of the rods about their width axis
    (> 0: centre of curvature on the +normal side), per edge or scalar; a stencil's rest
    k1 is rest_turning_curvature(mean k, l0, l1) added to its printed k1 (0 on a flat
    print). The rest k2 and tau are the printed state's (its in-plane turning, 0 twist).
    offset: the height (mm, along the frame normal d1) of the rods' neutral axis above their
    vertices, per edge or scalar (a stencil takes the mean); 0 everywhere (the default, the
    seed's Eq. 3.3) adds no term.
    """
    P = np.asarray(points, float)
    n = len(P)
    X = np.concatenate([P, np.zeros((n, 1))], 1) if P.shape[1] == 2 else P.copy()
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    ne = len(edges)
    EA, B1, B2, T = (_as_edge_array(v, ne) for v in (EA, B1, B2, T))
    kn = _as_edge_array(normal_rest_curvature, ne)
    off = _as_edge_array(offset, ne)
    rest_length = np.linalg.norm(X[edges[:, 1]] - X[edges[:, 0]], axis=1)
    if np.any(rest_length <= 0):
        raise ValueError("rod edges of zero length")
    # stencils: every pair of edges at a vertex of degree d >= 2, weight 1 / (d - 1)
    inc_v = np.concatenate([edges[:, 0], edges[:, 1]])
    inc_e = np.concatenate([np.arange(ne), np.arange(ne)])
    order = np.argsort(inc_v, kind="stable")
    inc_v, inc_e = inc_v[order], inc_e[order]
    verts, start, deg = np.unique(inc_v, return_index=True, return_counts=True)
    pairs = []
    for d in np.unique(deg[deg >= 2]):                 # loop over degrees, not vertices
        sel = np.flatnonzero(deg == d)
        ii, jj = np.triu_indices(d, 1)
        ea = inc_e[start[sel][:, None] + ii[None, :]].ravel()
        eb = inc_e[start[sel][:, None] + jj[None, :]].ravel()
        cv = np.repeat(verts[sel], len(ii))
        pairs.append(np.stack([ea, eb, cv, np.full(len(cv), 1.0 / (d - 1))], 1))
    pairs = np.concatenate(pairs) if pairs else np.zeros((0, 4))
    ea, eb, cv, w = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64), pairs[:, 2].astype(np.int64), pairs[:, 3]
    # stencils follow the stored edge direction where they can (a -> c -> b)
    swap = (edges[ea, 0] == cv) & (edges[eb, 1] == cv)
    ea, eb = np.where(swap, eb, ea), np.where(swap, ea, eb)
    other = lambda e, v: np.where(edges[e, 0] == v, edges[e, 1], edges[e, 0])   # noqa: E731
    a, b = other(ea, cv), other(eb, cv)
    nb = len(cv)
    G = np.zeros((nb, 12, 21))
    I3 = np.eye(3)
    # e0 = x_c - x_a (slots 1, 0), e1 = x_b - x_c (slots 2, 1)
    for row, plus, minus in ((0, 1, 0), (3, 2, 1)):
        G[:, row:row + 3, 3 * plus:3 * plus + 3] += I3
        G[:, row:row + 3, 3 * minus:3 * minus + 3] -= I3
    if triangles is not None:
        frame = "surface"
        L0, R0 = _sides(P, triangles, a, cv)
        L1, R1 = _sides(P, triangles, cv, b)
        pts = np.stack([a, cv, b, L0, R0, L1, R1], 1)
        # s0 = x_L0 - x_R0 (slots 3, 4), s1 = x_L1 - x_R1 (slots 5, 6)
        for row, plus, minus in ((6, 3, 4), (9, 5, 6)):
            G[:, row:row + 3, 3 * plus:3 * plus + 3] += I3
            G[:, row:row + 3, 3 * minus:3 * minus + 3] -= I3
        upv = np.zeros((nb, 3))
    else:
        if up is None:
            raise ValueError("build_network needs triangles (surface frame) or an up vector")
        frame = "up"
        pts = np.stack([a, cv, b, cv, cv, cv, cv], 1)
        upv = np.broadcast_to(np.asarray(up, float), (nb, 3)).copy()
    l0, l1 = rest_length[ea], rest_length[eb]
    net = RodNetwork(n, edges, rest_length, EA, pts.astype(np.int64), G, upv, w / (l0 + l1),
                     0.5 * (B1[ea] + B1[eb]), 0.5 * (B2[ea] + B2[eb]), 0.5 * (T[ea] + T[eb]), np.zeros((nb, 3)), frame)
    if np.any(off != 0):
        net.offset = 0.5 * (off[ea] + off[eb])
        net.stencil_EA = 0.5 * (EA[ea] + EA[eb])
        net.stencil_length = np.stack([l0, l1], 1)
    printed = net.measures(X)
    net.rest = printed + np.stack([rest_turning_curvature(0.5 * (kn[ea] + kn[eb]), l0, l1),
                                   np.zeros(nb), np.zeros(nb)], 1)
    return net


def _sides(P: np.ndarray, triangles: np.ndarray, p: np.ndarray, q: np.ndarray):
    """Third vertices L, R of the triangles left and right of the directed edges p -> q in the
    printed plane (the edge's start p where there is no triangle on that side)."""
    t = np.asarray(triangles, dtype=np.int64)
    P2 = P[:, :2]
    u, v = P2[t[:, 1]] - P2[t[:, 0]], P2[t[:, 2]] - P2[t[:, 0]]
    area = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    t = np.where((area < 0)[:, None], t[:, [0, 2, 1]], t)          # counter-clockwise
    n = len(P)
    src = np.concatenate([t[:, 0], t[:, 1], t[:, 2]])
    dst = np.concatenate([t[:, 1], t[:, 2], t[:, 0]])
    opp = np.concatenate([t[:, 2], t[:, 0], t[:, 1]])
    key = src * n + dst
    order = np.argsort(key)
    key, opp = key[order], opp[order]

    def lookup(u, v):
        k = u * n + v
        i = np.clip(np.searchsorted(key, k), 0, len(key) - 1)
        found = key[i] == k
        return np.where(found, opp[i], -1)

    L = lookup(p, q)                 # CCW triangle with directed edge p -> q: third vertex on the left
    R = lookup(q, p)
    if np.any((L < 0) & (R < 0)):
        raise ValueError("rod edges that are not edges of the sheet's triangles")
    return np.where(L >= 0, L, p), np.where(R >= 0, R, p)
