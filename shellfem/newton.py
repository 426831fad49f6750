"""Newton's method for the shell's total energy, robust to indefinite Hessians.

Each iteration assembles the exact Hessian H over the free DOFs and solves
(H + lambda D) d = -g with a sparse Cholesky factorisation (shellfem.linalg: MKL PARDISO,
else CHOLMOD, else SciPy's SuperLU; symbolic analysis once per mesh), D = |diag H| floored
per DOF kind (:func:`lm_metric`): a Levenberg-Marquardt trust region. lambda grows when the
factorisation reports H + lambda D indefinite (the flat released state is a saddle; buckling
passes through indefinite states) or when the step's actual energy decrease is poor compared
with the quadratic model's prediction, and shrinks to 0 when the model is good, so the end
game is plain Newton with quadratic convergence. The diagonal scaling makes the shift act on each DOF
in proportion to its own stiffness, which matters with a plastic/fabric stiffness
contrast of 10^3-10^4 (a fixed-cap identity shift, as in the seed's solver, stalls there).
Energies that leave the admissible set (inverted triangles, log barrier) are +inf and
the step is rejected.

After every accepted step (and at the start) the edge angles are re-minimised with the
positions frozen (shellfem.relaxations.EdgeAngleRelaxation, a nonlinear elimination of the
angles that costs ~1/20 of an outer iteration). Trial points that strain the stiff printed
regions (a cut Newton step doubled, LM steps with a poor model ratio) are first relaxed over
the printed regions' DOFs (shellfem.relaxations.StiffRegionRelaxation).

Newton steps follow a rotation-corrected curve instead of a straight line when the sheet
rotates (shellfem.corotational); optionally an indefinite Hessian is first retried with its
hinge (dihedral-angle) blocks projected to positive semi-definite before LM takes over.

Contact (a model whose ``contact`` is a shellfem.contact.Contact): its barrier energy and
gradient are in the model's; its exact Hessian (positions only, a changing sparsity) is added to
the assembled one on a grow-only union pattern (shellfem.assembly.PatternUnion), and when that
sum is indefinite its PSD-projected blocks are tried before the trust region takes over (such
steps never decide convergence). Every trial point - the Newton line search's (cut to the
collision-free fraction of the move), the LM step, the negative-curvature search, the printed
relaxation's inner steps - is judged by ``model.trial_energy(q, q_try)``: +inf unless the straight
move from the current iterate is free of contact (continuous collision detection); along a
rotation-corrected path the check is on the straight segment to the trial point, so every
accepted state is reached from the last one without passing through the sheet. Each trial passes
the bound it is judged by (``below``): one whose energy without the barriers (>= 0) is already
above it is rejected without a collision build or check. The edge-angle
relaxation moves no position and needs no check. A start that intersects or whose supports
force penetration stops the solve at once with that reason.

Creep: near a fold of the equilibrium path (a release step close to a snap-through) the
Hessian's smallest eigenvalue is small and full Newton steps advance along that soft mode by a
little each, the energy falling ever faster while the gradient does not fall (a 14k-vertex
stars tube crept so for 150 iterations of its second release step). When the last CREEP_WINDOW
accepted iterations were all full Newton steps, the gradient norm did not fall below half of
where the window started and the energy fell by less than CREEP_ENERGY of itself, the accepted
full step is extrapolated along the same path (2, 4, ... up to CREEP_MAX_FACTOR times, each
trial through the collision filter) as long as the energy keeps falling. A solve converging
quadratically never meets the test.

Convergence: ||grad||_2 over the free DOFs <= max(atol, rtol * gradient_reference) (the
reference defaults to the gradient norm at the start) AND the exact Hessian (lambda = 0)
factorised, so the state is a local minimum, not a saddle. Anything else is reported as
not converged, with the reason.
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from itertools import islice

import numpy as np

from shellfem.assembly import BlockScatter, PatternUnion, reduce_upper, symmetric_matvec
from shellfem.corotational import RotationPath, rotate
from shellfem.linalg import NotPositiveDefinite, SparseSPD, one_openblas_thread
from shellfem.relaxations import EdgeAngleRelaxation, StiffRegionRelaxation

#: inner steps of the start's edge-angle relaxation (after an accepted step: the relaxation's 4)
START_ANGLE_ITERATIONS = 50
#: a contact solve has stalled when STALL_ITERATIONS accepted iterations, each with a trial cut
#: by the collision filter on average, moved the sheet by less than STALL_MOVE x the offset in all
STALL_ITERATIONS = 30
STALL_MOVE = 0.01

#: creep (see the module's docstring): CREEP_WINDOW full Newton steps that lowered the energy by
#: less than CREEP_ENERGY x |E| in all and left the gradient norm above half of its value at the
#: window's start; the full step is then extrapolated by factors 2, 4, ... <= CREEP_MAX_FACTOR
CREEP_WINDOW = 10
CREEP_ENERGY = 1e-4
CREEP_MAX_FACTOR = 1024.0

#: an LM trial that raised the energy by less than this many times the model's predicted decrease
#: is relaxed over the printed regions before it is judged (beyond, it is rejected as it is)
STIFF_TRIAL_RISE = 10.0

#: Default trust-region metric floor (see :func:`lm_metric`); [solver] metric_floor = 0 gives
#: plain Marquardt scaling.
DEFAULT_METRIC_FLOOR = 10.0


MAX_ITERATIONS_REASON = "maximum number of iterations reached"

LAM_MIN = 1e-10          # below this the Levenberg-Marquardt shift is dropped to 0

#: A gradient norm above the tolerance by at most GRADIENT_FLOOR_FACTOR at a stable state whose
#: exact Newton step is below the step tolerance and promises no energy is at its round-off floor
#: (the solve has converged) when taking that step does not lower it, or when it stays so over
#: GRADIENT_FLOOR_STEPS consecutive Newton steps. Why: the tolerance is relative to a reference
#: force, and on a large sheet the gradient's round-off can sit just above it; such a solve used
#: to run on into a collapsed trust region, reported as not converged (docs/notes.md, session 26).
GRADIENT_FLOOR_FACTOR = 10.0
GRADIENT_FLOOR_STEPS = 3


def _psd_blocks(B):
    """Blocks (k, d, d) with their negative eigenvalues set to 0."""
    w, V = np.linalg.eigh(B)
    return (V * np.maximum(w, 0.0)[:, None, :]) @ np.swapaxes(V, 1, 2)


def lm_metric(diag: np.ndarray, is_position: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """Levenberg-Marquardt metric D (the shift is lam D): |H_ii|, floored at ``floor`` times the
    median |H_ii| over the DOFs of the same kind (positions, mm; edge angles, rad).

    Plain Marquardt scaling (floor 0) barely damps the softest DOFs, the bare fabric at free
    edges, where the slow phases of a star-sheet solve move (measured: 55-100 % of the squared
    displacement within 3 mm of the edge); the floor bounds their step like a trust region in
    mm while the stiff plastic DOFs keep their own scale. The default floor,
    DEFAULT_METRIC_FLOOR = 10, is the best of the floors 0.1-1000 measured on star sheets
    (docs/notes)."""
    D = np.abs(np.asarray(diag, float))
    D = D + 1e-8 * max(float(D.mean()), 1e-300) if len(D) else D
    if floor > 0:
        for kind in (is_position, ~is_position):
            if kind.any():
                D[kind] = np.maximum(D[kind], floor * float(np.median(D[kind])))
    return D


@dataclass
class SolveResult:
    q: np.ndarray
    converged: bool
    iterations: int
    energy: float
    gradient_norm: float
    reason: str
    stable: bool
    history: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)


@dataclass(frozen=True)
class NewtonOptions:
    """Options of :func:`newton` (the keyword arguments it takes).

    rtol, atol: gradient tolerance max(atol, rtol * gradient_reference) (N; the reference
        defaults to the gradient norm at the start).
    max_iterations: the cap on outer iterations. backend: shellfem.linalg.SparseSPD's.
    verbose: one line per iteration on stdout.
    callback: called after each accepted step with its history entry (a dict: iteration,
        energy N mm and gradient_norm N before the step, lam the trust-region shift), so a
        caller can show progress (the CLI's status line) without this layer printing.
    monitor: called with the iterate q (n_dofs,) after each accepted step; a returned
        non-empty string stops the solve, not converged, with that string as its reason (a
        caller whose objective shows the solve leaving the state it wants stops paying for it).
    stability_shift: a LM shift up to this still counts as the exact Hessian factorising.
    step_tolerance: the Newton step's largest position change must be below this times the
        sheet's size; energy_tolerance: the energy the Newton step still promises (half the
        Newton decrement, -g.d/2) must be below this times max(|E|, 1e-6 |E_start|).
    energy_reference: the problem's energy scale (N mm) when the solve is warm-started near
        an equilibrium (the exact-metric solve after the truncated one): E_start in the floor
        above is then at least this. A sheet with nothing to release (stretch 1) starts that
        solve at E ~ 1e-19 and ends at round-off (1e-28), so without it the floor was 1e-25
        and the solve stopped "not converged" at |g| 8e-14 (issue 19).
    rotation_path: steps whose triangles rotate by more than 1e-3 rad follow the
        rotation-corrected curve of :mod:`shellfem.corotational` (tangent to the step, each
        triangle rotated rigidly) instead of the straight line, which stretches rotating
        regions and forces short steps.
    project_hinges (off by default): when H is indefinite, first try the Hessian with each
        hinge's dihedral-angle block (moment x d2(phi)) projected to PSD: these blocks are
        where the indefiniteness sits (bare-fabric flaps hinged to a printed triangle
        carrying a large moment). It helps some sheets and slows others (docs/notes). Such
        steps never decide convergence (the exact H must factorise for that).
    metric_floor: the trust-region metric D of H + lam D is |H_ii| floored at this multiple
        of the median |H_ii| of its DOF kind (positions, edge angles); see :func:`lm_metric`.
        None means DEFAULT_METRIC_FLOOR (10); 0 gives plain Marquardt scaling, D = |diag H|.
    relax_angles (default on): re-minimise the free edge angles at frozen positions at the
        start and after every accepted step (EdgeAngleRelaxation); it never raises the
        energy and never decides convergence.
    relax_printed (default on): trial points of the outer iteration - twice the step the
        Newton line search accepted when it had to cut, and LM steps whose energy falls
        short of the model (rho < 0.75) - are first relaxed over the printed regions' DOFs
        (StiffRegionRelaxation; off when the printed DOFs are most of the sheet's, e.g. a
        strip printed all over).
    """
    rtol: float = 1e-8
    atol: float = 1e-10
    max_iterations: int = 300
    backend: str = "auto"
    verbose: bool = False
    callback: object = None
    monitor: object = None
    gradient_reference: float | None = None
    energy_reference: float | None = None
    stability_shift: float = 1e-6
    step_tolerance: float = 1e-7
    energy_tolerance: float = 1e-11
    rotation_path: bool = True
    project_hinges: bool = False
    metric_floor: float | None = None
    relax_angles: bool = True
    relax_printed: bool = True

    @property
    def floor(self) -> float:
        """The metric floor in use (metric_floor, or DEFAULT_METRIC_FLOOR for None)."""
        return DEFAULT_METRIC_FLOOR if self.metric_floor is None else self.metric_floor


@one_openblas_thread
def newton(model, q0: np.ndarray, free: np.ndarray, **options) -> SolveResult:
    """Minimise model energy over the DOFs where ``free`` is True, starting from q0.

    model: a ShellModel (energy, gradient, hessian_blocks, block_buffers, face_dofs,
    hinge_dofs, n_dofs, sheet, edge_angle_problem, printed_dofs). options: the fields of
    :class:`NewtonOptions` as keywords.

    Each iteration first factorises the exact Hessian; if it is positive definite the
    Newton step is taken with a backtracking (Armijo) line search, otherwise the
    Levenberg-Marquardt trust region (H + lambda D) with saddle escape takes over.
    ``converged`` is True only if, at the returned state, the gradient test passed, the
    exact Hessian (up to ``stability_shift``) factorised, the Newton step's largest
    position change is below ``step_tolerance`` times the sheet's size and the energy the
    Newton step still promises (half the Newton decrement, -g.d/2) is below
    ``energy_tolerance * max(|E|, 1e-6 |E_start|)``. The last two matter: released sheets start with huge
    misfit forces, so a gradient test relative to the start alone passes in the soft
    valleys of these problems (choice of rolling direction) far from the minimum."""
    return _Newton(model, q0, free, NewtonOptions(**options)).solve()


# what a step tells the outer loop: go to the next iteration, or stop unconverged
_NEXT, _STOP = "next", "stop"


class _Newton:
    """One solve's state (iterate, current Hessian and factor, trust-region shift, counters)
    and its steps: :meth:`_assemble`, :meth:`_newton_step`, :meth:`_lm_step`."""

    def __init__(self, model, q0, free, opts: NewtonOptions):
        self.t_start = time.perf_counter()
        self.model, self.free, self.opts = model, free, opts
        self.q = q0.copy()
        self.scatter = BlockScatter([model.face_dofs, model.hinge_dofs], model.n_dofs, free, upper=True)
        self.contact = getattr(model, "contact", None)
        self.union = PatternUnion() if self.contact is not None else None
        self.solver = SparseSPD(opts.backend)
        self.history = []
        self.timings = dict(assembly=0.0, factorisation=0.0, line_search=0.0, factorisations=0, rejected_steps=0,
                            newton_steps=0, regularised_steps=0)
        self.g_ref = opts.gradient_reference
        self.E_ref = None
        self.reason = MAX_ITERATIONS_REASON
        self.lam = 0.0
        self.lam_known = 0.0        # last shift that made H + lam D positive definite
        self.stable = False
        self.E = self.gnorm = np.inf
        self.fresh = True           # the iterate moved: assemble and factorise anew
        self.v_prev = None
        n = self.n = model.n_vertices
        x0 = q0[:3 * n].reshape(-1, 3)
        self.size = float(np.linalg.norm(x0.max(0) - x0.min(0)))
        self.length_scale = 0.02 * self.size
        is_position = np.zeros(model.n_dofs, bool)
        is_position[:3 * n] = True
        self.pos_free = is_position[free]
        self.step_tol = opts.step_tolerance * self.size
        self.rpath = RotationPath(model.sheet.triangles, n) if opts.rotation_path else None
        # element blocks are written into these buffers (no fresh 100 MB arrays per iteration); the
        # printed relaxation shares them: it runs only after the iteration's blocks are scattered
        self.blocks_out = model.block_buffers()
        self.relax = EdgeAngleRelaxation(model, free, opts.backend) if opts.relax_angles else None
        self.stiff = None
        if opts.relax_printed:
            mask = model.printed_dofs() & free
            if 0 < mask.sum() <= 0.9 * free.sum():
                self.stiff = StiffRegionRelaxation(model, free, mask, opts.backend, buffers=self.blocks_out)
        self.g = self.H = self.D = self.factor = self.tol = None
        self.exact = self.projected = False
        self.floor_steps = 0            # consecutive Newton steps at round-off with |g| above tol
        # contact: per accepted iteration (largest vertex move mm, cuts so far), kept for the last
        # STALL_ITERATIONS and the one before them (whose cut count the window's is counted from)
        self._stall = deque(maxlen=STALL_ITERATIONS + 1)
        self._x_accepted = None

    # --- helpers -----------------------------------------------------------------------
    def _result(self, converged: bool, it: int, energy=None) -> SolveResult:
        if converged:
            return SolveResult(self.q, True, it, energy, self.gnorm, self.reason, True, self.history,
                               _finish(self.timings, self.t_start))
        return SolveResult(self.q, False, it, float(self.E), self.gnorm, self.reason, self.stable, self.history,
                           _finish(self.timings, self.t_start))

    def _stiff_relaxed(self, q):
        t0 = time.perf_counter()
        out = self.stiff(q)
        self.timings["printed_relaxation"] = self.timings.get("printed_relaxation", 0.0) + time.perf_counter() - t0
        self.timings["printed_relaxations"] = self.stiff.calls
        return out

    def _relaxed(self, q, E, max_iterations=None):
        if self.relax is None:
            return q
        t0 = time.perf_counter()
        out = self.relax(q, max(abs(E), 1e-300), max_iterations)
        self.timings["angle_relaxation"] = self.timings.get("angle_relaxation", 0.0) + time.perf_counter() - t0
        self.timings["angle_iterations"] = self.relax.iterations
        return out

    def _energy_scale(self, E):
        """|E|, floored at 1e-6 of the start's energy (or of the energy_reference, if larger) so
        that an equilibrium with E = 0 can converge."""
        return max(abs(E), 1e-6 * max(self.E_ref, self.opts.energy_reference or 0.0))

    def _step_size(self, d_free):
        """Largest position change of a step and the energy it promises, -g.d/2."""
        step = float(np.abs(d_free[self.pos_free]).max()) if self.pos_free.any() else 0.0
        return step, -0.5 * float(self.g @ d_free)

    def _along(self, d):
        """q(alpha) along step d: the rotation-corrected path, or the straight line."""
        q = self.q
        return _path(self.rpath, q, d, self.n, self.free) if self.rpath is not None else (lambda a: q + a * d)

    # --- the iteration -------------------------------------------------------------------
    def solve(self) -> SolveResult:
        self._start()
        it = 0
        if getattr(self, "contact_reason", None):
            self.reason = self.contact_reason
            return self._result(False, 0)
        for it in range(self.opts.max_iterations + 1):
            if self.fresh and not self._assemble():
                break
            if self.exact and self.fresh:
                outcome = self._newton_step(it)
                if outcome == _NEXT:
                    continue
                if outcome == _STOP:
                    break
                if outcome is not None:
                    return outcome
            outcome = self._lm_step(it)
            if outcome == _STOP:
                break
            if outcome != _NEXT:
                return outcome
        return self._result(False, it)

    def _start(self):
        """Relax the start's angles; a start whose angles are inadmissible (|psi| >= 0.49 pi)
        but whose positions are fine (a transferred or smoothed shape) restarts them from 0."""
        model, q = self.model, self.q
        E0 = model.energy(q)
        if not np.isfinite(E0) and self.relax is not None:
            flat = q.copy()
            flat[3 * self.n:][self.relax.free] = 0.0
            E_flat = model.energy(flat)
            if np.isfinite(E_flat):
                q, E0 = flat, E_flat
        if np.isfinite(E0):
            # the start's angles to their minimum (the inner steps end there by themselves): a
            # start with angles that kink it (0 on a curved target, an interpolated mesh) can
            # hold printed triangles at the fold stop, whose cubic the 4 steps after every accepted
            # step do not undo (a refine start: 37,121 -> 23,392 N mm in 4 steps, 16.97 in 50)
            q = self._relaxed(q, E0, START_ANGLE_ITERATIONS)
        self.q = q
        if self.contact is not None:
            self._contact_start()

    def _contact_start(self):
        """Contact: the barrier stiffness from the elastic Hessian's position diagonal at the
        start (once per Contact, shellfem.contact), and the start's admissibility (an
        intersecting start or a support forcing penetration is the solve's reason to stop)."""
        contact, model = self.contact, self.model
        n = self.n
        if contact.kappa == 0.0:
            saved, model.contact = model.contact, None
            try:
                _, _, (Hf, Hh) = model.hessian_blocks(self.q, out=self.blocks_out)
            finally:
                model.contact = saved
            diag = np.zeros(model.n_dofs)
            for blocks, dofs in ((Hf, model.face_dofs), (Hh, model.hinge_dofs)):
                diag += np.bincount(dofs.ravel(), weights=np.diagonal(blocks, axis1=1, axis2=2).ravel(),
                                    minlength=model.n_dofs)
            pos = np.zeros(model.n_dofs, bool)
            pos[:3 * n] = True
            contact.set_stiffness(diag[pos & self.free])
        self.contact_reason = contact.check_start(self.q[:3 * n].reshape(n, 3))

    def _assemble(self) -> bool:
        """Energy, gradient, Hessian and LM metric at the iterate, and the exact Hessian's
        factor (or the hinge-projected one); False if the energy is not finite."""
        opts, timings, scatter = self.opts, self.timings, self.scatter
        t0 = time.perf_counter()
        E, g_all, (Hf, Hh) = self.model.hessian_blocks(self.q, out=self.blocks_out)
        self.E = E
        g = self.g = g_all[self.free]
        H = scatter.matrix([Hf, Hh])
        if self.union is not None:
            Hc = self.model.contact_hessian
            H = self.union.add(H, None if Hc is None else reduce_upper(Hc, scatter.reduced, scatter.n_free))
        self.H = H
        timings["assembly"] += time.perf_counter() - t0
        if not np.isfinite(E):
            self.reason = ("energy is not finite at the start (inverted or over-stretched triangles"
                           + (", or a contact closer than the offset)" if self.contact is not None else ")"))
            return False
        self.gnorm = float(np.linalg.norm(g))
        if self.g_ref is None:
            self.g_ref = self.gnorm
        if self.E_ref is None:
            self.E_ref = abs(E)
        self.tol = max(opts.atol, opts.rtol * self.g_ref)
        self.D = lm_metric(H.diagonal(), self.pos_free, opts.floor)
        # exact Newton first
        t0 = time.perf_counter()
        timings["factorisations"] += 1
        self.projected = False
        try:
            self.factor = self.solver.factor(H, upper=scatter.upper)
            self.exact = True
        except NotPositiveDefinite:
            self.factor, self.exact = None, False
            if self.union is not None and self.model.contact_hessian is not None and self.contact.indefinite_part:
                # the contact blocks projected to PSD (ipctk): a Newton step that cannot decide
                # convergence (the exact Hessian, tried first, gives the quadratic end game: with
                # the projected one the last phase converged linearly, |g| x 0.85 per step)
                Hp = self.union.add(scatter.matrix([Hf, Hh]),
                                    reduce_upper(self.contact.projected_hessian(), scatter.reduced, scatter.n_free))
                self._factor_projected(Hp, "contact_projected_steps")
            if not self.exact and opts.project_hinges:
                Hp = scatter.matrix([Hf, _psd_blocks(Hh)])
                if self.union is not None:
                    Hc = self.contact.projected_hessian()
                    Hp = self.union.add(Hp, None if Hc is None else reduce_upper(Hc, scatter.reduced, scatter.n_free))
                self._factor_projected(Hp, "projected_steps")
        timings["factorisation"] += time.perf_counter() - t0
        return True

    def _factor_projected(self, Hp, counter: str):
        """Factor a projected Hessian Hp as the step's (counted under timings[counter]); the
        state is left as it was if Hp is not positive definite either."""
        self.timings["factorisations"] += 1
        try:
            self.factor = self.solver.factor(Hp, upper=self.scatter.upper)
            self.exact = self.projected = True
            self.timings[counter] = self.timings.get(counter, 0) + 1
        except NotPositiveDefinite:
            pass

    def _accept_newton(self, it, q_try, E_new, a, note):
        self.q = self._relaxed(q_try, E_new)
        self.timings["newton_steps"] += 1
        self.history.append(dict(iteration=it, energy=self.E, gradient_norm=self.gnorm, lam=0.0, step=a))
        if self.opts.callback is not None:
            self.opts.callback(self.history[-1])
        if self.opts.verbose:
            print(f"  newton {it:3d}  E {self.E:.10e}  |g| {self.gnorm:.3e}  Newton step x {note}", flush=True)
        self.lam = 0.0
        self.fresh = True
        return self._monitored()

    def _monitored(self):
        """_NEXT, or _STOP with the monitor's reason when it asks to stop at the new iterate, or
        when a contact solve has stalled (:meth:`_stalled`)."""
        if self.contact is not None and self._stalled():
            return _STOP
        if self.opts.monitor is not None:
            why = self.opts.monitor(self.q)
            if why:
                self.reason = str(why)
                return _STOP
        return _NEXT

    def _stalled(self) -> bool:
        """True (with the reason set) when the last STALL_ITERATIONS accepted iterations together
        moved no vertex by more than STALL_MOVE x the contact offset while the collision filter cut
        at least one trial per iteration: the iterate creeps along layers held at the offset by
        steps the filter cuts to ~1e-10 of the Newton step, lowering the energy by ~1e-5 of itself
        per 10 iterations (stars_tube's coarse level crept like that for 290 iterations, where
        without contact its trust region collapsed after 84)."""
        x = self.model.split(self.q)[0]
        move = 0.0 if self._x_accepted is None else float(np.abs(x - self._x_accepted).max())
        self._x_accepted = x.copy()
        self._stall.append((move, self.timings.get("contact_cuts", 0)))
        if len(self._stall) <= STALL_ITERATIONS:
            return False
        moved = sum(m for m, _ in islice(self._stall, 1, None))
        cuts = self._stall[-1][1] - self._stall[0][1]
        offset = float(getattr(self.contact, "offset", 0.0) or 0.0)
        if cuts >= STALL_ITERATIONS and moved < STALL_MOVE * offset:
            self.reason = (f"stalled against contact: the last {STALL_ITERATIONS} iterations moved the sheet by "
                           f"{moved:.2g} mm in all ({cuts} steps cut by the collision filter), gradient norm "
                           f"{self.gnorm:.3e}")
            return True
        return False

    def _converged(self, it, step, reason, lam=0.0):
        """The converged SolveResult at the current iterate, its last history entry and ``reason``."""
        self.reason = reason
        self.history.append(dict(iteration=it, energy=self.E, gradient_norm=self.gnorm, lam=lam, step=step))
        return self._result(True, it, self.E)

    def _at_gradient_floor(self, it, step, how):
        """Converged: see GRADIENT_FLOOR_FACTOR."""
        return self._converged(it, step, f"Newton step below tolerance at a stable state, the gradient norm at its "
                                         f"round-off floor ({self.gnorm:.2e} N, {how}; tolerance {self.tol:.2e} N)")

    def _newton_step(self, it):
        """The Newton step of a positive definite Hessian with an Armijo line search: a
        converged SolveResult, _NEXT (step taken), _STOP (iteration cap) or None (no
        decrease: fall through to the trust region with this Hessian)."""
        opts, timings, model, free = self.opts, self.timings, self.model, self.free
        q, E, g, gnorm = self.q, self.E, self.g, self.gnorm
        d_free = -self.factor(g)
        step, promise = self._step_size(d_free)
        at_rest = (not self.projected and step <= self.step_tol
                   and promise <= opts.energy_tolerance * self._energy_scale(E))
        if at_rest and gnorm <= self.tol:
            return self._converged(it, step, "gradient norm and Newton step below tolerance at a stable state")
        near_floor = at_rest and gnorm <= GRADIENT_FLOOR_FACTOR * self.tol
        self.floor_steps = self.floor_steps + 1 if near_floor else 0
        if self.floor_steps >= GRADIENT_FLOOR_STEPS:
            return self._at_gradient_floor(it, step, f"over {self.floor_steps} steps")
        if it == opts.max_iterations:
            self.stable = True
            return _STOP
        t0 = time.perf_counter()
        d = np.zeros_like(q)
        d[free] = d_free
        slope = float(g @ d_free)
        a, E_new = 1.0, np.inf
        along = self._along(d)
        if promise <= 1e-13 * max(abs(E), self.E_ref):
            # the decrease is below the energy's round-off, so Armijo cannot see it (it
            # would cut a good step at random): accept the full step if the gradient falls
            q_try = along(1.0)
            E_try = model.trial_energy(q, q_try)
            g_try = model.gradient(q_try)[free] if np.isfinite(E_try) else None
            if np.isfinite(E_try) and float(np.linalg.norm(g_try)) < gnorm:
                timings["line_search"] += time.perf_counter() - t0
                return self._accept_newton(it, q_try, E_try, 1.0, "1 (round-off)")
            if near_floor:
                # the full Newton step, below the step tolerance, does not lower |g| either
                timings["line_search"] += time.perf_counter() - t0
                return self._at_gradient_floor(it, step, "the Newton step does not lower it")
        for _ in range(40):
            q_try = along(a)
            if self.contact is not None:
                # the contact step filter: shorten to the collision-free fraction of the move
                t = model.step_fraction(q, q_try)
                if t < 1.0:
                    timings["contact_cuts"] = timings.get("contact_cuts", 0) + 1
                    a *= min(0.5, max(0.9 * t, 0.01))
                    E_new = np.inf
                    continue
            E_new = model.energy(q_try, below=E + 1e-4 * a * slope)     # Armijo's bound
            if np.isfinite(E_new) and E_new <= E + 1e-4 * a * slope:
                break
            a *= 0.5
        timings["line_search"] += time.perf_counter() - t0
        accepted = np.isfinite(E_new) and E_new <= E + 1e-4 * a * slope and a * step > 1e-14 * self.size
        if accepted and self.stiff is not None and a < 1:
            # the line search had to cut: try twice the step with the printed regions relaxed
            q2, E2 = self._stiff_relaxed(along(2 * a)) if model.step_fraction(q, along(2 * a)) >= 1.0 else (q, np.inf)
            if np.isfinite(E2) and E2 < E_new:
                q_try, E_new, a = q2, E2, 2 * a
        if accepted and a == 1.0 and self._creeping():
            q_try, E_new, a = self._extrapolated(along, q_try, E_new)
        if accepted:
            return self._accept_newton(it, q_try, E_new, a, f"{a:.3g}")
        if not self.projected and gnorm <= self.tol and promise <= 1e3 * opts.energy_tolerance * self._energy_scale(E):
            # at round-off: no decrease is measurable any more along the Newton step
            self.reason = "gradient norm below tolerance at a stable state (energy at round-off)"
            return self._result(True, it, E)
        self.exact = False      # fall through to the trust region with this Hessian
        self.lam = max(self.lam, 1e-8)
        return None

    def _creeping(self) -> bool:
        """True when the last CREEP_WINDOW accepted iterations were full Newton steps that
        lowered the energy by less than CREEP_ENERGY of itself and the gradient norm did not
        fall below half of its value at the window's start (module docstring: creep)."""
        window = self.history[-CREEP_WINDOW:]      # each entry: the iterate a step started from
        if len(window) < CREEP_WINDOW or any(e["lam"] != 0.0 or e["step"] != 1.0 for e in window):
            return False
        fell = window[0]["energy"] - self.E
        return (0.0 <= fell <= CREEP_ENERGY * abs(self.E)
                and self.gnorm >= 0.5 * window[0]["gradient_norm"])

    def _extrapolated(self, along, q_try, E_new):
        """The accepted full step extrapolated along its path by 2, 4, ... (<= CREEP_MAX_FACTOR)
        while the energy falls and (under contact) the straight move from the iterate is free of
        contact: (q, E, factor)."""
        t0 = time.perf_counter()
        best = (q_try, E_new, 1.0)
        b = 2.0
        while b <= CREEP_MAX_FACTOR:
            qb = along(b)
            Eb = self.model.trial_energy(self.q, qb, below=best[1])
            if not (np.isfinite(Eb) and Eb < best[1]):
                break
            best = (qb, Eb, b)
            b *= 2.0
        self.timings["creep_extrapolations"] = self.timings.get("creep_extrapolations", 0) + (best[2] > 1.0)
        self.timings["line_search"] += time.perf_counter() - t0
        return best

    def _lm_factor(self):
        """Factor of H + lam D, raising lam until positive definite: (factor or None, lam)."""
        timings = self.timings
        t0 = time.perf_counter()
        factor = None
        lam_try = max(self.lam, LAM_MIN, self.lam_known / 8.0 if self.fresh and self.lam == 0.0 else 0.0)
        for _ in range(60):
            timings["factorisations"] += 1
            try:
                factor = self.solver.factor(self.H, shift=lam_try * self.D, upper=self.scatter.upper)
                break
            except NotPositiveDefinite:
                lam_try = max(8.0 * lam_try, 1e-10)
        if factor is not None:
            self.lam_known = lam_try
        timings["factorisation"] += time.perf_counter() - t0
        return factor, lam_try

    def _lm_step(self, it):
        """A Levenberg-Marquardt step (with saddle escape and the printed relaxation): a
        converged SolveResult, _NEXT (step taken or rejected) or _STOP."""
        opts, timings, model, free = self.opts, self.timings, self.model, self.free
        q, E, g, gnorm, H, D = self.q, self.E, self.g, self.gnorm, self.H, self.D
        self.floor_steps = 0
        factor, lam_try = self._lm_factor()
        self.factor = factor
        if factor is None:
            self.reason = "Hessian could not be regularised to positive definite"
            return _STOP
        self.stable = stable = lam_try <= opts.stability_shift
        if gnorm <= self.tol and stable:
            # near-neutral modes below what the factorisation resolves (pencil eigenvalues
            # ~ -1e-11, e.g. the twist of a narrow strip): check the step as for Newton
            d_free = -factor(g)
            step, promise = self._step_size(d_free)
            if step <= self.step_tol and promise <= opts.energy_tolerance * self._energy_scale(E):
                return self._converged(it, step, "gradient norm and step below tolerance at a stable state", lam_try)
        if it == opts.max_iterations:
            return _STOP
        self.lam = lam_try
        d_free = -factor(g)
        Hd = symmetric_matvec(H, d_free)
        pred = -(g @ d_free + 0.5 * d_free @ Hd)
        d = np.zeros_like(q)
        d[free] = d_free
        t0 = time.perf_counter()
        q_new = _path(self.rpath, q, d, self.n, free)(1.0) if self.rpath is not None else q + d
        blocked = self.contact is not None and model.step_fraction(q, q_new) < 1.0
        # the bound it is judged by: the printed relaxation takes trials up to E + STIFF_TRIAL_RISE pred
        below = E + STIFF_TRIAL_RISE * pred if (self.stiff is not None and pred > 0) else E
        E_new = np.inf if blocked else model.energy(q_new, below=below)
        timings["line_search"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        if not stable and self.fresh and ((not (np.isfinite(E_new) and E_new < E) and not blocked) or lam_try > 1e-2):
            # strongly indefinite, or the regularised step fails: also try the direction of
            # most negative curvature (saddle escape). Not on every indefinite step: local
            # near-neutral modes (fabric flaps at free corners) make that search cost more
            # than it gains; nor where the step fails only because it would pass through a
            # contact (a shorter step is the remedy, not another direction: on the 50 x 35 mm
            # stars tube these searches were a third of the solve).
            timings["negative_curvature_searches"] = timings.get("negative_curvature_searches", 0) + 1
            v_nc, E_nc = _negative_curvature_step(model, q, free, H, D, g, factor, E, self.v_prev,
                                                  self.length_scale)
            if v_nc is not None:
                self.v_prev = v_nc[free]
                if E_nc < min(E_new, E):
                    E_new = E_nc
                    q_new = q + v_nc
                    pred = E - E_nc
                    timings["negative_curvature_steps"] = timings.get("negative_curvature_steps", 0) + 1
            timings["negative_curvature_search"] = timings.get("negative_curvature_search", 0.0) + time.perf_counter() - t0
        actual = E - E_new
        rho = actual / pred if pred > 0 else (1.0 if actual > 0 else -1.0)
        if self.stiff is not None and rho < 0.75 and pred > 0 and np.isfinite(E_new) and E_new < E + STIFF_TRIAL_RISE * pred:
            # the step strained the stiff printed regions more than the model foresaw: relax
            # them at the trial point before judging it (rho capped at 1: the model stays the
            # model of the unrelaxed step)
            q2, E2 = self._stiff_relaxed(q_new)
            if E2 < E_new:
                q_new, E_new = q2, E2
                actual = E - E_new
                rho = min(actual / pred, 1.0)
        if not np.isfinite(E_new) or actual <= 0 or rho < 1e-4:
            # reject: shrink the trust region and re-solve with the same Hessian
            timings["rejected_steps"] += 1
            self.lam = max(8.0 * self.lam, 1e-8)
            self.fresh = False
            if self.lam > 1e12:
                self.reason = f"no decrease possible (trust region collapsed) with gradient norm {gnorm:.3e}"
                return _STOP
            return _NEXT
        self.q = self._relaxed(q_new, E_new)
        self.fresh = True
        timings["regularised_steps"] += 1
        lam = self.lam
        self.history.append(dict(iteration=it, energy=E, gradient_norm=gnorm, lam=lam, rho=rho))
        if opts.callback is not None:
            opts.callback(self.history[-1])
        if opts.verbose:
            print(f"  newton {it:3d}  E {E:.10e}  |g| {gnorm:.3e}  lambda {lam:.1e}  rho {rho:.2f}", flush=True)
        if rho > 0.75:
            self.lam = lam / 4 if lam > LAM_MIN else 0.0
        elif rho < 0.25:
            self.lam = max(4.0 * lam, 1e-8)
        return self._monitored()


def _negative_curvature_step(model, q, free, H, D, g, factor, E, v_prev, length_scale, n_inverse=12):
    """Inverse iteration on the pencil (H, D) with the factor of H + lam D gives the most
    negative curvature direction v; search along -sign(g.v) v for the lowest energy.
    Returns (full-length step, its energy) or (None, inf) if no negative curvature."""
    rng = np.random.default_rng(0)
    v = v_prev.copy() if v_prev is not None and len(v_prev) == len(g) else rng.standard_normal(len(g))
    for _ in range(n_inverse):
        v = factor(D * v)
        nv = np.sqrt(v @ (D * v))
        if not np.isfinite(nv) or nv == 0:
            return None, np.inf
        v /= nv
    mu = v @ symmetric_matvec(H, v)
    if mu >= 0:
        return None, np.inf
    n = model.n_vertices
    full = np.zeros_like(q)
    full[free] = v
    vmax = np.abs(full[:3 * n]).max()
    if vmax == 0:
        return None, np.inf
    full *= (length_scale / vmax) * (-1.0 if g @ v > 0 else 1.0)
    best_a, best_E = 0.0, E
    # under contact one collision check of the whole search length: the steps within its
    # collision-free fraction need none, those beyond it are inadmissible (skipped unevaluated)
    t_free = model.step_fraction(q, q + full)          # 1.0 without contact
    a = 1.0
    for _ in range(20):             # shrink until the energy decreases
        if a > t_free:
            a *= 0.5
            continue
        Ea = model.energy(q + a * full, below=best_E)
        if np.isfinite(Ea) and Ea < best_E:
            best_a, best_E = a, Ea
            break
        a *= 0.5
    if best_a == 0.0:
        return None, np.inf
    for _ in range(6):              # then expand while it keeps decreasing
        Ea = (model.energy(q + 2 * best_a * full, below=best_E) if 2 * best_a <= t_free
              else model.trial_energy(q, q + 2 * best_a * full, below=best_E))
        if not (np.isfinite(Ea) and Ea < best_E):
            break
        best_a, best_E = 2 * best_a, Ea
    return best_a * full, best_E


def _path(rpath, q, d, n, free):
    """q(alpha): positions along the rotation-corrected path of d, other DOFs linear. The
    path is moved rigidly so that the fixed position DOFs (gauge, supports) keep their values
    as well as a rigid motion allows; any remainder is then imposed."""
    x, dx = q[:3 * n].reshape(-1, 3), d[:3 * n].reshape(-1, 3)
    omega, at = rpath.step(x, dx)
    if not np.all(np.isfinite(omega)) or float(np.abs(omega).max()) < 1e-3:
        return lambda a: q + a * d          # small rotations: the straight line is as good (and exact to round-off)
    fixed = ~free
    fpos = np.flatnonzero(fixed[:3 * n])
    fv, fc = fpos // 3, fpos % 3

    def along(a):
        out = q + a * d
        y = at(a)
        if len(fpos):
            target = q[fpos]
            for _ in range(4):                   # Gauss-Newton on a rigid motion (w, t)
                c = y.mean(axis=0)
                r = y[fv, fc] - target
                if np.abs(r).max() < 1e-12:
                    break
                J = np.zeros((len(fpos), 6))
                for k in range(3):               # d(w x (y - c))/dw_k = e_k x (y - c)
                    J[:, k] = np.cross(np.eye(3)[k], y[fv] - c)[np.arange(len(fv)), fc]
                J[np.arange(len(fpos)), 3 + fc] = 1.0
                p = np.linalg.lstsq(J, -r, rcond=None)[0]
                y = rotate((y - c)[None], p[None, :3])[0] + c + p[3:]
        out[:3 * n] = y.ravel()
        out[fixed] = q[fixed]
        return out
    return along


def _finish(timings, t_start):
    timings = dict(timings)
    timings["total"] = time.perf_counter() - t_start
    return timings
