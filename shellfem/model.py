"""The discrete shell: DOF layout, per-region materials, total energy and derivatives.

DOFs q = [x (n x 3, vertex-major), theta (one angle per edge)], mm and radians.
Energy in N mm. Per triangle the energy is a function of y = (a, h, psi) (see
shellfem.kinematics, shellfem.face_energy); derivatives are chained exactly:

    W_q = J^T W_y,    W_qq = J^T W_yy J + sum_k W_y,k d2y_k/dq2

with J = dy/dq over the triangle's 21 local DOFs (own 3 vertices, 3 flap vertices,
3 edge angles), in shellfem.kinematics.face_chain. The dihedral-angle curvature term is
assembled per hinge (12 x 12).
"""
from __future__ import annotations

from functools import cached_property

import numpy as np
from numba import njit, prange

from shellfem.bending.midedge_tan import coefficients, from_coefficients, inadmissible, second_fundamental_form
from shellfem.face_energy import face_energy
from shellfem.kinematics import (C_OUTER, build_topology, face_chain, face_metrics, hinge_angle_values,
                                 hinge_angles)
from shellfem.layers import (QuadraticForm, bending_quadratic, layer_form, layer_scratch, layer_terms, rest_area,
                             sym_to_mat)
from shellfem.materials import MEMBRANE_MODELS, Fabric, Plastic, RestState
from shellfem.sheet import Sheet

_CHUNK = 512   # faces per parallel task in compiled kernels


def edge_metric(P: np.ndarray) -> np.ndarray:
    """Edge-basis metric (m, 3) of triangles with 2D/3D corner points P (m, 3, d)."""
    E1, E2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    return np.stack([np.einsum("ij,ij->i", E1, E1), np.einsum("ij,ij->i", E1, E2), np.einsum("ij,ij->i", E2, E2)], 1)


class ShellModel:
    """Energy of a sheet: layered quadratic terms + optional fabric membrane + gravity.

    Build with :meth:`from_materials` (fabric + printed plastic, the seed's model) or
    :meth:`homogeneous` (one isotropic St.Venant-Kirchhoff shell, for benchmarks).
    """

    def __init__(self, sheet: Sheet, quad: QuadraticForm, membrane_mask=None, membrane=None,
                 external_force=None):
        self.sheet = sheet
        self.topo = build_topology(sheet.triangles)
        self.quad = quad
        self.membrane_mask = membrane_mask
        self.membrane = membrane          # callable(a_masked) -> W, g, H
        self.external_force = external_force  # (n, 3) N, dead loads (gravity); potential -f.x
        # shellfem.contact.Contact or None: barrier energies on the positions (self-contact,
        # ground), included in energy/gradient; its (PSD-projected) Hessian of the last order-2
        # evaluation is left in contact_hessian for the solver (scattered outside the blocks)
        self.contact = None
        self.contact_hessian = None
        n, ne = sheet.n_vertices, self.topo.n_edges
        self.n_vertices, self.n_edges = n, ne
        self.n_dofs = 3 * n + ne
        self._build_indices()

    # --- construction ---------------------------------------------------------------
    @classmethod
    def homogeneous(cls, sheet: Sheet, E: float, nu: float, h: float, rest_curvature=None,
                    exact_metric: bool = False):
        """Single-layer isotropic shell (MPa, mm), flat and stress-free in the sheet's
        coordinates unless ``rest_curvature`` (2x2 in the sheet's x, y; 1/mm) is given.
        exact_metric: the exact Kirchhoff-Love metric through the thickness (shellfem.layers;
        False: the truncated metric a - 2 z b)."""
        P = np.concatenate([sheet.points, np.zeros((sheet.n_vertices, 1))], 1)[sheet.triangles]
        abar = edge_metric(P)
        bbar = np.zeros_like(abar)
        if rest_curvature is not None:
            P2 = sheet.points[sheet.triangles]
            Em = np.stack([P2[:, 1] - P2[:, 0], P2[:, 2] - P2[:, 0]], 2)        # columns E1, E2
            Bm = np.einsum("mji,jk,mkl->mil", Em, np.asarray(rest_curvature, float), Em)
            bbar = np.stack([Bm[:, 0, 0], Bm[:, 0, 1], Bm[:, 1, 1]], 1)
        quad = QuadraticForm(sheet.n_triangles)
        quad.add(*layer_form(abar, bbar, E, nu, -h / 2, h / 2, exact_metric=exact_metric))
        return cls(sheet, quad)

    @classmethod
    def from_materials(cls, sheet: Sheet, fabric: Fabric, plastic: Plastic, gravity: bool = True,
                       exact_metric: bool = True):
        """The seed's model: bare fabric = the fabric's membrane model (Fabric.model, from the
        registry of shellfem.materials) + bending with k_B; printed triangles = fabric layer (E2, nu_f) + plastic layer(s)
        on the front (+z) and/or back (-z) face, plastic with rest curvature (plastic set).
        The fabric's rest metric is diag(1/sx^2, 1/sy^2) in printed coordinates. The layers
        carry the exact Kirchhoff-Love metric (shellfem.layers; exact_metric=False: the
        truncated a - 2 z b, O(kappa h) off for bilayers)."""
        m = sheet.n_triangles
        P2 = sheet.points[sheet.triangles]                      # (m, 3, 2) printed
        P3 = np.concatenate([P2, np.zeros((m, 3, 1))], 2)
        sx, sy = fabric.stretch
        Prest = P2 / np.array([sx, sy])
        abar_print = edge_metric(P3)
        abar_fab = edge_metric(Prest)
        hf = fabric.thickness
        tf, tb = sheet.thickness_front, sheet.thickness_back
        printed = (tf > 0) | (tb > 0)
        bare = ~printed
        quad = QuadraticForm(m)
        if printed.any():
            quad.add(*layer_form(abar_fab, np.zeros((m, 3)), fabric.young_modulus, fabric.poisson, -hf / 2, hf / 2,
                                 exact_metric=exact_metric), mask=printed)
            for mask, bbar, z0, z1, _, _ in plastic_layers(sheet, fabric, plastic, abar_print):
                quad.add(*layer_form(abar_print, bbar, plastic.young_modulus, plastic.poisson, z0, z1,
                                     exact_metric=exact_metric), mask=mask)
        membrane = None
        if bare.any():
            if fabric.bending_stiffness > 0:
                quad.add(*bending_quadratic(abar_fab, fabric.bending_stiffness, fabric.poisson), mask=bare)
            ab = abar_fab[bare]
            rest = RestState(points=Prest[bare], metric=ab, area=rest_area(ab))
            membrane = MEMBRANE_MODELS[fabric.model](rest, fabric).energy
        force = None
        if gravity and fabric.areal_weight > 0:
            force = np.zeros((sheet.n_vertices, 3))
            force[:, 2] = -nodal_loads(sheet, fabric.areal_weight / (sx * sy))
        return cls(sheet, quad, bare if membrane is not None else None, membrane, force)

    # --- index maps -------------------------------------------------------------------
    def _build_indices(self):
        t, topo = self.sheet.triangles, self.topo
        m = len(t)
        flaps = np.where(topo.flaps >= 0, topo.flaps, t)          # dummy = own vertex, zero weight
        pts = np.concatenate([t, flaps], 1)                       # (m, 6)
        self.face_dofs = np.concatenate([(3 * pts[:, :, None] + np.arange(3)).reshape(m, 18),
                                         3 * self.n_vertices + topo.face_edges], 1)   # (m, 21)
        self.hinge_dofs = (3 * topo.hinge[:, :, None] + np.arange(3)).reshape(-1, 12)
        hinge_of_edge = -np.ones(topo.n_edges, dtype=np.int64)
        hinge_of_edge[topo.hinge_edges] = np.arange(len(topo.hinge_edges))
        self.face_hinge = hinge_of_edge[topo.face_edges]             # (m, 3), -1 on boundary
        # local columns (0..17) of the hinge's 12 coordinates inside the face's 21 DOFs
        cols = np.zeros((m, 3, 12), dtype=np.int64)
        for i in range(3):       # local edge i: hinge points (e0, e1, oA, oB)
            j, k = (i + 1) % 3, (i + 2) % 3
            as_A = np.array([j, k, i, 3 + i])
            as_B = np.array([k, j, 3 + i, i])
            order = np.where((topo.face_sign[:, i] > 0)[:, None], as_A, as_B)    # (m, 4)
            cols[:, i] = (3 * order[:, :, None] + np.arange(3)).reshape(m, 12)
        self._hinge_cols = cols

    # --- evaluation ---------------------------------------------------------------------
    def split(self, q):
        n = self.n_vertices
        return q[:3 * n].reshape(n, 3), q[3 * n:]

    def _psi(self, x, theta, with_gradient):
        """Mid-edge angles psi (m, 3) and the dihedral angles' gradients (k, 12) (None
        without)."""
        topo = self.topo
        xh = x[topo.hinge]
        if with_gradient:
            phi, gphi, _ = hinge_angles(xh, with_hessian=False)
        else:
            phi, gphi = hinge_angle_values(xh), None
        fh = self.face_hinge
        interior = fh >= 0
        psi = topo.face_sign * theta[topo.face_edges] + np.where(interior, 0.5 * phi[np.maximum(fh, 0)], 0.0)
        return psi, gphi

    def energy(self, q, below: float | None = None) -> float:
        """Total energy at q (N mm). ``below``: the value the caller will compare it against
        (accepting only a smaller one): when the energy without the contact barriers (which are
        >= 0) is already not below it, that part is returned, a lower bound that the caller
        rejects as it would the total, and no collisions are built (a build costs ~0.3 s on a
        10k-vertex sheet in contact, about half of such a solve's time)."""
        return float(self._evaluate(q, order=0, below=below)[0])

    def _evaluate(self, q, order=2, out=None, below=None, barriers=True):
        """(E, gradient or None, Hessian blocks or None) up to ``order``; ``below`` as for
        :meth:`energy`; ``barriers=False``: without the contact barriers (order 0 only)."""
        x, theta = self.split(q)
        t = self.sheet.triangles
        m = len(t)
        xf = x[t]
        a, h = face_metrics(xf)
        psi, gphi = self._psi(x, theta, order >= 1)
        mm = self.membrane_mask
        membrane = None
        if self.membrane is not None:
            def membrane(aa):
                W = np.zeros(m)
                g = np.zeros((m, 3))
                H = np.zeros((m, 3, 3))
                W[mm], g[mm], H[mm] = self.membrane(aa[mm])
                return W, g, H
        W, Wy, Wyy = face_energy(a, h, psi, self.quad, membrane, order=order)
        E = W.sum()
        if self.external_force is not None:
            E -= float(np.sum(self.external_force * x))
        contact_g = None
        if order == 0 and below is not None and not E <= below:
            return E, None, None         # the contact barriers (>= 0) cannot bring it below
        if self.contact is not None and barriers:
            Ec, contact_g, self.contact_hessian = self.contact.evaluate(x, order=order)
            E += Ec                      # +inf when inadmissible (callers test E first)
        if order == 0:
            return E, None, None
        g_face, Hf = face_chain(xf, self.topo.face_sign, self.face_hinge, self._hinge_cols, gphi, Wy,
                                Wyy if order >= 2 else None, out=None if out is None else out[0])
        grad = np.bincount(self.face_dofs.ravel(), weights=g_face.ravel(), minlength=self.n_dofs)
        if self.external_force is not None:
            grad[:3 * self.n_vertices] -= self.external_force.ravel()
        if contact_g is not None:
            grad[:3 * self.n_vertices] += contact_g
        if order == 1:
            return E, grad, None
        # hinge curvature term: w_e d2phi_e with w_e = 1/2 sum over the edge's faces of dW/dpsi
        wpsi = np.where(self.face_hinge >= 0, 0.5 * Wy[:, 6:9], 0.0)
        wh = np.bincount(np.maximum(self.face_hinge, 0).ravel(), weights=wpsi.ravel(), minlength=len(gphi))
        Hh_blocks = hinge_angles(x[self.topo.hinge], weights=wh, out=None if out is None else out[1])[2]
        return E, grad, (Hf, Hh_blocks)

    def gradient(self, q):
        return self._evaluate(q, order=1)[1]

    def step_fraction(self, q0, q1) -> float:
        """Largest fraction t in [0, 1] of the straight move q0 -> q1 that no contact forbids
        (shellfem.contact.Contact.step_fraction; 1.0 without contact): the solver's step filter."""
        if self.contact is None:
            return 1.0
        n = self.n_vertices
        return self.contact.step_fraction(q0[:3 * n].reshape(n, 3), q1[:3 * n].reshape(n, 3))

    def trial_energy(self, q0, q1, below: float | None = None) -> float:
        """Energy at q1 (N mm), +inf if the straight move from q0 to q1 passes through a contact
        (:meth:`step_fraction` < 1): how the solver and its relaxations judge trial points.
        ``below`` as for :meth:`energy`: a trial whose energy without the contact barriers is
        not below it is rejected on that lower bound, before any collision check."""
        if self.contact is None:
            return self.energy(q1)
        E0 = None
        if below is not None:
            E0 = float(self._evaluate(q1, order=0, barriers=False)[0])
            if not E0 <= below:
                return E0
        if self.step_fraction(q0, q1) < 1.0:
            return np.inf
        if E0 is None:
            return self.energy(q1)
        n = self.n_vertices
        return E0 + float(self.contact.evaluate(q1[:3 * n].reshape(n, 3), order=0)[0])

    def hessian_blocks(self, q, out=None):
        """(E, gradient, (face blocks (m, 21, 21), hinge blocks (k, 12, 12))) at q (N mm, N, N/mm
        for positions); the blocks are written into ``out`` = :meth:`block_buffers` if given
        (reused between calls: no page faults on fresh arrays)."""
        return self._evaluate(q, order=2, out=out)

    def block_buffers(self):
        """Arrays (face blocks, hinge blocks) for hessian_blocks(q, out=...)."""
        return np.empty((self.sheet.n_triangles, 21, 21)), np.empty((len(self.topo.hinge), 12, 12))

    def printed_dofs(self) -> np.ndarray:
        """Mask over the DOFs of the printed (stiff) regions: positions of the vertices of
        printed triangles and the angles of their edges (all False on a bare sheet)."""
        t = self.sheet.triangles
        printed = (self.sheet.thickness_front > 0) | (self.sheet.thickness_back > 0)
        mask = np.zeros(self.n_dofs, bool)
        v = np.unique(t[printed])
        mask[(3 * v[:, None] + np.arange(3)).ravel()] = True
        mask[3 * self.n_vertices + np.unique(self.topo.face_edges[printed])] = True
        return mask

    @cached_property
    def edge_bending_form(self) -> np.ndarray:
        """(m, 3, 3) sigma_i sigma_j c_i^T W_bb c_j per face with W_bb the quadratic part's
        constant d2W/db2: EdgeAngleProblem's Hessian is elementwise with it (the einsum it
        replaces cost 8 of the 18 ms per evaluation at 21k faces); on the exact-metric faces
        (quad.thick) W_bb depends on the state and is recomputed there."""
        sign = self.topo.face_sign
        return (C_OUTER @ self.quad.Q[:, 3:, 3:] @ C_OUTER.T) * sign[:, :, None] * sign[:, None, :]

    def edge_angle_problem(self, q) -> "EdgeAngleProblem":
        """The energy as a function of the edge angles alone, positions frozen at those of q."""
        return EdgeAngleProblem(self, q)

    def initial_state(self) -> np.ndarray:
        """Flat printed state: x = (X, Y, 0), theta = 0."""
        x = np.concatenate([self.sheet.points, np.zeros((self.n_vertices, 1))], 1)
        return np.concatenate([x.ravel(), np.zeros(self.n_edges)])

    # --- derived fields ---------------------------------------------------------------------
    def fundamental_forms(self, q):
        x, theta = self.split(q)
        xf = x[self.sheet.triangles]
        a, h = face_metrics(xf)
        psi = self._psi(x, theta, False)[0]
        return a, second_fundamental_form(h, psi)

    def cartesian_forms(self, q):
        """First and second fundamental forms (m, 2, 2) in the printed Cartesian coordinates
        (X, Y) of each triangle (a = I and b = 0 in the flat printed state; mm units)."""
        a, b = self.fundamental_forms(q)
        P = self.sheet.points[self.sheet.triangles]
        Dinv = np.linalg.inv(np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]], 1))   # rows: edge vectors
        return tuple(Dinv @ sym_to_mat(f) @ np.swapaxes(Dinv, 1, 2) for f in (a, b))

    def curvatures(self, q):
        """Principal curvatures (m, 2) (1/mm, k1 >= k2; > 0 = centre of curvature on the +normal
        side) and mean/Gaussian curvature per triangle, from the shape operator a^-1 b."""
        a, b = self.fundamental_forms(q)
        S = np.linalg.solve(sym_to_mat(a), sym_to_mat(b))
        tr = S[:, 0, 0] + S[:, 1, 1]
        det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
        disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0))
        k = np.stack([tr / 2 + disc, tr / 2 - disc], 1)
        return k, tr / 2, det

    def fibre_bending(self, q) -> np.ndarray:
        """rho (m,) = zmax^2 (k1^2 + k2^2) of each triangle with exact-metric layers (0 elsewhere;
        zmax mm the layers' largest |z|, k_i 1/mm): the measure in which the exact metric's
        third-form terms fade (shellfem.layers.RHO_EXACT, RHO_TRUNCATED); sqrt(rho) bounds every
        fibre's |k z|. Above RHO_EXACT a fibre is shortened or lengthened by more than half (the
        exact energy is faded there); from RHO_TRUNCATED the fold stop holds the triangle (past
        the thin-shell range); at RHO_FOLDED a fibre has zero length: the Kirchhoff body has
        folded (no elastic equilibrium of a printed sheet)."""
        rho = np.zeros(self.sheet.n_triangles)
        thick = self.quad.thick
        if thick.any():
            k = self.curvatures(q)[0][thick]
            rho[thick] = np.max(self.quad.zspan[thick] ** 2, axis=1) * (k * k).sum(1)
        return rho


class EdgeAngleProblem:
    """E(theta) at frozen positions x: the bending part of the energy that depends on the
    edge angles (N mm; the membrane, gravity and other theta-free terms are dropped, so
    values are differences, not totals), with its gradient (n_edges,) and sparse Hessian.

    With x frozen, each face's energy depends only on its own three tan(psi_i), and each
    angle on its two faces: the Hessian has the sparsity of the face-edge adjacency and
    factorises in a fraction of the full Hessian's time (used by
    shellfem.relaxations.EdgeAngleRelaxation)."""

    def __init__(self, model: ShellModel, q):
        x, _ = model.split(q)
        self.model = model
        xf = x[model.sheet.triangles]
        self.a, self.h = face_metrics(xf)
        self.half_phi = model._psi(x, np.zeros(model.n_edges), False)[0]     # psi at theta = 0
        self._CWC = model.edge_bending_form
        self._thick = bool(model.quad.thick.any())
        self._sign = model.topo.face_sign.astype(float)

    def evaluate(self, theta, order: int = 2):
        """(E, gradient, Hessian blocks (m, 3, 3) over each face's edges); E = inf where an
        angle leaves the admissible set |psi| < PSI_MAX (0.49 pi)."""
        topo, quad = self.model.topo, self.model.quad
        psi = topo.face_sign * theta[topo.face_edges] + self.half_phi
        h = self.h
        beta, _, b_psi, _, b_psipsi = coefficients(h, psi)
        z = np.concatenate([self.a, from_coefficients(beta)], 1)
        CWC = self._CWC
        if self._thick and order == 2:    # W_bb depends on the state on the exact-metric faces
            CWC = CWC.copy()
        W, Wz = np.empty(len(z)), np.empty((len(z), 6))
        ptr, Qs, zbars, Rs, cbars, thick, zspan = quad.packed()
        _edge_angle_kernel(z, ptr, Qs, zbars, Rs, cbars, thick, zspan, quad.Q, C_OUTER, self._sign, order, W, Wz,
                           CWC)
        E = float(np.where(inadmissible(psi), np.inf, W).sum())
        if order == 0:
            return E, None, None
        gi = Wz[:, 3:] @ C_OUTER.T                       # dW/d beta_i
        Wpsi = b_psi * gi
        grad = np.bincount(topo.face_edges.ravel(), weights=(topo.face_sign * Wpsi).ravel(),
                           minlength=self.model.n_edges)
        if order == 1:
            return E, grad, None
        Hpsi = b_psi[:, :, None] * b_psi[:, None, :] * CWC
        idx = np.arange(3)
        Hpsi[:, idx, idx] += b_psipsi * gi                # face_sign^2 = 1 on the diagonal
        return E, grad, Hpsi


@njit(cache=True, parallel=True)
def _edge_angle_kernel(z, ptr, Qs, zbars, Rs, cbars, thick, zspan, Qtot, C, sign, order, W, Wz, CWC):
    """The layered energy W (m,) and dW/dz (m, 6) (order >= 1) at z (m, 6) in one pass and, with
    order 2, CWC[f] = sigma_i sigma_j c_i^T W_bb(z_f) c_j on the exact-metric faces (the
    state-dependent counterpart of ShellModel.edge_bending_form; CWC holds that on entry)."""
    m = z.shape[0]
    for chunk in prange((m + _CHUNK - 1) // _CHUNK):
        g = np.empty(6)
        Z = np.empty((6, 6))
        work = layer_scratch()
        for f in range(chunk * _CHUNK, min(m, (chunk + 1) * _CHUNK)):
            o = 2 if (order == 2 and thick[f]) else min(order, 1)
            g[:] = 0.0
            if o == 2:
                for k in range(6):
                    for l in range(6):
                        Z[k, l] = Qtot[f, k, l]
            W[f] = layer_terms(z[f], ptr[f], ptr[f + 1], Qs, zbars, Rs, cbars, thick[f], zspan[f, 0], zspan[f, 1], o,
                               g, Z, work)
            for k in range(6):
                Wz[f, k] = g[k]
            if o == 2:
                for p in range(3):
                    for r in range(3):
                        s = 0.0
                        for k in range(3):
                            for l in range(3):
                                s += C[p, k] * Z[3 + k, 3 + l] * C[r, l]
                        CWC[f, p, r] = sign[f, p] * sign[f, r] * s


def plastic_layers(sheet: Sheet, fabric: Fabric, plastic: Plastic, abar_print: np.ndarray):
    """The printed plastic layers of the seed's model, front then back, where present: tuples
    (mask (m,), rest curvature bbar (m, 3), z0 (m,), z1 (m,), dz0/dt, dz1/dt) with the layer
    between z0 and z1 (mm about the fabric's mid-surface) and the rates at which its bounds
    move with the layer's thickness t (for shellfem.sensitivity). Front plastic ([hf/2,
    hf/2 + t]) bends the sheet towards -z (centre of curvature on the fabric side: b < 0),
    back plastic ([-hf/2 - t, -hf/2]) towards +z; both carry the plastic set as rest
    curvature."""
    hf, kap = fabric.thickness, plastic.rest_curvature
    tf, tb = sheet.thickness_front, sheet.thickness_back
    out = []
    if (tf > 0).any():
        out.append((tf > 0, -kap * abar_print, np.full(len(tf), hf / 2), hf / 2 + tf, 0.0, 1.0))
    if (tb > 0).any():
        out.append((tb > 0, kap * abar_print, -hf / 2 - tb, np.full(len(tb), -hf / 2), -1.0, 0.0))
    return out


def nodal_loads(sheet: Sheet, load_per_area: float) -> np.ndarray:
    """Consistent P1 nodal loads (N) of a uniform areal load (N/mm^2 of printed area),
    assembled with scikit-fem."""
    from skfem import Basis, ElementTriP1, LinearForm

    @LinearForm
    def unit(v, w):
        return load_per_area * v

    return unit.assemble(Basis(sheet.mesh, ElementTriP1()))
