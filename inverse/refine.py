"""Refinement with the shell in the loop: per-ribbon plastic thicknesses (mm) chosen so that
the simulated equilibrium of the printed sheet matches target positions (mm).

Objective (mm^2), over the sheet's vertices x_i(p) at equilibrium for thicknesses p:

    J(p) = min over rigid motions (R, c) of  sum_i w_i |R x_i + c - T_i|^2 / sum_i w_i
           + smoothness * mean over neighbouring parameter pairs (p_r - p_s)^2

with w_i the vertex areas of the printed sheet and T_i the target position of vertex i (the
flattening's correspondence). Outer iterations are Gauss-Newton steps in a trust region
(Levenberg-Marquardt damping, bounds on p): the Jacobian dx/dp = -H^-1 dg/dp comes from the
factorised Hessian at the equilibrium and the analytic dg/dp (shellfem.sensitivity), one
back-substitution per parameter; the rigid motion is linearised alongside. Each trial
re-solves the equilibrium warm-started from the current one moved by the linear prediction,
so the iteration follows one equilibrium branch: the one the first solve found (started
from the target itself, the state nearest it).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from geometry.meshops import signed_areas
from inverse.registration import kabsch
from shellfem.errors import SelfshapeError
from shellfem.linalg import one_openblas_thread

#: the reason of a trial solve stopped because its objective rose past the limit
LEFT_BRANCH = "left the branch"


@dataclass(frozen=True)
class RefineOptions:
    """Choices of the refinement (mm). bounds: printable thickness range [lo, hi] (mm).
    max_outer: cap on outer (Gauss-Newton) iterations; ftol ends most runs before it. ftol: stop
    when an accepted step lowers J by less than this fraction (J is a mean squared distance: 1 %
    of J is 0.5 % of the RMS distance, below what the rounding to layers moves; each further
    outer iteration costs a sensitivity and a trial solve). newton_iterations: cap of each
    equilibrium solve; start_iterations: cap of the first one (from the caller's start, e.g. the
    target itself, from which the soft sheets relax in 100-300 iterations), which the caller may
    retry from another start. max_step: largest thickness change of one outer iteration (mm):
    the warm-started solves stay short and the Gauss-Newton
    model valid; it is also the largest trust radius: a rejected trial halves the radius to half
    its step's largest change (the damping alone does not shorten a step whose changes sit at
    the radius: the bounded least-squares step keeps them there until the damping outweighs the
    model) and remembers that change as a ceiling; an accepted trial that the model predicted
    well (rho > 0.75) raises the ceiling by a quarter and grows the radius to at most twice
    itself and at most the geometric mean of itself and the ceiling (a step as long as one that
    just left the branch is likely to leave it again, and each rejected trial costs a long
    solve). damping: initial Levenberg-Marquardt weight relative to the Gauss-Newton matrix's
    mean diagonal. leave_factor: a trial solve is stopped once its iterate's objective exceeds
    this times the current J: it is heading into another state (these sheets are multistable),
    and finishing that long solve only to reject the step costs more than the rest of the outer
    iteration; the trial counts as rejected. shifted_run: a trial solve is also stopped once
    this many consecutive iterations (after its first ``shifted_grace``) were
    Levenberg-Marquardt steps (a shifted Hessian: indefinite, or a full Newton step that did not
    lower the energy) while its iterate's objective is above the current J: the prediction put
    it beyond a fold of the branch and it is crossing to another state (0: never). A trial that
    stays on the branch converges from the prediction in Newton steps after at most a few
    shifted ones.
    stability: the stability margin (:class:`StabilityMargin`) as a fraction of the start
    equilibrium's lowest eigenvalue (0: no margin; the eigenvalue is recorded either way). On by
    default (0.5): without it the refinement walks these soft sheets towards a fold, where every
    trial step leaves the branch and the trust region collapses (docs/notes.md, session 30);
    stability_weight: its penalty at a fold, in units of the start's objective."""
    bounds: tuple = (0.1, 1.6)
    max_outer: int = 24
    ftol: float = 1e-2
    newton_iterations: int = 400
    trial_iterations: int = 100
    start_iterations: int = 300
    max_step: float = 0.2
    damping: float = 1e-3
    leave_factor: float = 1.25
    shifted_run: int = 6
    shifted_grace: int = 3
    stability: float = 0.5
    stability_weight: float = 1.0
    verbose: bool = False


@dataclass
class RefineResult:
    """thickness (P,) mm; q: the equilibrium there; objective (mm^2); rms_mm: the aligned RMS
    distance to the targets; history: per outer iteration dict(iteration, objective, rms_mm,
    accepted, damping, newton_iterations, seconds); converged: the last equilibrium solve
    converged (the refinement itself stops at ftol or max_outer, reason says which)."""
    thickness: np.ndarray
    q: np.ndarray
    objective: float
    rms_mm: float
    history: list = field(default_factory=list)
    reason: str = ""
    converged: bool = True
    model: tuple | None = None     # (p_lin, M, b): the last Gauss-Newton model |M (p - p_lin) - b|^2 of J
    margin: "StabilityMargin | None" = None    # the stability margin used (its lambda_star), for the rounding


def _coordinate_descent(M, res, offsets, choice, sweeps: int = 20) -> np.ndarray:
    """Per parameter j one of the values offsets[j, k] (NaN: not allowed) lowering |res|^2,
    where res is the model residual at the starting choice (P,) of indices and moving
    parameter j by an offset difference d moves res by d M[:, j]: coordinate descent, each
    parameter taking the best of its values given the others (strict decrease), a few sweeps.
    Returns the chosen offsets (P,)."""
    choice = np.asarray(choice, np.int64).copy()
    for _ in range(sweeps):
        changed = False
        for j in range(len(choice)):
            cur = offsets[j, choice[j]]
            best, best_k = res @ res, choice[j]
            for k, v in enumerate(offsets[j]):
                if k == choice[j] or not np.isfinite(v):
                    continue
                new = res + (v - cur) * M[:, j]
                if new @ new < best - 1e-15:
                    best, best_k = new @ new, k
            if best_k != choice[j]:
                res = res + (offsets[j, best_k] - cur) * M[:, j]
                choice[j], changed = best_k, True
        if not changed:
            break
    return offsets[np.arange(len(choice)), choice]


def linear_rounding(model, p, candidates_lo, step, sweeps: int = 20) -> np.ndarray:
    """Round thicknesses p (P,) to the grid candidates_lo + {0, step} choosing, per parameter,
    the side that the Gauss-Newton model (p_lin, M, b) of J predicts lower: coordinate descent
    from the nearest rounding (a few sweeps of P one-column updates; mm)."""
    p_lin, M, b = model
    lo = np.asarray(candidates_lo, float)
    choice = (np.asarray(p) - lo > 0.5 * step).astype(np.int64)
    offsets = np.tile([0.0, step], (len(lo), 1))
    res = M @ (lo + offsets[np.arange(len(lo)), choice] - p_lin) - b
    return lo + _coordinate_descent(M, res, offsets, choice, sweeps)


def vertex_areas(sheet) -> np.ndarray:
    """Lumped (one third of each triangle) printed-state area per vertex, mm^2."""
    a = np.abs(signed_areas(sheet.points, sheet.triangles))
    return np.bincount(sheet.triangles.ravel(), weights=np.repeat(a / 3.0, 3), minlength=sheet.n_vertices)


def neighbour_pairs(sheet, parameter: np.ndarray, n_parameters: int) -> np.ndarray:
    """(k, 2) pairs of parameters whose printed areas are natural neighbours: the edges of the
    Delaunay triangulation of their area-weighted centroids (printed-state mm)."""
    if n_parameters < 2:
        return np.zeros((0, 2), np.int64)
    P = sheet.points[sheet.triangles].mean(1)
    a = np.abs(signed_areas(sheet.points, sheet.triangles))
    sel = parameter >= 0
    w = np.bincount(parameter[sel], weights=a[sel], minlength=n_parameters)
    c = np.stack([np.bincount(parameter[sel], weights=a[sel] * P[sel, k], minlength=n_parameters) for k in (0, 1)], 1)
    c = c / np.maximum(w, 1e-300)[:, None]
    if n_parameters < 4:
        i, j = np.triu_indices(n_parameters, 1)
        return np.column_stack([i, j])
    from scipy.spatial import Delaunay
    try:
        tri = Delaunay(c)
    except Exception:                   # collinear centroids: neighbours along the line
        order = np.argsort(c[:, 0] + 1e-3 * c[:, 1])
        return np.column_stack([order[:-1], order[1:]])
    s = tri.simplices
    e = np.sort(np.concatenate([s[:, [0, 1]], s[:, [1, 2]], s[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


class ThicknessProblem:
    """The sheet, its materials and the triangle -> parameter map, evaluated at thicknesses p:
    models, equilibria and the aligned residual (mm). targets (n, 3): the target position of
    each sheet vertex (mm); free: the DOFs the equilibrium solves over (the rigid-motion
    gauge held); smoothness: weight of the mean squared thickness difference of neighbouring
    parameters (mm^2 of mean squared deviation per mm^2 of thickness difference); pairs: the
    neighbours (default :func:`neighbour_pairs`)."""

    def __init__(self, sheet, fabric, plastic, parameter, targets, free, *, smoothness=0.05, pairs=None):
        from shellfem.sensitivity import face_parameter_map
        self.sheet, self.fabric, self.plastic = sheet, fabric, plastic
        self.parameter, self.P = face_parameter_map(sheet, parameter)
        self.front = sheet.thickness_front > 0
        self.targets = np.asarray(targets, float)
        if self.targets.shape != (sheet.n_vertices, 3) or not np.all(np.isfinite(self.targets)):
            raise SelfshapeError(f"refine: targets must be finite, one (x, y, z) per sheet vertex "
                                 f"({sheet.n_vertices}), got shape {self.targets.shape}")
        self.free = free
        w = vertex_areas(sheet)
        self.w = w / w.sum()
        self.pairs = neighbour_pairs(sheet, self.parameter, self.P) if pairs is None else np.asarray(pairs)
        self.smoothness = float(smoothness)
        self.gradient_reference = None
        self.rtol = 1e-10
        self.trace = []                 # the objective at each iterate of the last limited solve (mm^2)
        self.drift = []                 # and each iterate's RMS distance from that solve's start (mm)

    def sheet_at(self, p):
        from shellfem.sheet import Sheet
        t = np.where(self.parameter >= 0, np.asarray(p, float)[np.maximum(self.parameter, 0)], 0.0)
        sh = self.sheet
        tf = np.where(self.parameter >= 0, np.where(self.front, t, 0.0), sh.thickness_front)
        tb = np.where(self.parameter >= 0, np.where(self.front, 0.0, t), sh.thickness_back)
        return Sheet(sh.points, sh.triangles, region=sh.region, thickness_front=tf, thickness_back=tb)

    def model_at(self, p):
        from shellfem.model import ShellModel
        return ShellModel.from_materials(self.sheet_at(p), self.fabric, self.plastic)

    def solve(self, model, q0, max_iterations, p=None, limit=None, shifted=None):
        """Equilibrium from q0; the gradient tolerance is relative to the force scale of the
        released flat sheet (not to the warm start's small residual, which would ask for
        round-off-level gradients in the soft valleys of these sheets). With ``limit`` (mm^2)
        and the thicknesses ``p`` of ``model``, the solve stops, not converged, with a reason
        starting LEFT_BRANCH, once an iterate's objective exceeds ``limit``; ``trace`` then keeps
        the objective at each accepted iterate. ``shifted`` = (run, grace, bound): also stop
        once ``run`` consecutive accepted iterations after the first ``grace`` were shifted
        (Levenberg-Marquardt) steps while the iterate's objective exceeds ``bound`` (mm^2)."""
        from shellfem.newton import newton
        if self.gradient_reference is None:
            self.gradient_reference = float(np.linalg.norm(model.gradient(model.initial_state())[self.free]))
        monitor = callback = None
        self.trace, self.drift = [], []
        if limit is not None:
            x0 = model.split(q0)[0]
            run, grace, bound = shifted if shifted is not None else (0, 0, np.inf)
            steps = []                  # each accepted iteration: shifted (True) or a Newton step

            def callback(entry):
                steps.append(entry.get("lam", 0.0) > 0.0)

            def monitor(q):
                x = model.split(q)[0]
                J = self.objective(x, p)[0]
                self.trace.append(J)
                self.drift.append(float(np.sqrt(self.w @ np.sum((x - x0) ** 2, 1))))
                if J > limit:
                    return f"{LEFT_BRANCH} (objective {J:.4g} > {limit:.4g} mm^2)"
                if run > 0 and J > bound and len(steps) >= grace + run and all(steps[-run:]):
                    return (f"{LEFT_BRANCH} ({run} shifted iterations in a row, objective {J:.4g} > "
                            f"{bound:.4g} mm^2)")
                return None
        return newton(model, q0, self.free, max_iterations=max_iterations, gradient_reference=self.gradient_reference,
                      rtol=self.rtol, monitor=monitor, callback=callback)

    def trial_solve(self, model, q_guess, q, max_iterations, p, limit, shifted=None):
        """A trial step's equilibrium (thicknesses p of ``model``): from the linear prediction
        q_guess, and from the current equilibrium q only when the prediction gave no start (the
        solve stopped within its first iteration); stopped past ``limit`` or on a run of
        shifted iterations (``shifted``) as in :meth:`solve`."""
        res = self.solve(model, q_guess, max_iterations, p, limit, shifted)
        if not res.converged and res.iterations < 2:
            res = self.solve(model, q, max_iterations, p, limit, shifted)
        return res

    def residual(self, x):
        """(rotation R, translation c, weighted residual rows (3n,), mean squared distance mm^2)."""
        R, c = kabsch(x, self.targets, self.w)
        d = x @ R.T + c - self.targets
        return R, c, (np.sqrt(self.w)[:, None] * d).ravel(), float(np.einsum("i,ij,ij->", self.w, d, d))

    def regulariser(self, p):
        if len(self.pairs) == 0 or self.smoothness <= 0:
            return np.zeros(0), sp.csr_matrix((0, self.P))
        k = len(self.pairs)
        s = np.sqrt(self.smoothness / k)
        rows = np.repeat(np.arange(k), 2)
        L = sp.csr_matrix((np.tile([s, -s], k), (rows, self.pairs.ravel())), shape=(k, self.P))
        return L @ p, L

    def objective(self, x, p):
        _, _, _, msd = self.residual(x)
        r, _ = self.regulariser(p)
        return msd + float(r @ r), msd


def gauss_newton_model(problem: ThicknessProblem, model, q, p, solve=None):
    """The Gauss-Newton model of J at the equilibrium q of thicknesses p (P,) mm:
    (M, b, dq, A) with J(p + s) ~ |M s - b|^2 (mm^2), dq (n_dofs, P) the equilibrium's
    Jacobian dq/dp (-H^-1 dg/dp: one factorisation, P back-substitutions; zero on held DOFs)
    and A the residual rows of M (the regulariser's rows below them). ``solve``: the free
    Hessian's factorisation at q if the caller has it. Raises
    shellfem.linalg.NotPositiveDefinite where the equilibrium is not stable."""
    from shellfem.sensitivity import equilibrium_factor, equilibrium_jacobian, thickness_form, thickness_gradient

    P, n, free = problem.P, problem.sheet.n_vertices, problem.free
    x = model.split(q)[0]
    R, c, r, msd = problem.residual(x)
    rr, L = problem.regulariser(p)
    form = thickness_form(model, problem.fabric, problem.plastic)
    _, G = thickness_gradient(model, form, q, problem.parameter, P)
    if solve is None:
        solve = equilibrium_factor(model, q, free)
    S = equilibrium_jacobian(solve, G, free)               # (n_free, P)
    dq = np.zeros((model.n_dofs, P))
    dq[free] = S
    dx = dq[:3 * n].reshape(n, 3, P)
    sw = np.sqrt(problem.w)[:, None, None]
    A_p = (sw * np.einsum("ij,njp->nip", R, dx)).reshape(3 * n, P)
    y = x @ R.T + c
    yc = y - problem.w @ y
    # rigid motions at the aligned state: small rotations about the weighted centroid, translations
    skew = np.zeros((n, 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = yc[:, 2], -yc[:, 1], yc[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = -yc[:, 2], yc[:, 1], -yc[:, 0]
    A_r = np.concatenate([sw * skew, sw * np.broadcast_to(np.eye(3), (n, 3, 3))], 2).reshape(3 * n, 6)
    # the objective re-aligns rigidly: to first order its residual moves by the part of
    # A_p orthogonal to the rigid motions (variable projection; a linearised rotation kept
    # as a variable would be an affine map and promise reductions no rigid motion gives)
    A = A_p - A_r @ np.linalg.lstsq(A_r, A_p, rcond=None)[0]
    M = np.concatenate([A, L.toarray()], 0)
    b = -np.concatenate([r, rr])
    return M, b, dq, A


class StabilityMargin:
    """A penalty that keeps the refined equilibrium away from a fold (mm^2, added to J):

        weight * J0 * max(0, 1 - lambda / lambda_star)^2,   lambda_star = fraction * lambda0

    lambda: the equilibrium's lowest eigenvalue (shellfem.stability.lowest_mode, N/mm^3),
    lambda0 and J0 those of the start. Why: the objective is often lowest where the branch is
    about to end (the target asks for a shape the sheet only just holds); there, rounding the
    thicknesses to printer layers, or a print's tolerance, tips the sheet into another state,
    and release from flat misses the refined state. The Gauss-Newton model gains the row
    sqrt(weight J0) (1 - (lambda + dlambda/dp s) / lambda_star) where lambda < lambda_star."""

    def __init__(self, problem: ThicknessProblem, fraction: float, weight: float = 1.0):
        self.problem, self.fraction, self.weight = problem, float(fraction), float(weight)
        self.lam_star = self.scale = None

    @property
    def on(self) -> bool:
        """A margin is asked for (fraction > 0) and its reference is set (a stable start)."""
        return self.fraction > 0 and self.lam_star is not None

    def reference(self, lam0: float, J0: float):
        """Set lambda_star from the start's eigenvalue lam0 (none if the start is not stable)."""
        if not lam0 > 0:
            return
        self.lam_star = self.fraction * float(lam0)
        self.scale = float(np.sqrt(self.weight * J0))

    def value(self, lam: float) -> float:
        if not self.on:
            return 0.0
        if not lam > 0:
            return np.inf
        return self.scale ** 2 * max(0.0, 1.0 - lam / self.lam_star) ** 2

    def active(self, lam: float) -> bool:
        return self.on and lam < self.lam_star

    def gradient(self, model, q, solve, u) -> np.ndarray:
        """dlambda/dp (P,) at the equilibrium q (shellfem.stability.mode_sensitivity)."""
        from shellfem.sensitivity import thickness_form, thickness_gradient
        from shellfem.stability import mode_sensitivity

        pr = self.problem
        form = thickness_form(model, pr.fabric, pr.plastic)
        return mode_sensitivity(model, q, pr.free, u,
                                lambda s: thickness_gradient(model, form, s, pr.parameter, pr.P)[1], solve)

    def row(self, model, q, solve, lam, u):
        """(M row (P,), b entry, dlambda/dp (P,)) of the penalty's Gauss-Newton row at lambda,
        the linearisation of its active side: |row s - b|^2 = the penalty at lambda + dlambda/dp s."""
        d = self.gradient(model, q, solve, u)
        return -self.scale * d / self.lam_star, -self.scale * (1.0 - lam / self.lam_star), d


def finite_or_none(x):
    """x as a float, or None where it is not finite (a trial solve that did not converge has no
    objective: reports say null and give the solve's reason, never Infinity)."""
    x = float(x)
    return x if np.isfinite(x) else None


def layer_descent(M, b, p, step: float, lo: float, hi: float, sweeps: int = 20) -> np.ndarray:
    """Thicknesses p (P,) on a layer grid moved by -step, 0 or +step each (inside [lo, hi], mm)
    to lower the Gauss-Newton model |M (p_new - p) - b|^2 of J linearised at p: coordinate
    descent, each parameter taking the best of its three values given the others."""
    p = np.asarray(p, float)
    offsets = np.tile([-step, 0.0, step], (len(p), 1))
    offsets[~((lo - 1e-9 <= p[:, None] + offsets) & (p[:, None] + offsets <= hi + 1e-9))] = np.nan
    return p + _coordinate_descent(M, -np.asarray(b, float), offsets, np.ones(len(p), np.int64), sweeps)


@one_openblas_thread
def refine_layers(problem: ThicknessProblem, p, q, step: float, bounds, rounds: int = 2,
                  newton_iterations: int = 400, max_trials: int = 4, verbose: bool = False,
                  leave_factor: float = RefineOptions.leave_factor, shifted_run: int = RefineOptions.shifted_run,
                  shifted_grace: int = RefineOptions.shifted_grace, margin: "StabilityMargin | None" = None,
                  ftol: float = 0.0, leaving_in_a_row: int = 2):
    """Layer-count refinement of rounded thicknesses p (P,) mm at their equilibrium q: up to
    ``rounds`` times, linearise J at the rounded state (gauss_newton_model), move ribbons by
    at most one layer (layer_descent), re-solve warm-started, and keep the move if J fell;
    a move that raises J is cut to the half of its ribbons whose single moves the model rates
    best, up to ``max_trials`` solves per round (a trust region on the number of ribbons moved);
    a trial solve whose objective passes ``leave_factor`` times the current J, or that runs
    ``shifted_run`` shifted iterations in a row above J (RefineOptions), is stopped.
    Rounding a continuous optimum to layers is linearised at the continuous point, far from
    the rounded one for thin ribbons (a 0.1 mm layer is 20 % of a 0.5 mm ribbon); this
    re-linearises where the design now is. ``margin`` (a StabilityMargin with its reference
    set, or None): moves are judged with its penalty, and the move is chosen with its row where
    the move's linearised eigenvalue would fall below lambda_star. Returns (p, q, J, history:
    per trial dict(round, changed, objective (None, with the solve's ``reason``, when the trial
    did not converge), predicted, accepted, seconds, lambda_min when a margin is given)).
    ``ftol``: the rounds also end after a round whose accepted move lowered the objective (with
    the margin's penalty) by less than this fraction, as the outer iteration ends
    (RefineOptions.ftol; 0: only a round without an accepted move ends them). Why: past that the
    moves trade a fraction of a per cent of J, less than the release from flat moves the state,
    at a trial solve each. ``leaving_in_a_row``: a round also ends once this many of its trials
    in a row left the branch (their solves stopped as LEFT_BRANCH; a trial that converged above
    J does not count). Why: a state whose one-layer move and its best half both tip the sheet
    into another state is at a fold for layer moves; on the hat, beetle, saddle, wave and hypar
    every smaller half then left too (docs/notes.md), at a long trial solve each."""
    from shellfem.linalg import NotPositiveDefinite
    from shellfem.sensitivity import equilibrium_factor
    from shellfem.stability import lowest_mode

    on = margin is not None and margin.on
    lo, hi = bounds
    model = problem.model_at(p)
    J = problem.objective(model.split(q)[0], p)[0]
    lam = u = solve = None          # the current state's lowest mode and factorisation, when known
    history = []
    for k in range(1, rounds + 1):
        shifted = (shifted_run, shifted_grace, J)
        try:
            if solve is None:
                solve = equilibrium_factor(model, q, problem.free)
            M, b, dq, _ = gauss_newton_model(problem, model, q, p, solve)
        except NotPositiveDefinite:
            break
        if on and lam is None:
            lam, u = lowest_mode(model, q, problem.free, solve)
        Jt = J + (margin.value(lam) if on else 0.0)
        move = layer_descent(M, b, p, step, lo, hi) - p
        if on:
            row, rhs, dlam = margin.row(model, q, solve, lam, u)
            if margin.active(lam) or lam + dlam @ move < margin.lam_star:
                M, b = np.concatenate([M, row[None]], 0), np.concatenate([b, [rhs]])
                move = layer_descent(M, b, p, step, lo, hi) - p
        idx = np.flatnonzero(np.abs(move) > 1e-9)
        # each move's own gain in the model from the current state: |b|^2 - |m M_j - b|^2
        m, Mj = move[idx], M[:, idx]
        gain = 2.0 * m * (Mj.T @ b) - m ** 2 * np.einsum("ij,ij->j", Mj, Mj)
        idx = idx[np.argsort(-gain, kind="stable")]
        accepted = False
        leaving = 0
        for _ in range(max_trials):
            if len(idx) == 0 or (leaving_in_a_row > 0 and leaving >= leaving_in_a_row):
                break
            t0 = time.perf_counter()
            s = np.zeros_like(p)
            s[idx] = move[idx]
            p_new = p + s
            pred = M @ s - b
            model_new = problem.model_at(p_new)
            res = problem.trial_solve(model_new, q + dq @ s, q, newton_iterations, p_new, leave_factor * J, shifted)
            J_new = problem.objective(model_new.split(res.q)[0], p_new)[0] if res.converged else np.inf
            Jt_new, lam_new, u_new, solve_new = J_new, None, None, None
            if on and res.converged:
                try:
                    solve_new = equilibrium_factor(model_new, res.q, problem.free)
                    lam_new, u_new = lowest_mode(model_new, res.q, problem.free, solve_new, v0=u)
                    Jt_new = J_new + margin.value(lam_new)
                except NotPositiveDefinite:
                    Jt_new = np.inf
            ok = bool(Jt_new < Jt)
            history.append(dict(round=k, changed=int(len(idx)), objective=finite_or_none(J_new),
                                predicted=float(pred @ pred), accepted=ok, seconds=round(time.perf_counter() - t0, 2),
                                **({"lambda_min": lam_new} if on else {}),
                                **({} if res.converged else {"reason": res.reason})))
            if verbose:
                print(f"layers {k}: {len(idx)} ribbons moved one layer, J {J:.4e} -> {J_new:.4e} "
                      f"(predicted {pred @ pred:.4e}{'' if lam_new is None else f', lambda_min {lam_new:.4e}'})"
                      f"{'' if ok else ', rejected'}", flush=True)
            if ok:
                p, q, model, J, accepted = p_new, res.q, model_new, J_new, True
                lam, u, solve = lam_new, u_new, solve_new
                break
            leaving = leaving + 1 if (not res.converged and res.reason.startswith(LEFT_BRANCH)) else 0
            idx = idx[:len(idx) // 2]
        if not accepted or Jt - Jt_new < ftol * Jt:
            break
    return p, q, J, history


def follow_thickness(problem: ThicknessProblem, p_from, q_from, p_to, steps: int = 4, newton_iterations: int = 400):
    """The equilibrium at thicknesses p_to (P,) mm followed from the equilibrium q_from at p_from
    in ``steps`` equal thickness steps, each solve warm-started from the last: the same branch
    where one solve from q_from would jump to another state. Returns (q, converged)."""
    q = q_from
    p_from, p_to = np.asarray(p_from, float), np.asarray(p_to, float)
    for k in range(1, steps + 1):
        p_k = p_from + (k / steps) * (p_to - p_from)
        r = problem.solve(problem.model_at(p_k), q, newton_iterations)
        if not r.converged:
            return q, False
        q = r.q
    return q, True


def next_trust_radius(radius: float, ceiling: float, step, rho: float, max_step: float):
    """The refinement's trust radius and ceiling (mm) after a trial of the step ``step`` (P,)
    whose actual over predicted decrease was ``rho`` (see RefineOptions.max_step): rejected
    (rho <= 0.1): half the step's largest change, which becomes the ceiling; accepted and well
    predicted (rho > 0.75): the ceiling raised by a quarter, the radius grown to at most twice
    itself, ``max_step`` and the geometric mean of itself and the ceiling; otherwise unchanged."""
    if not rho > 0.1:                   # rejected (also a NaN)
        ceiling = float(np.max(np.abs(step)))
        return 0.5 * ceiling, ceiling
    if rho > 0.75:
        ceiling = 1.25 * ceiling
        radius = min(max_step, 2.0 * radius, float(np.sqrt(radius * ceiling)))
    return radius, ceiling


@one_openblas_thread
def refine_thickness(problem: ThicknessProblem, p0, q0, options: RefineOptions = RefineOptions(),
                     callback=None) -> RefineResult:
    """Gauss-Newton refinement of the thicknesses from p0 (P,) with the equilibrium solve
    started from q0 (see the module doc). ``callback(iteration, p, q, model)`` is called at
    each accepted iterate (for measurements), its dict merged into the history entry.
    Raises SelfshapeError if the first equilibrium cannot be found (nothing to refine)."""
    from scipy.optimize import lsq_linear

    from shellfem.linalg import NotPositiveDefinite
    from shellfem.sensitivity import equilibrium_factor
    from shellfem.stability import lowest_mode

    lo, hi = (float(b) for b in options.bounds)
    p = np.clip(np.asarray(p0, float), lo, hi)
    P = problem.P
    t0 = time.perf_counter()
    model = problem.model_at(p)
    res = problem.solve(model, q0, options.start_iterations)
    if not res.converged:
        raise SelfshapeError(f"refine: no equilibrium near the start ({res.reason}; {res.iterations} iterations)")
    q = res.q
    J, msd = problem.objective(model.split(q)[0], p)
    margin = StabilityMargin(problem, options.stability, options.stability_weight)
    try:
        solve = equilibrium_factor(model, q, problem.free)
        lam, u = lowest_mode(model, q, problem.free, solve)
    except NotPositiveDefinite:
        solve, lam, u = None, 0.0, None
    margin.reference(lam, J)
    history = [dict(iteration=0, objective=J, rms_mm=float(np.sqrt(msd)), accepted=True, damping=None,
                    lambda_min=lam, newton_iterations=int(res.iterations), seconds=round(time.perf_counter() - t0, 2))]
    if callback is not None:
        history[-1].update(callback(0, p, q, model) or {})
    if options.verbose:
        print(f"refine 0: J {J:.4e} mm^2, rms {np.sqrt(msd):.4f} mm, lambda_min {lam:.4e} N/mm^3, {res.iterations} Newton iterations", flush=True)
    mu = None
    radius = options.max_step
    ceiling = np.inf            # the largest change of the last rejected step (mm), raised by each good one
    reason = f"reached max_outer = {options.max_outer}"
    last_model = None
    it = 0
    while it < options.max_outer:
        it += 1
        t_it = time.perf_counter()
        try:
            M, b, dq, A = gauss_newton_model(problem, model, q, p, solve)
        except NotPositiveDefinite:
            reason = "the equilibrium is not stable (Hessian not positive definite): no sensitivity"
            break
        Jt = J + margin.value(lam)              # the objective with the stability margin's penalty
        systems = [(M, b)]
        dlam = None
        if margin.on:
            # the penalty's row (exact on its active side, lambda < lambda_star): used where the
            # current state is active, or where a step's linearised lambda would cross (a margin
            # is on only from a stable start, and every accepted state keeps its factorisation)
            row, rhs, dlam = margin.row(model, q, solve, lam, u)
            systems.append((np.concatenate([M, row[None]], 0), np.concatenate([b, [rhs]])))
        t_sens = time.perf_counter() - t_it
        t_solves, trials = 0.0, 0
        last_model = (p.copy(), *systems[-1 if margin.active(lam) else 0])
        g_scale = float(np.mean(np.sum(A ** 2, 0))) + 1e-300
        if mu is None:
            mu = options.damping * g_scale
        accepted = False
        # |M s - b|^2 = |R s - Q^T b|^2 + |b|^2 - |Q^T b|^2 (thin QR): the bounded steps are
        # solved on the P x P factor instead of the (3n + pairs) x P matrix
        factors = []
        for Ms, bs in systems:
            Qm, Rm = np.linalg.qr(Ms, mode="reduced")
            Qb = Qm.T @ bs
            factors.append((Rm, Qb, max(float(bs @ bs) - float(Qb @ Qb), 0.0)))
        while True:
            for k in range(1 if margin.active(lam) else 0, len(factors)):
                Rm, Qb, rest = factors[k]
                sol = lsq_linear(np.concatenate([Rm, np.sqrt(mu) * np.eye(P)], 0), np.concatenate([Qb, np.zeros(P)]),
                                 bounds=(np.maximum(lo - p, -radius), np.minimum(hi - p, radius)),
                                 method="bvls")
                step = sol.x
                if dlam is None or lam + dlam @ step >= margin.lam_star:
                    break
            pred_lin = Rm @ step - Qb
            predicted = float(pred_lin @ pred_lin) + rest   # the Gauss-Newton model's J at the step
            if np.max(np.abs(step)) < 1e-6:
                reason = "the step vanished (a stationary point within the bounds)"
                break
            p_try = np.clip(p + step, lo, hi)
            model_try = problem.model_at(p_try)
            q_guess = q + dq @ (p_try - p)
            t_s = time.perf_counter()
            trials += 1
            res = problem.trial_solve(model_try, q_guess, q, options.trial_iterations, p_try, options.leave_factor * J,
                                      (options.shifted_run, options.shifted_grace, J))
            t_solves += time.perf_counter() - t_s
            solve_try, lam_try, u_try = None, 0.0, None
            if res.converged:
                J_try, msd_try = problem.objective(model_try.split(res.q)[0], p_try)
                try:
                    solve_try = equilibrium_factor(model_try, res.q, problem.free)
                    lam_try, u_try = lowest_mode(model_try, res.q, problem.free, solve_try, v0=u)
                except NotPositiveDefinite:      # converged to a saddle point of the energy: not a state
                    J_try = np.inf
                Jt_try = J_try + margin.value(lam_try)
                rho = (Jt - Jt_try) / max(Jt - predicted, 1e-300)
            else:
                J_try, Jt_try, rho = np.inf, np.inf, -np.inf
            if options.verbose:
                peak = max(problem.trace, default=np.nan) / J
                print(f"  trial: J {J_try:.4e}, with the margin {Jt_try:.4e} (predicted {predicted:.4e}), lambda_min {lam_try:.4e}, "
                      f"rho {rho:.3f}, mu {mu:.2e}, radius {radius:.3g} mm, "
                      f"{res.iterations} Newton iterations, peak J / J {peak:.3f}"
                      f"{'' if res.converged else ' (' + res.reason + ')'}", flush=True)
                pred_move = float(np.sqrt(problem.w @ np.sum((model.split(q_guess)[0] - model.split(q)[0]) ** 2, 1)))
                steps = "".join("N" if h.get("lam", 0.0) == 0.0 else str(min(9, max(0, int(np.log10(h["lam"]) + 10))))
                                for h in res.history)
                dr = problem.drift
                print(f"    predicted move {pred_move:.4f} mm; drift from the guess at 3/5/10/20/end "
                      + " ".join(f"{dr[k]:.4f}" if k < len(dr) else "-" for k in (2, 4, 9, 19))
                      + f" {dr[-1] if dr else float('nan'):.4f} mm; steps {steps}", flush=True)
                print("    objective / J per iterate " + " ".join(f"{t / J:.2f}" for t in problem.trace), flush=True)
            if rho > 0.1:
                accepted = True
                mu = mu / 3 if rho > 0.75 else mu
                radius, ceiling = next_trust_radius(radius, ceiling, step, rho, options.max_step)
                break
            mu *= 8
            radius, ceiling = next_trust_radius(radius, ceiling, step, rho, options.max_step)
            if mu > 1e8 * g_scale or radius < 1e-4:
                reason = "the trust region collapsed: no trial step lowered the objective"
                break
        if not accepted:
            history.append(dict(iteration=it, objective=J, rms_mm=float(np.sqrt(msd)), accepted=False,
                                damping=float(mu), radius_mm=radius, newton_iterations=0, seconds=round(time.perf_counter() - t_it, 2)))
            break
        decrease = (Jt - Jt_try) / max(Jt, 1e-300)
        p, q, model, J, msd = p_try, res.q, model_try, J_try, msd_try
        solve, lam, u = solve_try, lam_try, u_try
        history.append(dict(iteration=it, objective=J, rms_mm=float(np.sqrt(msd)), accepted=True, damping=float(mu),
                            lambda_min=lam, penalty=margin.value(lam),
                            radius_mm=radius, newton_iterations=int(res.iterations), trials=trials, sensitivity_s=round(t_sens, 2),
                            solves_s=round(t_solves, 2), seconds=round(time.perf_counter() - t_it, 2)))
        if callback is not None:
            history[-1].update(callback(it, p, q, model) or {})
        if options.verbose:
            print(f"refine {it}: J {J:.4e} mm^2, rms {np.sqrt(msd):.4f} mm, lambda_min {lam:.4e} N/mm^3 "
                  f"(start {history[0]['lambda_min']:.4e})", flush=True)
        if decrease < options.ftol:
            reason = f"relative decrease {decrease:.2e} < ftol {options.ftol:g}"
            break
    return RefineResult(thickness=p, q=q, objective=J, rms_mm=float(np.sqrt(msd)), history=history, reason=reason,
                        model=last_model, margin=margin)
