"""Large-rotation benchmarks (Sze, Liu & Lo 2004) and the solver's honesty."""
import numpy as np
import pytest

from shellfem.layers import QuadraticForm
from shellfem.model import ShellModel
from shellfem.sheet import Sheet
from shellfem.newton import lm_metric, newton

E, H, B = 1.2e6, 0.1, 1.0


def _cantilever(L, nx):
    dx = L / nx
    sh = Sheet.rectangle(L + dx, B, nx + 1, 2)
    sh = Sheet(sh.points - [dx, 0.0], sh.triangles)       # the row x in [-dx, 0] is clamped
    free = np.ones(3 * sh.n_vertices, bool)
    clamp = np.flatnonzero(sh.points[:, 0] <= 1e-9)
    for c in range(3):
        free[3 * clamp + c] = False
    tip = np.flatnonzero(np.abs(sh.points[:, 0] - L) < 1e-9)
    # mid-edge normals of edges inside the clamped row stay on the (flat, held) row: a clamp
    from shellfem.kinematics import build_topology
    edges = build_topology(sh.triangles).edges
    held = (sh.points[edges, 0] <= 1e-9).all(1)
    return sh, np.concatenate([free, ~held]), tip


def _loaded_cantilever():
    """The 10 mm cantilever of 20 elements with the full tip load 4: (model, free dofs, tip)."""
    sh, free_x, tip = _cantilever(10.0, 20)
    M = ShellModel.homogeneous(sh, E, 0.0, H)
    f = np.zeros((sh.n_vertices, 3))
    f[tip, 2] = 4.0 / len(tip)
    M.external_force = f
    return M, free_x, tip


def _path(models, q, free):
    """Load steps, each started from the secant prediction of the last two equilibria."""
    q_prev, out = None, []
    for M in models:
        guess = q if q_prev is None else q + (q - q_prev)
        r = newton(M, guess, free, max_iterations=200)
        assert r.converged, r.reason
        q_prev, q = q, r.q
        out.append((M, r))
    return out


def test_sze_end_moment_rolls_into_a_full_circle():
    """Moment M on the tip of a clamped strip: uniform curvature M/EI. Applied as the
    equivalent natural curvature (identical potential for a uniform moment, nu = 0) on the
    free part; tip (-u, w) within 0.5 % of L at M/M_max = 0.25, 0.5, 1."""
    L, nx = 12.0, 48
    sh, free_x, tip = _cantilever(L, nx)
    EI, Mmax = E * B * H ** 3 / 12, 50 * np.pi / 3
    inside = sh.points[sh.triangles].mean(1)[:, 0] > 0
    models = []
    for frac in np.arange(1, 17) / 16:
        Mk = ShellModel.homogeneous(sh, E, 0.0, H, rest_curvature=[[-frac * Mmax / EI, 0], [0, 0]])
        flat = ShellModel.homogeneous(sh, E, 0.0, H)
        quad = QuadraticForm(sh.n_triangles)
        quad.add_form(Mk.quad, inside)
        quad.add_form(flat.quad, ~inside)
        Mk.quad = quad
        models.append(Mk)
    free = free_x
    results = _path(models, models[0].initial_state(), free)
    expected = {4: (4.361, 7.639), 8: (12.000, 7.639), 16: (12.000, 0.000)}
    for k, (u_ref, w_ref) in expected.items():
        M, r = results[k - 1]
        x = M.split(r.q)[0]
        u, w = L - x[tip, 0].mean(), abs(x[tip, 2].mean())
        assert abs(u - u_ref) < 0.005 * L and abs(w - w_ref) < 0.005 * L, (k, u, w)


def test_sze_end_shear_cantilever():
    """Transverse tip load P_max = 4 on L = 10: tip (-u, w) = (3.289, 6.700) (Sze et al. 2004).
    Measured with 40 elements: (3.397, ...); the clamp (one held row of triangles) adds
    about half an element of effective length, hence 1.5 % of L here."""
    L, nx = 10.0, 40
    sh, free_x, tip = _cantilever(L, nx)
    models = []
    for frac in np.arange(1, 9) / 8:
        Mk = ShellModel.homogeneous(sh, E, 0.0, H)
        f = np.zeros((sh.n_vertices, 3))
        f[tip, 2] = 4.0 * frac / len(tip)
        Mk.external_force = f
        models.append(Mk)
    free = free_x
    M, r = _path(models, models[0].initial_state(), free)[-1]
    x = M.split(r.q)[0]
    u, w = L - x[tip, 0].mean(), x[tip, 2].mean()
    assert u == pytest.approx(3.289, abs=0.015 * L)
    assert w == pytest.approx(6.700, abs=0.015 * L)


def test_iteration_cap_is_reported_as_not_converged():
    M, free_x, tip = _loaded_cantilever()
    r = newton(M, M.initial_state(), free_x, max_iterations=2)
    assert not r.converged
    assert "maximum" in r.reason


def test_a_gradient_at_its_round_off_floor_just_above_the_tolerance_is_converged():
    """Exact Newton steps below the step tolerance that leave |g| at its round-off floor, just
    above a tolerance set too tight, end the solve as converged with that reason (before, such a
    solve ran on into a collapsed trust region); a floor far above the tolerance does not."""
    from shellfem.newton import GRADIENT_FLOOR_FACTOR
    M, free_x, tip = _loaded_cantilever()
    r0 = newton(M, M.initial_state(), free_x, max_iterations=200)
    assert r0.converged
    # the floor: the gradient norms of Newton steps from the converged state, with no tolerance to reach
    probe = newton(M, r0.q, free_x, max_iterations=12, atol=1e-300, rtol=0.0)
    assert not probe.converged
    floor = min(h["gradient_norm"] for h in probe.history)
    assert 0 < floor < 1e-6
    r = newton(M, r0.q, free_x, max_iterations=50, atol=0.5 * floor, rtol=0.0)
    assert r.converged and "round-off floor" in r.reason, r.reason
    assert np.abs(M.split(r.q)[0] - M.split(r0.q)[0]).max() < 1e-9
    far = newton(M, r0.q, free_x, max_iterations=12, atol=floor / (4 * GRADIENT_FLOOR_FACTOR), rtol=0.0)
    assert not far.converged


def test_a_monitor_stops_the_solve_unconverged_with_its_reason():
    """The monitor sees each accepted iterate; the first non-empty answer ends the solve there
    (not converged, that reason, the iterate it saw returned). Without a stop the solve is the
    plain one."""
    M, free_x, tip = _loaded_cantilever()
    seen = []

    def monitor(q):
        seen.append(q.copy())
        return "tip past 1 mm" if M.split(q)[0][tip, 2].max() > 1.0 else None

    r = newton(M, M.initial_state(), free_x, max_iterations=200, monitor=monitor)
    plain = newton(M, M.initial_state(), free_x, max_iterations=200)
    assert plain.converged and M.split(plain.q)[0][tip, 2].max() > 1.0
    assert not r.converged and r.reason == "tip past 1 mm"
    assert np.array_equal(r.q, seen[-1]) and M.split(r.q)[0][tip, 2].max() > 1.0
    assert all(M.split(q)[0][tip, 2].max() <= 1.0 for q in seen[:-1])
    assert r.iterations < plain.iterations
    quiet = newton(M, M.initial_state(), free_x, max_iterations=200, monitor=lambda q: None)
    assert quiet.converged and quiet.iterations == plain.iterations and np.allclose(quiet.q, plain.q, atol=1e-12)


def test_lm_metric_floors_each_dof_kind_at_its_own_median():
    diag = np.array([1.0, 2.0, 3.0, 1000.0, -0.5, 0.01, 0.02, 0.03])
    pos = np.array([True] * 5 + [False] * 3)
    plain = lm_metric(diag, pos, floor=0.0)
    shift = 1e-8 * np.abs(diag).mean()
    assert np.allclose(plain, np.abs(diag) + shift, rtol=0, atol=1e-15)
    D = lm_metric(diag, pos, floor=10.0)
    med_pos = np.median(np.abs(diag[:5]) + shift)           # 2.0 + shift
    med_ang = np.median(np.abs(diag[5:]) + shift)           # 0.02 + shift
    assert np.allclose(D[:5], [10 * med_pos] * 3 + [1000.0 + shift, 10 * med_pos])
    assert np.allclose(D[5:], 10 * med_ang)
    assert (D > 0).all() and (D >= plain).all()


def test_newton_runs_with_one_openblas_thread_and_restores_the_count(monkeypatch):
    # OpenBLAS round-off depends on its thread count, and its busy-waiting threads take the
    # second core from PARDISO: the solver holds every loaded OpenBLAS to one thread
    from threadpoolctl import ThreadpoolController
    import sksparse.cholmod  # noqa: F401  (loads the system OpenBLAS CHOLMOD uses)
    import shellfem.newton as nt

    def counts():
        return [c.num_threads for c in ThreadpoolController().select(internal_api="openblas").lib_controllers]

    openblas = ThreadpoolController().select(internal_api="openblas")
    if not openblas.lib_controllers:
        pytest.skip("no OpenBLAS loaded")
    with openblas.limit(limits=2):
        before = counts()
        seen = []

        class Recorder:
            def __init__(self, *args):
                pass

            def solve(self):
                seen.extend(counts())
                return "solved"

        monkeypatch.setattr(nt, "_Newton", Recorder)
        assert nt.newton(None, None, None) == "solved"
        after = counts()
    assert seen and all(n == 1 for n in seen)
    assert after == before


def _solver_at(M, q, free):
    """A _Newton at q with its energy and gradient assembled (no step taken)."""
    from shellfem.newton import NewtonOptions, _Newton
    s = _Newton(M, q, free, NewtonOptions(relax_angles=False, relax_printed=False, rotation_path=False))
    s._start()
    s._assemble()
    return s


def test_creep_is_recognised_only_after_a_window_of_full_steps_that_barely_lower_the_energy():
    """_creeping: CREEP_WINDOW full Newton steps (lambda 0, step 1) whose energy fell by less than
    CREEP_ENERGY |E| and whose gradient stayed above half of the window's first: creep; one cut
    step, a shift, a gradient that fell to a third (quadratic or linear convergence) or an energy
    that fell by more: not creep."""
    from shellfem.newton import CREEP_ENERGY, CREEP_WINDOW
    M, free_x, tip = _loaded_cantilever()
    s = _solver_at(M, newton(M, M.initial_state(), free_x, max_iterations=3).q, free_x)
    E, gn = s.E, s.gnorm
    assert E != 0.0

    def window(step=1.0, lam=0.0, dE=0.1 * CREEP_ENERGY * abs(E), g0=gn):
        return [dict(iteration=k, energy=E + dE * (CREEP_WINDOW - k) / CREEP_WINDOW, gradient_norm=g0,
                     lam=lam, step=step) for k in range(CREEP_WINDOW)]

    s.history = window()
    assert s._creeping()
    s.history = window()[1:]
    assert not s._creeping()                       # too few steps
    h = window()
    h[3]["step"] = 0.5
    s.history = h
    assert not s._creeping()                       # one step cut by the line search
    s.history = window(lam=1e-6)
    assert not s._creeping()                       # trust-region steps
    s.history = window(g0=3.0 * gn)
    assert not s._creeping()                       # the gradient fell to a third
    s.history = window(dE=2.0 * CREEP_ENERGY * abs(E))
    assert not s._creeping()                       # the energy fell by more than CREEP_ENERGY


def test_creep_extrapolation_follows_the_step_while_the_energy_falls_and_never_through_a_contact():
    """_extrapolated doubles the accepted full step along its path while the energy falls (on a
    quadratic energy whose minimum lies 5.3 steps out: factor 4, the best of 1, 2, 4, 8), never
    returns a higher energy than the full step's, and stops where the trial energy is +inf (a
    contact the collision filter finds on the straight move)."""
    from shellfem.newton import CREEP_MAX_FACTOR
    M, free_x, tip = _loaded_cantilever()
    q0 = M.initial_state()
    s = _solver_at(M, q0, free_x)
    d = np.zeros_like(q0)
    d[np.flatnonzero(free_x)[:6]] = 1e-3

    class Quadratic:
        """E(q) = (a - 5.3)^2 along q0 + a d, the straight path's parameter a."""
        def __init__(self, wall=np.inf):
            self.wall = wall

        def trial_energy(self, q_from, q, below=None):
            a = float((q - q0) @ d / (d @ d))
            return np.inf if a > self.wall else (a - 5.3) ** 2

    along = lambda a: q0 + a * d
    s.model = Quadratic()
    q, E_new, a = s._extrapolated(along, along(1.0), (1.0 - 5.3) ** 2)
    assert a == 4.0 and E_new == pytest.approx(1.3 ** 2) and np.allclose(q, along(4.0))
    s.model = Quadratic(wall=3.0)                  # a contact between 2 and 4 steps out
    q, E_new, a = s._extrapolated(along, along(1.0), (1.0 - 5.3) ** 2)
    assert a == 2.0
    s.model = Quadratic()
    q, E_new, a = s._extrapolated(along, along(1.0), -1.0)    # nothing beats the full step
    assert a == 1.0 and E_new == -1.0
    assert s.timings["creep_extrapolations"] == 2
    assert CREEP_MAX_FACTOR >= 4


def test_converging_solves_never_extrapolate():
    """A solve that converges (Sze's loaded cantilever, 20 elements) never meets the creep test."""
    M, free_x, tip = _loaded_cantilever()
    r = newton(M, M.initial_state(), free_x, max_iterations=200)
    assert r.converged and r.timings.get("creep_extrapolations", 0) == 0
