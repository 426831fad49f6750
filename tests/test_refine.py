"""Refinement with the shell in the loop (inverse.refine): recovery of known thicknesses from
the shape they deploy to, and the objective's pieces."""
import numpy as np
import pytest

from ribbon_sheets import ribbon_checkerboard, sheet_at
from inverse.refine import (RefineOptions, ThicknessProblem, neighbour_pairs, next_trust_radius, refine_thickness,
                            vertex_areas)
from shellfem.boundary import gauge_dofs, smooth_perturbation
from shellfem.materials import Fabric, Plastic
from shellfem.model import ShellModel
from shellfem.newton import newton

FABRIC = Fabric(stretch=1.3)
PLASTIC = Plastic(young_modulus=1180.0)
TRUE = np.array([0.8, 1.0, 1.2, 0.9, 1.1, 0.7, 1.0, 0.8, 0.9])


def basket(size=36.0, n=24):
    """A size x size mm sheet with a 3 x 3 checkerboard of 10 x 2 mm front ribbons, along x and
    along y in turn (a doubly curved, well-determined shape); one parameter per ribbon."""
    return ribbon_checkerboard(size, n, 3, 5.0)


@pytest.fixture(scope="module")
def deployed():
    base, param = basket()
    model = ShellModel.from_materials(sheet_at(base, param, TRUE), FABRIC, PLASTIC)
    q = model.initial_state()
    x, _ = model.split(q)
    x[:, 2] += smooth_perturbation(base.points, 0, 0.3)
    free = np.ones(model.n_dofs, bool)
    free[gauge_dofs(x, np.zeros(0, int))] = False
    r = newton(model, q, free, max_iterations=500, rtol=1e-10)
    assert r.converged, r.reason
    return base, param, model.split(r.q)[0]


def test_refinement_recovers_the_thicknesses_a_shape_was_deployed_with(deployed):
    """The deployed surface of known thicknesses as the target, started +-30 % off and from the
    target itself (edge angles 0): back to the surface within 0.2 % of its diagonal and to the
    thicknesses within 5 % (here: to round-off)."""
    base, param, X = deployed
    diag = float(np.linalg.norm(X.max(0) - X.min(0)))
    p0 = TRUE * (1 + 0.3 * np.array([1, -1, 1, -1, -1, 1, 1, -1, 1]))
    prob = ThicknessProblem(sheet_at(base, param, p0), FABRIC, PLASTIC, param, X, None, smoothness=0.0)
    prob.free = np.ones(3 * base.n_vertices + prob.model_at(p0).n_edges, bool)
    prob.free[gauge_dofs(X, np.zeros(0, int))] = False
    q0 = np.concatenate([X.ravel(), np.zeros(len(prob.free) - X.size)])
    res = refine_thickness(prob, p0, q0, RefineOptions(ftol=1e-8, max_outer=15))
    start = res.history[0]["rms_mm"]
    assert start > 0.02                             # mm: the perturbed start is off (0.03 mm rms)
    assert res.rms_mm < min(0.002 * diag, 0.01 * start)
    assert np.max(np.abs(res.thickness / TRUE - 1)) < 0.05
    J = [h["objective"] for h in res.history if h["accepted"]]
    assert all(b <= a for a, b in zip(J, J[1:]))    # accepted steps never raise the objective


def test_the_trust_radius_does_not_grow_back_to_a_step_that_was_just_rejected():
    max_step = 0.2
    # no rejection yet: good trials double the radius up to max_step; a fair one keeps it
    assert next_trust_radius(0.05, np.inf, np.full(3, 0.05), 0.9, max_step) == (0.1, np.inf)
    assert next_trust_radius(0.1, np.inf, np.full(3, 0.1), 0.9, max_step) == (0.2, np.inf)
    assert next_trust_radius(0.1, np.inf, np.full(3, 0.1), 0.5, max_step) == (0.1, np.inf)
    # a rejected step of largest change 0.2 mm: half of it, and 0.2 becomes the ceiling
    r, c = next_trust_radius(0.2, np.inf, np.array([0.05, -0.2, 0.1]), -np.inf, max_step)
    assert (r, c) == (0.1, 0.2)
    assert next_trust_radius(r, c, np.full(3, 0.1), float("nan"), max_step) == (0.05, 0.1)   # NaN: rejected
    # good trials after it: the radius climbs towards the raised ceiling, below twice itself
    radii = []
    for _ in range(6):
        r, c = next_trust_radius(r, c, np.full(3, r), 0.9, max_step)
        radii.append(r)
    assert radii[0] == pytest.approx(np.sqrt(0.1 * 0.25))
    assert all(b > a for a, b in zip(radii, radii[1:] + [np.inf]) if a < max_step)
    assert radii[0] < 0.2 and radii[-1] == max_step


def test_vertex_areas_sum_to_the_sheet_and_neighbours_are_the_adjacent_ribbons():
    base, param = basket()
    assert vertex_areas(base).sum() == pytest.approx(36.0 * 36.0, rel=1e-12)
    pairs = {tuple(p) for p in neighbour_pairs(base, param, 9).tolist()}
    for a, b in ((0, 1), (1, 2), (0, 3), (4, 5), (4, 7)):    # grid neighbours are Delaunay edges
        assert (a, b) in pairs


def test_smoothness_pulls_neighbours_together():
    """With a large smoothness weight the refined thicknesses spread less than the truth."""
    base, param = basket()
    prob = ThicknessProblem(sheet_at(base, param, TRUE), FABRIC, PLASTIC, param,
                            np.zeros((base.n_vertices, 3)), None, smoothness=1.0)
    r, L = prob.regulariser(TRUE)
    assert float(r @ r) == pytest.approx(np.mean([(TRUE[a] - TRUE[b]) ** 2 for a, b in prob.pairs]), rel=1e-12)
    assert L.shape == (len(prob.pairs), 9)


def test_linear_rounding_picks_the_side_the_model_prefers():
    """Two parameters whose effects cancel: rounding each to its nearest layer leaves a residual
    that rounding one of them the other way removes."""
    from inverse.refine import linear_rounding
    M = np.array([[1.0, 1.0], [0.0, 1e-3]])
    p_lin = np.array([0.0, 0.0])
    b = np.array([0.0, 0.0])
    p = np.array([0.31, -0.29])                     # nearest layers 0.4 and -0.2 do not cancel
    lo = np.array([0.2, -0.4])
    nearest = np.array([0.4, -0.2])
    t = linear_rounding((p_lin, M, b), p, lo, 0.2)
    J = lambda x: float(np.sum((M @ (x - p_lin) - b) ** 2))     # noqa: E731
    assert J(t) < J(nearest) - 1e-3
    assert set(np.round(t, 9)) <= {0.2, 0.4, -0.4, -0.2}


def test_layer_descent_moves_each_parameter_at_most_one_layer_inside_the_bounds():
    from inverse.refine import layer_descent
    M = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    p = np.array([0.5, 0.5])
    b = np.array([0.35, -0.35, 0.0])                     # the model asks +0.35 / -0.35
    np.testing.assert_allclose(layer_descent(M, b, p, 0.1, 0.1, 1.6), [0.6, 0.4])
    np.testing.assert_allclose(layer_descent(M, b, p, 0.1, 0.1, 0.5), [0.5, 0.4])      # capped at hi
    np.testing.assert_allclose(layer_descent(M, np.zeros(3), p, 0.1, 0.1, 1.6), p)   # nothing to gain


def layers_off(deployed, layers: int):
    """(problem, p0, r0): the basket's thicknesses ``layers`` 0.1 mm layers off on every ribbon
    (alternating signs) and the equilibrium r0 at p0 solved from the deployed shape X."""
    base, param, X = deployed
    p0 = np.round(TRUE + 0.1 * layers * np.array([1, -1, 1, -1, -1, 1, 1, -1, 1]), 6)
    prob = ThicknessProblem(sheet_at(base, param, p0), FABRIC, PLASTIC, param, X, None, smoothness=0.0)
    prob.free = np.ones(3 * base.n_vertices + prob.model_at(p0).n_edges, bool)
    prob.free[gauge_dofs(X, np.zeros(0, int))] = False
    r0 = prob.solve(prob.model_at(p0), np.concatenate([X.ravel(), np.zeros(len(prob.free) - X.size)]), 400)
    return prob, p0, r0


def test_layer_refinement_returns_layer_counts_that_are_one_layer_off(deployed):
    """The thicknesses the shape was deployed with lie on a 0.1 mm grid; started one layer off
    on every ribbon (at the equilibrium nearest the shape), the re-linearised layer moves return
    to them, and the objective falls to round-off."""
    from inverse.refine import refine_layers
    prob, p0, r0 = layers_off(deployed, 1)
    assert r0.converged
    J0 = prob.objective(prob.model_at(p0).split(r0.q)[0], p0)[0]
    p, q, J, hist = refine_layers(prob, p0, r0.q, 0.1, (0.1, 1.6), rounds=4)
    np.testing.assert_allclose(p, TRUE, atol=1e-9)
    assert J < 1e-8 * J0 and J0 > 5e-5                 # mm^2: one layer off is ~0.01 mm rms here
    assert all(h["accepted"] for h in hist if h["changed"])
    # with a stability margin below every eigenvalue on the way the moves are the same, and
    # each trial records its equilibrium's lowest eigenvalue
    from inverse.refine import StabilityMargin
    from shellfem.stability import lowest_mode
    lam0 = lowest_mode(prob.model_at(p0), r0.q, prob.free)[0]
    low = StabilityMargin(prob, 0.5)
    low.reference(lam0, J0)
    p_low, _, J_low, hist_low = refine_layers(prob, p0, r0.q, 0.1, (0.1, 1.6), rounds=4, margin=low)
    np.testing.assert_allclose(p_low, TRUE, atol=1e-9)
    assert all(h["lambda_min"] > 0.5 * lam0 for h in hist_low if h["accepted"])


def test_layer_rounds_end_when_a_round_gains_less_than_ftol(deployed):
    """Started two layers off on every ribbon, the first round moves each by one layer (J falls
    by most of itself) and the second returns them; with ftol above the first round's relative
    gain the rounds end after it, one layer short, with the first round's thicknesses."""
    from inverse.refine import refine_layers
    prob, p0, r0 = layers_off(deployed, 2)
    assert r0.converged
    J0 = prob.objective(prob.model_at(p0).split(r0.q)[0], p0)[0]
    p, _, J, hist = refine_layers(prob, p0, r0.q, 0.1, (0.1, 1.6), rounds=4, ftol=0.5)
    np.testing.assert_allclose(p, TRUE, atol=1e-9)
    assert [h["round"] for h in hist if h["accepted"]] == [1, 2]
    J1 = hist[0]["objective"]
    assert 0.5 * J0 > J1 > 0.01 * J0                       # the first round's gain: between 50 and 99 %
    p, _, J, hist = refine_layers(prob, p0, r0.q, 0.1, (0.1, 1.6), rounds=4, ftol=0.999)
    assert [h["round"] for h in hist] == [1] and J == J1
    np.testing.assert_allclose(np.abs(p - TRUE), 0.1, atol=1e-9)


def test_following_the_thicknesses_in_steps_reaches_the_direct_equilibrium(deployed):
    """Where no other state is near, the equilibrium followed in 4 thickness steps is the one a
    single solve finds (mm)."""
    from inverse.refine import follow_thickness
    base, param, X = deployed
    prob = ThicknessProblem(sheet_at(base, param, TRUE), FABRIC, PLASTIC, param, X, None, smoothness=0.0)
    prob.free = np.ones(3 * base.n_vertices + prob.model_at(TRUE).n_edges, bool)
    prob.free[gauge_dofs(X, np.zeros(0, int))] = False
    q0 = prob.solve(prob.model_at(TRUE), np.concatenate([X.ravel(), np.zeros(len(prob.free) - X.size)]), 400).q
    p1 = TRUE * 1.15
    q, ok = follow_thickness(prob, TRUE, q0, p1, 4)
    direct = prob.solve(prob.model_at(p1), q0, 400)
    assert ok and direct.converged
    x, y = prob.model_at(p1).split(q)[0], prob.model_at(p1).split(direct.q)[0]
    assert np.abs(x - y).max() < 1e-5 and np.abs(x - X).max() > 0.01      # moved 0.02 mm, to the same state


def test_a_trial_solve_stops_once_its_objective_passes_the_limit(deployed):
    """ThicknessProblem.solve with a limit: from the flat sheet (far from the deployed target)
    it stops, not converged, with the LEFT_BRANCH reason at the first iterate whose objective
    passes the limit; with a limit no iterate reaches it returns the plain solve's equilibrium."""
    from inverse.refine import LEFT_BRANCH
    base, param, X = deployed
    prob = ThicknessProblem(sheet_at(base, param, TRUE), FABRIC, PLASTIC, param, X, None, smoothness=0.0)
    model = prob.model_at(TRUE)
    prob.free = np.ones(model.n_dofs, bool)
    prob.free[gauge_dofs(X, np.zeros(0, int))] = False
    q0 = np.concatenate([X.ravel(), np.zeros(model.n_edges)])
    plain = prob.solve(model, q0, 300)
    assert plain.converged
    J_end = prob.objective(model.split(plain.q)[0], TRUE)[0]
    assert J_end < 1e-12                                 # the target is this sheet's own equilibrium
    flat = model.initial_state()
    x, _ = model.split(flat)
    x[:, 2] += smooth_perturbation(base.points, 0, 0.3)
    stopped = prob.solve(model, flat, 300, TRUE, limit=1e-3)
    assert not stopped.converged and stopped.reason.startswith(LEFT_BRANCH)
    assert prob.objective(model.split(stopped.q)[0], TRUE)[0] > 1e-3
    assert stopped.iterations <= 2
    loose = prob.solve(model, q0, 300, TRUE, limit=1e6)
    assert loose.converged and np.allclose(loose.q, plain.q, atol=1e-12)


def test_a_trial_solve_stops_on_a_run_of_shifted_iterations_above_the_bound(deployed):
    """ThicknessProblem.solve with shifted = (run, grace, bound): released from flat (a saddle
    of the energy: Levenberg-Marquardt steps) it stops, not converged, once ``run`` accepted
    iterations in a row after the first ``grace`` were shifted while the objective is above
    ``bound``; with a bound no iterate exceeds it, the solve is the plain one."""
    from inverse.refine import LEFT_BRANCH
    base, param, X = deployed
    prob = ThicknessProblem(sheet_at(base, param, TRUE), FABRIC, PLASTIC, param, X, None, smoothness=0.0)
    model = prob.model_at(TRUE)
    prob.free = np.ones(model.n_dofs, bool)
    prob.free[gauge_dofs(X, np.zeros(0, int))] = False
    flat = model.initial_state()
    x, _ = model.split(flat)
    x[:, 2] += smooth_perturbation(base.points, 0, 0.3)
    plain = prob.solve(model, flat, 300, TRUE, limit=1e6)
    assert plain.converged
    shifted = [h["lam"] > 0 for h in plain.history]
    run = 3
    first = next(i for i in range(1, len(shifted) + 1) if i >= 1 + run and all(shifted[i - run:i]))
    stopped = prob.solve(model, flat, 300, TRUE, limit=1e6, shifted=(run, 1, 0.0))
    assert not stopped.converged and stopped.reason.startswith(LEFT_BRANCH)
    assert "shifted iterations in a row" in stopped.reason
    assert len(stopped.history) == first
    high = prob.solve(model, flat, 300, TRUE, limit=1e6, shifted=(run, 1, 1e6))
    assert high.converged and np.allclose(high.q, plain.q, atol=1e-12)


def test_a_layer_trial_that_does_not_converge_is_recorded_without_an_objective(deployed, monkeypatch):
    """A one-layer move whose trial solve stops (left the branch, or the cap) is rejected and
    recorded with objective None and the solve's reason, so the report stays finite JSON."""
    import json

    from inverse.refine import refine_layers
    from shellfem.newton import SolveResult
    prob, p0, r0 = layers_off(deployed, 1)

    def stopped(self, model, q_guess, q, max_iterations, p, limit, shifted=None):
        return SolveResult(q=q_guess, converged=False, iterations=7, energy=np.nan, gradient_norm=np.nan,
                           reason="left the branch (objective 2 > 1 mm^2)", stable=False)
    monkeypatch.setattr(ThicknessProblem, "trial_solve", stopped)
    p, q, J, hist = refine_layers(prob, p0, r0.q, 0.1, (0.1, 1.6), rounds=2)
    np.testing.assert_array_equal(p, p0)
    assert hist and all(h["objective"] is None and not h["accepted"] and h["reason"].startswith("left the branch")
                        for h in hist)
    json.dumps(hist, allow_nan=False)
    # the round ends after its first two trials left the branch (the move and its best half),
    # with leaving_in_a_row = 0 it halves the move down to one ribbon (up to max_trials solves)
    assert [h["changed"] for h in hist] == [hist[0]["changed"], hist[0]["changed"] // 2]
    _, _, _, every = refine_layers(prob, p0, r0.q, 0.1, (0.1, 1.6), rounds=2, leaving_in_a_row=0)
    assert len(every) > 2 and [h["changed"] for h in every[:2]] == [h["changed"] for h in hist]


def test_a_layer_trial_that_converges_above_the_objective_does_not_end_the_round(deployed, monkeypatch):
    """Trials that converge to a state above J are rejected but are no fold: the round halves
    the move down to max_trials solves, as before the leaving rule."""
    from inverse.refine import refine_layers
    from shellfem.newton import SolveResult
    prob, p0, r0 = layers_off(deployed, 1)
    n3 = 3 * deployed[0].n_vertices
    bump = np.zeros_like(r0.q)
    bump[:n3] = np.random.default_rng(0).normal(scale=1.0, size=n3)      # 1 mm of non-rigid noise

    def above(self, model, q_guess, q, max_iterations, p, limit, shifted=None):
        return SolveResult(q=q_guess + bump, converged=True, iterations=3, energy=1.0, gradient_norm=0.0,
                           reason="gradient norm below tolerance", stable=True)
    monkeypatch.setattr(ThicknessProblem, "trial_solve", above)
    _, _, _, hist = refine_layers(prob, p0, r0.q, 0.1, (0.1, 1.6), rounds=2, max_trials=4)
    assert len(hist) > 2 and not any(h["accepted"] for h in hist)


def test_the_history_records_the_lowest_eigenvalue_and_the_margin_raises_it(deployed):
    """Each accepted iterate records lambda_min (N/mm^3), the lowest eigenvalue of its
    equilibrium (shellfem.stability), and the last one is that of the returned state. With a
    margin above every reachable eigenvalue (fraction 2 of the start's, weight 10) the
    refinement trades objective for stability: it ends with a larger lambda_min and a larger
    objective than without."""
    from shellfem.stability import lowest_mode
    base, param, X = deployed
    p0 = TRUE * (1 + 0.3 * np.array([1, -1, 1, -1, -1, 1, 1, -1, 1]))
    out = {}
    for fraction in (0.0, 2.0):
        prob = ThicknessProblem(sheet_at(base, param, p0), FABRIC, PLASTIC, param, X, None, smoothness=0.0)
        prob.free = np.ones(3 * base.n_vertices + prob.model_at(p0).n_edges, bool)
        prob.free[gauge_dofs(X, np.zeros(0, int))] = False
        q0 = np.concatenate([X.ravel(), np.zeros(len(prob.free) - X.size)])
        res = refine_thickness(prob, p0, q0, RefineOptions(ftol=1e-8, max_outer=4, stability=fraction,
                                                           stability_weight=10.0))
        lam = [h["lambda_min"] for h in res.history if h["accepted"]]
        assert all(np.isfinite(lam)) and min(lam) > 0
        again = lowest_mode(prob.model_at(res.thickness), res.q, prob.free, tol=1e-10)[0]
        assert lam[-1] == pytest.approx(again, rel=1e-5)
        out[fraction] = (lam[-1], res.objective, lam[0])
    assert out[2.0][2] == pytest.approx(out[0.0][2], rel=1e-9)        # the same start
    assert out[2.0][0] > 1.002 * out[0.0][0]
    assert out[2.0][1] > out[0.0][1]
