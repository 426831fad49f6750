"""How far an equilibrium is from losing stability, and how that distance moves with the
printed thicknesses (N, mm).

An equilibrium q of the sheet is stable where the free-DOF Hessian H is positive definite. Its
distance from a fold (the state where the branch ends and the sheet snaps to another state) is
the smallest eigenvalue of the stiffness the sheet's vertices feel, with the edge-angle DOFs
relaxed (the Schur complement K of H onto the vertex positions), measured per unit area:

    lambda = min over v of  v^T K v / v^T M v          (N/mm^3)

with M the lumped vertex areas of the printed state (mm^2), so that lambda does not depend on
the mesh: a displacement field v of the softest mode, held against the sheet's own stiffness,
costs lambda |v|^2 per mm^2. lambda -> 0 at a fold; a design whose equilibrium sits near one
is tipped into another state by the rounding of its thicknesses or by a print's tolerance.

The sensitivity to the thickness parameters p (P,) at an equilibrium, for a simple lambda with
mode u = (v, v_theta) (v_theta the relaxed edge angles, v^T M v = 1; H u = (lambda M v, 0)):

    dlambda/dp_j = u^T (dH/dp_j) u + T(u, u, dq/dp_j),    dq/dp = -H^-1 dg/dp

where T(u, u, .) = d/dt [H(q + t u) u] is the third derivative of the energy along the mode
(a central difference of two Hessian products; the only finite difference here) and
u^T (dH/dp_j) u = d/dt [u^T dg/dp_j (q + t u)] likewise from the exact dg/dp
(shellfem.sensitivity.thickness_gradient). The second term is an adjoint: one solve with the
factorised Hessian.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from shellfem.assembly import symmetric_matvec
from shellfem.errors import SelfshapeError


def lowest_mode(model, q, free, solve=None, tol: float = 1e-6, v0=None):
    """The smallest eigenvalue lambda (N/mm^3, see the module doc) of the equilibrium q and its
    mode u (n_dofs,) (zero on held DOFs; positions normalised to v^T M v = 1). ``solve``: a
    factorisation of the free Hessian (shellfem.sensitivity.equilibrium_factor; made here if
    None; it raises shellfem.linalg.NotPositiveDefinite when q is not stable). Lanczos on
    M^1/2 (H^-1)_xx M^1/2, whose largest eigenvalue is 1 / lambda; v0 (n_dofs,) starts it (a
    previous mode: a few iterations)."""
    from shellfem.model import nodal_loads
    from shellfem.sensitivity import equilibrium_factor

    if solve is None:
        solve = equilibrium_factor(model, q, free)
    n = model.sheet.n_vertices
    free = np.asarray(free, bool)
    fx = free[:3 * n]                                   # free position DOFs
    m = np.repeat(nodal_loads(model.sheet, 1.0), 3)[fx]    # lumped vertex areas (mm^2)
    s = np.sqrt(m)
    nf = int(free.sum())
    pos = np.flatnonzero(fx)                            # free positions inside the free vector:
    index = np.cumsum(free) - 1                         # position DOF k is free entry index[k]
    fpos = index[pos]

    def op(y):
        r = np.zeros(nf)
        r[fpos] = s * np.asarray(y).ravel()
        return s * solve(r)[fpos]

    C = spla.LinearOperator((len(pos), len(pos)), matvec=op, dtype=float)
    start = None
    if v0 is not None:
        start = s * np.asarray(v0, float)[pos]
        if not np.all(np.isfinite(start)) or np.linalg.norm(start) == 0:
            start = None
    if start is None:
        start = np.random.default_rng(len(pos)).standard_normal(len(pos))
    mu, w = spla.eigsh(C, k=1, which="LA", v0=start, tol=tol)
    mu = float(mu[0])
    if not mu > 0:
        raise SelfshapeError("lowest_mode: the Hessian's inverse is not positive (state not stable)")
    lam = 1.0 / mu
    r = np.zeros(nf)
    r[fpos] = s * w[:, 0]                               # M v with v = w / s
    uf = lam * solve(r)                                 # H u = (lambda M v, 0)
    u = np.zeros(model.n_dofs)
    u[free] = uf
    vx = u[:3 * n][fx]
    u /= np.sqrt(vx @ (m * vx))
    return lam, u


def mode_sensitivity(model, q, free, u, G_at, solve, step: float | None = None):
    """dlambda/dp (P,) (N/mm^3 per mm) of the lowest mode u of :func:`lowest_mode` at the
    equilibrium q; ``G_at(q)`` returns dg/dp (n_dofs, P) at a state (the exact thickness
    derivative of the gradient); ``solve`` the free Hessian's factorisation. ``step``: the
    central-difference step along u (mm; default 1e-4 of the mode's largest displacement
    scaled to 1 mm)."""
    from shellfem.sensitivity import free_hessian

    free = np.asarray(free, bool)
    n = model.sheet.n_vertices
    umax = float(np.max(np.abs(u[:3 * n]))) if n else 1.0
    if not umax > 0:
        raise SelfshapeError("mode_sensitivity: the mode has no displacement")
    h = (1e-4 if step is None else float(step)) / umax
    qp, qm = q + h * u, q - h * u
    uf = u[free]
    Tuu = (symmetric_matvec(free_hessian(model, qp, free), uf)
           - symmetric_matvec(free_hessian(model, qm, free), uf)) / (2 * h)   # T(u, u, .) on free DOFs
    Gp, Gm = sp.csr_matrix(G_at(qp)), sp.csr_matrix(G_at(qm))
    direct = (Gp.T @ u - Gm.T @ u) / (2 * h)                                    # u^T dH/dp u
    G = sp.csc_matrix(G_at(q))[free]
    adj = solve(np.ascontiguousarray(Tuu))
    return np.asarray(direct).ravel() - np.asarray(G.T @ adj).ravel()
