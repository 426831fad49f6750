"""Newton's method for the shell's total energy, robust to indefinite Hessians.

Each iteration assembles the exact Hessian H over the free DOFs and solves
(H + lambda D) d = -g with a sparse Cholesky factorisation (:func:`default_backend`: MKL
PARDISO, else CHOLMOD, else SciPy's SuperLU; symbolic analysis once per mesh), D = |diag H| floored
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
positions frozen (:class:`EdgeAngleRelaxation`, a nonlinear elimination of the angles that
costs ~1/20 of an outer iteration): star sheets 30 x 20 mm 68 / 62 -> 51 / 50 iterations,
40 x 30 mm 216 / 251 / 248 -> 182 / 144 / 181 (seeds 0 / 1 / 2), both with metric floor 0.
Trial points that strain the stiff printed regions (a cut Newton step doubled, LM steps with a
poor model ratio) are first relaxed over the printed regions' DOFs (:class:`StiffRegionRelaxation`):
85 x 60 benchmark 248 -> 80 iterations.

Newton steps follow a rotation-corrected curve instead of a straight line when the sheet
rotates (shellfem.corotational); optionally an indefinite Hessian is first retried with its
hinge (dihedral-angle) blocks projected to positive semi-definite before LM takes over.

Convergence: ||grad||_2 over the free DOFs <= max(atol, rtol * gradient_reference) (the
reference defaults to the gradient norm at the start) AND the exact Hessian (lambda = 0)
factorised, so the state is a local minimum, not a saddle. Anything else is reported as
not converged, with the reason.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from threadpoolctl import threadpool_limits

from shellfem import pardiso
from shellfem.assembly import BlockScatter, symmetric_matvec

try:  # CHOLMOD: ~2x faster than SuperLU here and it reports non-definiteness (toolchain.md)
    # (PARDISO, shellfem.pardiso, is 5x faster again and is preferred when MKL is installed)
    from sksparse.cholmod import CholmodNotPositiveDefiniteError, analyze
    HAVE_CHOLMOD = True
except Exception:  # pragma: no cover - exercised on machines without scikit-sparse
    HAVE_CHOLMOD = False

    class CholmodNotPositiveDefiniteError(Exception):
        pass


#: Default trust-region metric floor (see :func:`lm_metric`); [solver] metric_floor = 0 gives
#: plain Marquardt scaling.
DEFAULT_METRIC_FLOOR = 10.0


MAX_ITERATIONS_REASON = "maximum number of iterations reached"


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
    mm while the stiff plastic DOFs keep their own scale. Floors 0.1 / 1 / 10 / 30 / 100 / 1000
    on a 40 x 30 mm star sheet: 222 / 187 / 175 / 179 / 199 / 249 iterations (session 6).
    With the edge-angle relaxation (the default since session 7), floor 0 -> 10, single-threaded:
    star sheets 30 x 20 mm 51 / 50 -> 46 / 43 (seeds 0 / 1), 40 x 30 mm 182 / 144 -> 117 / 120,
    85 x 60 benchmark 310 -> 236; gallery ribbons 87 -> 53, ortho_0 33 -> 35, ortho_90 37 -> 31,
    half annulus 170 -> 160; examples/ribbons.toml 150 (floor 10). Without the relaxation the
    floor made ortho_90 creep (not converged in 1000), which kept it opt-in until then."""
    D = np.abs(np.asarray(diag, float))
    D = D + 1e-8 * max(float(D.mean()), 1e-300) if len(D) else D
    if floor > 0:
        for kind in (is_position, ~is_position):
            if kind.any():
                D[kind] = np.maximum(D[kind], floor * float(np.median(D[kind])))
    return D


class NotPositiveDefinite(Exception):
    pass


def default_backend() -> str:
    """The fastest sparse Cholesky here: MKL PARDISO (shellfem.pardiso; 5x CHOLMOD on the
    benchmark's Hessian), else CHOLMOD (scikit-sparse), else SciPy's SuperLU."""
    if pardiso.available():
        return "pardiso"
    return "cholmod" if HAVE_CHOLMOD else "superlu"


def _same_frozen(a: np.ndarray, b: np.ndarray) -> bool:
    """a and b are read-only views of the same memory (so equal, now and later)."""
    return (not a.flags.writeable and not b.flags.writeable and a.shape == b.shape and a.dtype == b.dtype
            and a.ctypes.data == b.ctypes.data and a.strides == b.strides)


class SparseSPD:
    """Factorise SPD matrices; raise NotPositiveDefinite. The symbolic analysis (ordering) is
    kept while the sparsity pattern stays the same (as in a Newton loop).

    backend: "auto" (:func:`default_backend`), "pardiso", "cholmod" or "superlu"."""

    def __init__(self, backend: str = "auto"):
        self.backend = default_backend() if backend == "auto" else backend
        if self.backend not in ("pardiso", "cholmod", "superlu"):
            raise ValueError(f"unknown sparse solver backend {backend!r}")
        if self.backend == "pardiso" and not pardiso.available():
            raise ValueError("sparse solver backend 'pardiso' needs MKL (pip install mkl)")
        if self.backend == "cholmod" and not HAVE_CHOLMOD:
            raise ValueError("sparse solver backend 'cholmod' needs scikit-sparse")
        self._symbolic = None
        self._pattern = None

    def _same_pattern(self, A) -> bool:
        """True if A (CSR or CSC) has the pattern of the last analysis; else remember A's."""
        p = self._pattern
        if p is not None and p[0] == A.shape and _same_frozen(p[1], A.indptr) and _same_frozen(p[2], A.indices):
            return True           # the same read-only index arrays (BlockScatter's matrices)
        if (p is not None and p[0] == A.shape and len(p[2]) == len(A.indices) and np.array_equal(p[1], A.indptr)
                and np.array_equal(p[2], A.indices)):
            return True
        shared = not (A.indptr.flags.writeable or A.indices.flags.writeable)
        self._pattern = (A.shape, A.indptr if shared else A.indptr.copy(), A.indices if shared else A.indices.copy())
        return False

    def factor(self, A: sp.csr_matrix, shift=None, upper: bool = False):
        """A solve function for A + diag(shift) (shift: (n,) array, scalar or None). upper:
        A holds only the upper triangle of the symmetric matrix (BlockScatter(upper=True))."""
        if self.backend == "pardiso":     # reads the upper triangle either way
            A = A if isinstance(A, sp.csr_matrix) else sp.csr_matrix(A)
            if not A.has_canonical_format:
                A = A.copy()
                A.sum_duplicates()
            if not self._same_pattern(A):
                self._symbolic = pardiso.PardisoCholesky(A)
            try:
                self._symbolic.factor(A.data, shift)
            except pardiso.ZeroPivot as e:
                raise NotPositiveDefinite(str(e)) from None
            return self._symbolic.solve
        if upper:
            if self.backend == "cholmod":     # CHOLMOD reads the lower triangle of a CSC matrix
                A = sp.csc_matrix((A.data, A.indices, A.indptr), shape=A.shape)
            else:
                A = A + sp.triu(A, k=1, format="csr").T
        if shift is not None:
            A = A + sp.diags(np.broadcast_to(shift, A.shape[0]))
        A = A.tocsc()
        if self.backend == "cholmod":
            if not self._same_pattern(A):
                self._symbolic = analyze(A, mode="supernodal", ordering_method="metis")
            try:
                f = self._symbolic.cholesky(A)
            except CholmodNotPositiveDefiniteError as e:
                raise NotPositiveDefinite(str(e)) from None
            return f
        # SuperLU has no definiteness test: check the pivots' signs via the diagonal of U
        lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options=dict(SymmetricMode=True))
        d = lu.U.diagonal()
        if np.any(d <= 0) or not np.all(np.isfinite(d)):
            raise NotPositiveDefinite("non-positive pivot")
        return lu.solve


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


# numpy's OpenBLAS threads busy-wait after its many small batched products and take the
# second core from the compiled kernels and PARDISO: one OpenBLAS thread while solving
# (85 x 60 benchmark, seed 0: 90 -> 75 s, same 80 iterations); restored on return
@threadpool_limits.wrap(limits={"openblas": 1})
def newton(model, q0: np.ndarray, free: np.ndarray, *, rtol: float = 1e-8, atol: float = 1e-10,
           max_iterations: int = 300, backend: str = "auto", verbose: bool = False,
           gradient_reference: float | None = None, stability_shift: float = 1e-6,
           step_tolerance: float = 1e-7, energy_tolerance: float = 1e-11, rotation_path: bool = True,
           project_hinges: bool = False, metric_floor: float = DEFAULT_METRIC_FLOOR,
           relax_angles: bool = True, relax_printed: bool = True) -> SolveResult:
    """Minimise model energy over the DOFs where ``free`` is True, starting from q0.

    model: a ShellModel (energy, gradient, hessian_blocks, face_dofs, hinge_dofs, n_dofs).
    Each iteration first factorises the exact Hessian; if it is positive definite the
    Newton step is taken with a backtracking (Armijo) line search, otherwise the
    Levenberg-Marquardt trust region (H + lambda D) with saddle escape takes over.
    ``converged`` is True only if, at the returned state, the gradient test passed, the
    exact Hessian (up to ``stability_shift``) factorised, the Newton step's largest
    position change is below ``step_tolerance`` times the sheet's size and the energy the
    Newton step still promises (half the Newton decrement, -g.d/2) is below
    ``energy_tolerance * max(|E|, 1e-6 |E_start|)``. The last two matter: released sheets start with huge
    misfit forces, so a gradient test relative to the start alone passes in the soft
    valleys of these problems (choice of rolling direction) far from the minimum.

    rotation_path: steps whose triangles rotate by more than 1e-3 rad follow the
    rotation-corrected curve of :mod:`shellfem.corotational` (tangent to the step, each
    triangle rotated rigidly) instead of the straight line, which stretches rotating regions
    and forces short steps (free narrow strip: 60 -> 19 iterations; 40 x 30 mm star sheet
    334 -> 215). project_hinges (off by default): when H is indefinite, first try the
    Hessian with each hinge's dihedral-angle block (moment x d2(phi)) projected to PSD: these
    blocks are where the indefiniteness sits (bare-fabric flaps hinged to a printed triangle
    carrying a large moment). Measured: strip 19 -> 15 iterations and 40 x 30 star sheet
    215 -> 206, but 30 x 20 star sheet 68 -> 91 and a ribbon patch 117 -> 186, so not default.
    Such steps never decide convergence (the exact H must factorise for that).

    relax_angles (default on): re-minimise the free edge angles at frozen positions at the
    start and after every accepted step (:class:`EdgeAngleRelaxation`); it never raises the
    energy and never decides convergence.

    relax_printed (default on): trial points of the outer iteration - twice the step the Newton
    line search accepted when it had to cut, and LM steps whose energy falls short of the
    model (rho < 0.75) - are first relaxed over the printed regions' DOFs
    (:class:`StiffRegionRelaxation`; off when the printed DOFs are most of the sheet's, e.g. a
    strip printed all over). 85 x 60 benchmark seeds 0 / 1 / 2 / 3: 248 / 137 / 229 / 215 ->
    80 / 126 / 84 / 69 iterations (seed 0: 239 -> 139 s; 118 s with the upper-triangle assembly).

    metric_floor: the trust-region metric D of H + lam D is |H_ii| floored at this multiple of
    the median |H_ii| of its DOF kind (positions, edge angles); see :func:`lm_metric`. Default
    10 (DEFAULT_METRIC_FLOOR); 0 gives plain Marquardt scaling, D = |diag H|."""
    t_start = time.perf_counter()
    q = q0.copy()
    scatter = BlockScatter([model.face_dofs, model.hinge_dofs], model.n_dofs, free, upper=True)
    solver = SparseSPD(backend)
    history = []
    timings = dict(assembly=0.0, factorisation=0.0, line_search=0.0, factorisations=0, rejected_steps=0,
                   newton_steps=0, regularised_steps=0)
    g_ref = gradient_reference
    E_ref = None
    reason = MAX_ITERATIONS_REASON
    lam, lam_min = 0.0, 1e-10
    lam_known = 0.0        # last shift that made H + lam D positive definite
    stable = False
    E = gnorm = np.inf
    it = 0
    fresh = True
    v_prev = None
    n = model.n_vertices
    x0 = q0[:3 * n].reshape(-1, 3)
    size = float(np.linalg.norm(x0.max(0) - x0.min(0)))
    length_scale = 0.02 * size
    is_position = np.zeros(model.n_dofs, bool)
    is_position[:3 * n] = True
    pos_free = is_position[free]
    step_tol = step_tolerance * size
    rpath = None
    if rotation_path and hasattr(model, "sheet"):
        from shellfem.corotational import RotationPath
        rpath = RotationPath(model.sheet.triangles, n)

    # element blocks are written into these buffers (no fresh 100 MB arrays per iteration); the
    # printed relaxation shares them: it runs only after the iteration's blocks are scattered
    blocks_out = model.block_buffers() if hasattr(model, "block_buffers") else None
    relax = EdgeAngleRelaxation(model, free, backend) if relax_angles and hasattr(model, "edge_angle_problem") else None
    stiff = None
    if relax_printed and hasattr(model, "printed_dofs"):
        mask = model.printed_dofs() & free
        if 0 < mask.sum() <= 0.9 * free.sum():
            stiff = StiffRegionRelaxation(model, free, mask, backend, buffers=blocks_out)

    def _stiff_relaxed(q):
        t0 = time.perf_counter()
        out = stiff(q)
        timings["printed_relaxation"] = timings.get("printed_relaxation", 0.0) + time.perf_counter() - t0
        timings["printed_relaxations"] = stiff.calls
        return out

    def _relaxed(q, E):
        if relax is None:
            return q
        t0 = time.perf_counter()
        out = relax(q, max(abs(E), 1e-300))
        timings["angle_relaxation"] = timings.get("angle_relaxation", 0.0) + time.perf_counter() - t0
        timings["angle_iterations"] = relax.iterations
        return out

    def _energy_scale(E):
        """|E|, floored at 1e-6 of the start's energy so that an equilibrium with E = 0 can converge."""
        return max(abs(E), 1e-6 * E_ref)

    def _step_size(d_free):
        """Largest position change of a step and the energy it promises, -g.d/2."""
        step = float(np.abs(d_free[pos_free]).max()) if pos_free.any() else 0.0
        return step, -0.5 * float(g @ d_free)

    E0 = model.energy(q)
    if not np.isfinite(E0) and relax is not None:
        # a start whose angles are inadmissible (|psi| >= 0.49 pi) but whose positions are
        # fine, e.g. a transferred or smoothed shape: the relaxation re-solves the angles from 0
        flat = q.copy()
        flat[3 * n:][relax.free] = 0.0
        E_flat = model.energy(flat)
        if np.isfinite(E_flat):
            q, E0 = flat, E_flat
    if np.isfinite(E0):
        q = _relaxed(q, E0)
    for it in range(max_iterations + 1):
        if fresh:
            t0 = time.perf_counter()
            E, g_all, (Hf, Hh) = model.hessian_blocks(q, out=blocks_out)
            g = g_all[free]
            H = scatter.matrix([Hf, Hh])
            timings["assembly"] += time.perf_counter() - t0
            if not np.isfinite(E):
                reason = "energy is not finite at the start (inverted or over-stretched triangles)"
                break
            gnorm = float(np.linalg.norm(g))
            if g_ref is None:
                g_ref = gnorm
            if E_ref is None:
                E_ref = abs(E)
            tol = max(atol, rtol * g_ref)
            D = lm_metric(H.diagonal(), pos_free, metric_floor)
            # exact Newton first
            t0 = time.perf_counter()
            timings["factorisations"] += 1
            projected = False
            try:
                factor = solver.factor(H, upper=scatter.upper)
                exact = True
            except NotPositiveDefinite:
                factor, exact = None, False
                if project_hinges:
                    Hp = scatter.matrix([Hf, _psd_blocks(Hh)])
                    timings["factorisations"] += 1
                    try:
                        factor = solver.factor(Hp, upper=scatter.upper)
                        exact = projected = True
                        timings["projected_steps"] = timings.get("projected_steps", 0) + 1
                    except NotPositiveDefinite:
                        pass
            timings["factorisation"] += time.perf_counter() - t0
        if exact and fresh:
            d_free = -factor(g)
            step, promise = _step_size(d_free)
            if not projected and gnorm <= tol and step <= step_tol and promise <= energy_tolerance * _energy_scale(E):
                reason = "gradient norm and Newton step below tolerance at a stable state"
                history.append(dict(iteration=it, energy=E, gradient_norm=gnorm, lam=0.0, step=step))
                return SolveResult(q, True, it, E, gnorm, reason, True, history, _finish(timings, t_start))
            if it == max_iterations:
                stable = True
                break
            t0 = time.perf_counter()
            d = np.zeros_like(q)
            d[free] = d_free
            slope = float(g @ d_free)
            a, E_new = 1.0, np.inf
            along = _path(rpath, q, d, n, free) if rpath is not None else (lambda a: q + a * d)
            if promise <= 1e-13 * max(abs(E), E_ref):
                # the decrease is below the energy's round-off, so Armijo cannot see it (it
                # would cut a good step at random): accept the full step if the gradient falls
                q_try = along(1.0)
                E_try, g_try = model.energy(q_try), model.gradient(q_try)[free]
                if np.isfinite(E_try) and float(np.linalg.norm(g_try)) < gnorm:
                    timings["line_search"] += time.perf_counter() - t0
                    q = _relaxed(q_try, E_try)
                    timings["newton_steps"] += 1
                    history.append(dict(iteration=it, energy=E, gradient_norm=gnorm, lam=0.0, step=1.0))
                    if verbose:
                        print(f"  newton {it:3d}  E {E:.10e}  |g| {gnorm:.3e}  Newton step x 1 (round-off)", flush=True)
                    lam = 0.0
                    fresh = True
                    continue
            for _ in range(40):
                q_try = along(a)
                E_new = model.energy(q_try)
                if np.isfinite(E_new) and E_new <= E + 1e-4 * a * slope:
                    break
                a *= 0.5
            timings["line_search"] += time.perf_counter() - t0
            accepted = np.isfinite(E_new) and E_new <= E + 1e-4 * a * slope and a * step > 1e-14 * size
            if accepted and stiff is not None and a < 1:
                # the line search had to cut: try twice the step with the printed regions relaxed
                q2, E2 = _stiff_relaxed(along(2 * a))
                if np.isfinite(E2) and E2 < E_new:
                    q_try, E_new, a = q2, E2, 2 * a
            if accepted:
                q = _relaxed(q_try, E_new)
                timings["newton_steps"] += 1
                history.append(dict(iteration=it, energy=E, gradient_norm=gnorm, lam=0.0, step=a))
                if verbose:
                    print(f"  newton {it:3d}  E {E:.10e}  |g| {gnorm:.3e}  Newton step x {a:.3g}", flush=True)
                lam = 0.0
                fresh = True
                continue
            if not projected and gnorm <= tol and promise <= 1e3 * energy_tolerance * _energy_scale(E):
                # at round-off: no decrease is measurable any more along the Newton step
                reason = "gradient norm below tolerance at a stable state (energy at round-off)"
                return SolveResult(q, True, it, E, gnorm, reason, True, history, _finish(timings, t_start))
            exact = False      # fall through to the trust region with this Hessian
            lam = max(lam, 1e-8)
        # Levenberg-Marquardt: factorise H + lam D, raising lam until positive definite
        t0 = time.perf_counter()
        factor = None
        lam_try = max(lam, lam_min, lam_known / 8.0 if fresh and lam == 0.0 else 0.0)
        for _ in range(60):
            timings["factorisations"] += 1
            try:
                factor = solver.factor(H, shift=lam_try * D, upper=scatter.upper)
                break
            except NotPositiveDefinite:
                lam_try = max(8.0 * lam_try, 1e-10)
        if factor is not None:
            lam_known = lam_try
        timings["factorisation"] += time.perf_counter() - t0
        if factor is None:
            reason = "Hessian could not be regularised to positive definite"
            break
        stable = lam_try <= stability_shift
        if gnorm <= tol and stable:
            # near-neutral modes below what the factorisation resolves (pencil eigenvalues
            # ~ -1e-11, e.g. the twist of a narrow strip): check the step as for Newton
            d_free = -factor(g)
            step, promise = _step_size(d_free)
            if step <= step_tol and promise <= energy_tolerance * _energy_scale(E):
                reason = "gradient norm and step below tolerance at a stable state"
                history.append(dict(iteration=it, energy=E, gradient_norm=gnorm, lam=lam_try, step=step))
                return SolveResult(q, True, it, E, gnorm, reason, True, history, _finish(timings, t_start))
        if it == max_iterations:
            break
        lam = lam_try
        d_free = -factor(g)
        Hd = symmetric_matvec(H, d_free)
        pred = -(g @ d_free + 0.5 * d_free @ Hd)
        d = np.zeros_like(q)
        d[free] = d_free
        t0 = time.perf_counter()
        q_new = _path(rpath, q, d, n, free)(1.0) if rpath is not None else q + d
        E_new = model.energy(q_new)
        timings["line_search"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        if not stable and fresh and (not (np.isfinite(E_new) and E_new < E) or lam_try > 1e-2):
            # strongly indefinite, or the regularised step fails: also try the direction of
            # most negative curvature (saddle escape). Not on every indefinite step: local
            # near-neutral modes (fabric flaps at free corners) make that search cost more
            # than it gains (40 x 30 mm star sheet: 14 of 71 searches won).
            v_nc, E_nc = _negative_curvature_step(model, q, free, H, D, g, factor, E, v_prev, length_scale)
            if v_nc is not None:
                v_prev = v_nc[free]
                if E_nc < min(E_new, E):
                    d, E_new = v_nc, E_nc
                    q_new = q + v_nc
                    pred = E - E_nc
                    timings["negative_curvature_steps"] = timings.get("negative_curvature_steps", 0) + 1
            timings["negative_curvature_search"] = timings.get("negative_curvature_search", 0.0) + time.perf_counter() - t0
        actual = E - E_new
        rho = actual / pred if pred > 0 else (1.0 if actual > 0 else -1.0)
        if stiff is not None and rho < 0.75 and pred > 0 and np.isfinite(E_new) and E_new < E + 10 * pred:
            # the step strained the stiff printed regions more than the model foresaw: relax
            # them at the trial point before judging it (rho capped at 1: the model stays the
            # model of the unrelaxed step)
            q2, E2 = _stiff_relaxed(q_new)
            if E2 < E_new:
                q_new, E_new = q2, E2
                actual = E - E_new
                rho = min(actual / pred, 1.0)
        if not np.isfinite(E_new) or actual <= 0 or rho < 1e-4:
            # reject: shrink the trust region and re-solve with the same Hessian
            timings["rejected_steps"] += 1
            lam = max(8.0 * lam, 1e-8)
            fresh = False
            if lam > 1e12:
                reason = f"no decrease possible (trust region collapsed) with gradient norm {gnorm:.3e}"
                break
            continue
        q = _relaxed(q_new, E_new)
        fresh = True
        timings["regularised_steps"] += 1
        history.append(dict(iteration=it, energy=E, gradient_norm=gnorm, lam=lam, rho=rho))
        if verbose:
            print(f"  newton {it:3d}  E {E:.10e}  |g| {gnorm:.3e}  lambda {lam:.1e}  rho {rho:.2f}", flush=True)
        if rho > 0.75:
            lam = lam / 4 if lam > lam_min else 0.0
        elif rho < 0.25:
            lam = max(4.0 * lam, 1e-8)
    return SolveResult(q, False, it, float(E), gnorm, reason, stable, history, _finish(timings, t_start))


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

    def __call__(self, q, energy_scale: float):
        """q with its free angles relaxed (never with a higher energy)."""
        if not self.free.any():
            return q
        problem = self.model.edge_angle_problem(q)
        theta = q[3 * self.n:].copy()
        E, g_all, blocks = problem.evaluate(theta)
        if not np.isfinite(E):
            return q
        for _ in range(self.max_iterations):
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
                E_try = model.energy(trial)
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
    a = 1.0
    for _ in range(20):             # shrink until the energy decreases
        Ea = model.energy(q + a * full)
        if np.isfinite(Ea) and Ea < best_E:
            best_a, best_E = a, Ea
            break
        a *= 0.5
    if best_a == 0.0:
        return None, np.inf
    for _ in range(6):              # then expand while it keeps decreasing
        Ea = model.energy(q + 2 * best_a * full)
        if not (np.isfinite(Ea) and Ea < best_E):
            break
        best_a, best_E = 2 * best_a, Ea
    return best_a * full, best_E


def _path(rpath, q, d, n, free):
    """q(alpha): positions along the rotation-corrected path of d, other DOFs linear. The
    path is moved rigidly so that the fixed position DOFs (gauge, supports) keep their values
    as well as a rigid motion allows; any remainder is then imposed."""
    from shellfem.corotational import rotate
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
