"""Sensitivity of the shell's energy and equilibrium to the printed thickness (N, mm).

Parameters p_1..p_P are plastic thicknesses (mm), one per group of printed triangles (a
ribbon, a region): ``parameter`` (m,) maps each triangle to its group (-1: not a
parameter). The plastic layer of a printed triangle is W = 1/2 w^T Q9 w in the differences
w = (a - abar, b - bbar, c - cbar) of its fundamental forms (exact metric, shellfem.layers),
with Q9 linear in the through-thickness moments M_k = int z^k K mu dz, whose derivatives in
the layer's bounds are the integrand at the bounds (exact), and w independent of t, so

    dE/dp_j        = sum over j's triangles of 1/2 w^T dQ9/dt w
    d(dE/dq)/dp_j  = the gradient of that derivative form, chained to the DOFs like the
                     energy's own (shellfem.face_energy, shellfem.kinematics.face_chain)

exactly, with no finite differences. At an equilibrium g(q, p) = 0 the implicit function
theorem gives dq/dp = -H^-1 dg/dp over the free DOFs (H the Hessian there), and for an
objective J(q) the adjoint lam = H^-1 dJ/dq gives dJ/dp = -lam^T dg/dp (one solve).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from shellfem.errors import SelfshapeError
from shellfem.face_energy import face_energy
from shellfem.kinematics import face_chain, face_metrics
from shellfem.layers import QuadraticForm, layer_form_derivative
from shellfem.model import ShellModel, edge_metric, plastic_layers


def thickness_form(model: ShellModel, fabric, plastic, exact_metric: bool | None = None) -> QuadraticForm:
    """The per-triangle derivative dW/dt of the plastic layers' energy with respect to the
    triangle's own plastic thickness t (mm), as a QuadraticForm (N mm per mm). A triangle
    printed on both faces cannot take one thickness parameter: SelfshapeError. Exact where the
    third-form terms carry their full weight (shellfem.layers.RHO_EXACT: every fibre within
    |z k| <= 0.5, as at every equilibrium); in the fade before a focal point it is the
    derivative of the unfaded exact-metric energy, and past it that of the energy without the
    fold stop (shellfem.layers.RHO_FOLDED)."""
    sheet = model.sheet
    if ((sheet.thickness_front > 0) & (sheet.thickness_back > 0)).any():
        raise SelfshapeError("thickness sensitivity: a triangle is printed on both faces; "
                             "one thickness parameter per triangle cannot describe it")
    m = sheet.n_triangles
    P3 = np.concatenate([sheet.points[sheet.triangles], np.zeros((m, 3, 1))], 2)
    abar = edge_metric(P3)
    if exact_metric is None:
        exact_metric = bool(model.quad.thick.any())
    form = QuadraticForm(m)
    for mask, bbar, z0, z1, dz0, dz1 in plastic_layers(sheet, fabric, plastic, abar):
        form.add(*layer_form_derivative(abar, bbar, plastic.young_modulus, plastic.poisson, z0, z1, dz0, dz1,
                                        exact_metric=exact_metric), mask=mask)
    return form


def face_parameter_map(sheet, parameter) -> tuple[np.ndarray, int]:
    """Check a (m,) triangle -> parameter map; returns it as int64 and the parameter count."""
    p = np.asarray(parameter)
    if p.shape != (sheet.n_triangles,) or not np.issubdtype(p.dtype, np.integer):
        raise SelfshapeError(f"thickness sensitivity: parameter must be one integer per triangle "
                             f"({sheet.n_triangles}), got shape {p.shape}")
    p = p.astype(np.int64)
    if (p >= 0).any() and not sheet.printed[p >= 0].all():
        raise SelfshapeError("thickness sensitivity: a parameter is assigned to an unprinted triangle")
    return p, int(p.max(initial=-1)) + 1


def thickness_gradient(model: ShellModel, form: QuadraticForm, q: np.ndarray, parameter: np.ndarray,
                       n_parameters: int | None = None):
    """dE/dp (P,) (N mm per mm) and d(dE/dq)/dp as a sparse (n_dofs, P) matrix (N per mm for
    positions, N mm per mm for edge angles) at state q. ``form``: :func:`thickness_form` of the
    model; ``parameter`` (m,): each triangle's parameter index, -1 for none."""
    parameter, P = face_parameter_map(model.sheet, parameter)
    P = P if n_parameters is None else int(n_parameters)
    x, theta = model.split(q)
    xf = x[model.sheet.triangles]
    a, h = face_metrics(xf)
    psi, gphi = model._psi(x, theta, True)
    W, Wy, _ = face_energy(a, h, psi, form, None, order=1)
    sel = parameter >= 0
    dE = np.bincount(parameter[sel], weights=W[sel], minlength=P)
    g_face, _ = face_chain(xf, model.topo.face_sign, model.face_hinge, model._hinge_cols, gphi, Wy)
    rows = model.face_dofs[sel].ravel()
    cols = np.repeat(parameter[sel], 21)
    G = sp.csr_matrix((g_face[sel].ravel(), (rows, cols)), shape=(model.n_dofs, P))
    G.sum_duplicates()
    return dE, G


def free_hessian(model: ShellModel, q: np.ndarray, free: np.ndarray):
    """The Hessian over the free DOFs at q, upper triangle in CSR (N/mm for positions), as the
    Newton solver assembles it (shellfem.assembly.BlockScatter)."""
    from shellfem.assembly import BlockScatter

    _, _, (Hf, Hh) = model.hessian_blocks(q)
    return BlockScatter([model.face_dofs, model.hinge_dofs], model.n_dofs, free, upper=True).matrix([Hf, Hh])


def equilibrium_factor(model: ShellModel, q: np.ndarray, free: np.ndarray, backend: str = "auto"):
    """A solve function for the free-DOF Hessian at the equilibrium q (SparseSPD); raises
    shellfem.linalg.NotPositiveDefinite when the state is not a stable equilibrium."""
    from shellfem.linalg import SparseSPD

    return SparseSPD(backend).factor(free_hessian(model, q, free), upper=True)


def equilibrium_jacobian(solve, G: sp.spmatrix, free: np.ndarray, block: int = 128) -> np.ndarray:
    """dq/dp (n_free, P) at an equilibrium: -H^-1 dg/dp with the factorised free Hessian
    ``solve`` (SparseSPD's: it takes the right-hand sides as the columns of a matrix). The
    columns go ``block`` at a time: the factor is read once per block, not once per parameter
    (a refinement with a hundred ribbons spent most of its sensitivity time in the one-column
    solves), and memory stays at n_free x block beside the result."""
    Gf = sp.csc_matrix(G)[free]
    nf, P = Gf.shape
    out = np.empty((nf, P))
    for j in range(0, P, block):
        cols = Gf[:, j:j + block].toarray()
        out[:, j:j + cols.shape[1]] = -np.asarray(solve(cols)).reshape(nf, cols.shape[1])
    return out


def adjoint_gradient(solve, G: sp.spmatrix, free: np.ndarray, dJ_dq: np.ndarray) -> np.ndarray:
    """dJ/dp (P,) of an objective J(q(p)) at an equilibrium through one adjoint solve:
    lam = H^-1 dJ/dq_free, dJ/dp = -lam^T dg/dp (``solve``: the factorised free Hessian)."""
    lam = solve(np.ascontiguousarray(dJ_dq[free], dtype=float))
    return -(sp.csc_matrix(G)[free].T @ lam)
