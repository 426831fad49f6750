"""Relaxations inside the Newton iteration: partial minimisations over a subset of the DOFs.

- :class:`EdgeAngleRelaxation`: the edge angles at frozen positions (a nonlinear
  elimination of the angles, after every accepted step);
- :class:`StiffRegionRelaxation`: the printed regions' DOFs at trial points, before they
  are judged.

Both take a few damped Newton steps on their subproblem, keep the sparsity pattern and the
symbolic factorisation between calls, and never raise the energy (N mm).
"""
from __future__ import annotations

import numpy as np

from shellfem.assembly import BlockScatter
from shellfem.linalg import NotPositiveDefinite, SparseSPD


class EdgeAngleRelaxation:
    """Minimise the energy over the free edge angles at frozen positions (a few damped Newton
    steps on shellfem.model.EdgeAngleProblem; sparsity and symbolic factorisation kept).

    A nonlinear elimination of the angles: after every accepted step of the full Newton
    iteration the angles are re-solved, so the outer iteration works on (nearly) the reduced
    energy min_theta E(x, theta). The angles enter the energy through tan(psi), which curves
    the landscape strongly at the kinks between stiff plastic and soft fabric (|theta| ~ 1.2 rad
    at a star sheet's equilibrium); a full-Newton step that moves x cannot follow that curvature
    and is cut short. Costs ~1/20 of a full assembly + factorisation per inner step."""

    def __init__(self, model, free, backend: str = "auto", max_iterations: int = 4):
        n = model.n_vertices
        self.model, self.n = model, n
        self.free = free[3 * n:].copy()
        self.scatter = BlockScatter([model.topo.face_edges], model.n_edges, self.free, upper=True)
        self.solver = SparseSPD(backend)
        self.max_iterations = max_iterations
        self.iterations = 0
        self._shift = 0.0          # last shift that made the inner Hessian positive definite

    def __call__(self, q, energy_scale: float, max_iterations: int | None = None):
        """q with its free angles relaxed (never with a higher energy); at most max_iterations
        inner steps (default: the instance's)."""
        if not self.free.any():
            return q
        problem = self.model.edge_angle_problem(q)
        theta = q[3 * self.n:].copy()
        E, g_all, blocks = problem.evaluate(theta)
        if not np.isfinite(E):
            return q
        for _ in range(self.max_iterations if max_iterations is None else max_iterations):
            g = g_all[self.free]
            H = self.scatter.matrix([blocks])
            factor, self._shift = _factor_shifted(self.solver, H, self.scatter.upper, self._shift)
            if factor is None:
                break
            d = -factor(g)
            slope = float(g @ d)
            if -0.5 * slope <= 1e-12 * energy_scale:
                break
            a = 1.0
            self.iterations += 1
            for _ in range(20):
                trial = theta.copy()
                trial[self.free] += a * d
                E_try = problem.evaluate(trial, order=0)[0]
                if np.isfinite(E_try) and E_try <= E + 1e-4 * a * slope:
                    break
                a *= 0.5
            else:
                break
            theta = trial
            E, g_all, blocks = problem.evaluate(theta)
        out = q.copy()
        out[3 * self.n:] = theta
        return out


class StiffRegionRelaxation:
    """Re-minimise the energy over the printed regions' DOFs with the rest frozen (a few
    damped Newton steps; the energy never rises), applied to trial points of the outer
    iteration before they are judged.

    Why: along a star sheet's slow valley (the roll changing shape) the Newton step is cut to
    1/4-1/8 and LM steps stay short, because a finite step strains the stiff printed plastic:
    on the 40 x 30 mm sheet at iteration 50, the trial at half the Newton step raises the
    printed triangles' energy by +2.80 while the bare fabric gains -0.23 (N mm). Relaxing the
    printed DOFs at that trial point recovers a decrease (-0.054 after a few steps, against
    -0.016 for the step the line search took), so the outer iteration can take the longer
    step. Each inner step costs one full assembly (sheet-wide kernels, scattered to the
    printed DOFs only) and one factorisation of that much smaller block."""

    def __init__(self, model, free, mask, backend: str = "auto", max_iterations: int = 2, buffers=None):
        self.model = model
        self._blocks = buffers            # model.block_buffers() to write the element blocks into
        self.mask = mask & free
        self.scatter = BlockScatter([model.face_dofs, model.hinge_dofs], model.n_dofs, self.mask, upper=True)
        self.solver = SparseSPD(backend)
        self.max_iterations = max_iterations
        self.calls = 0
        self._shift = 0.0

    def __call__(self, q):
        """(q, E) after up to max_iterations damped Newton steps on the masked DOFs (E is
        the energy at the returned q; the start's energy comes with its Hessian)."""
        model, P = self.model, self.mask
        self.calls += 1
        E = None
        for _ in range(self.max_iterations):
            E_q, g_all, blocks = model.hessian_blocks(q, out=self._blocks)
            E = E_q if E is None else E
            g = g_all[P]
            H = self.scatter.matrix(blocks)
            factor, self._shift = _factor_shifted(self.solver, H, self.scatter.upper, self._shift)
            if factor is None:
                break
            d = -factor(g)
            slope = float(g @ d)
            if not slope < 0:
                break
            t = 1.0
            for _ in range(20):
                trial = q.copy()
                trial[P] += t * d
                E_try = model.trial_energy(q, trial, below=E + 1e-4 * t * slope)   # +inf through a contact
                if np.isfinite(E_try) and E_try <= E + 1e-4 * t * slope:
                    break
                t *= 0.5
            else:
                break
            q, E = trial, E_try
        return q, E


def _factor_shifted(solver, H, upper: bool, last: float = 0.0, tries: int = 30):
    """(factor, shift): factor of H + shift |diag H| with the smallest shift of the ladder
    0, 1e-6, 8e-6, ... from last / 8 on that is positive definite ((None, 0.0) if none of
    ``tries`` is, so the next call starts from 0): the inner solves of the relaxations, which
    pass their last shift. The printed block at trial points is indefinite most of the time
    and climbing the ladder from 0 failed 2.5 times per success (85 x 60 benchmark: 247 of 345
    factorisations)."""
    D = np.abs(H.diagonal()) + 1e-12
    shift = last / 8 if last / 8 >= 1e-6 else 0.0
    for _ in range(tries):
        try:
            return solver.factor(H, shift=shift * D if shift else None, upper=upper), shift
        except NotPositiveDefinite:
            shift = max(8.0 * shift, 1e-6)
    return None, 0.0
