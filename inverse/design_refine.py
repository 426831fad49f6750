"""`selfshape design --refine`: the open-loop design's ribbon thicknesses refined with the shell
in the loop (inverse.refine) so that the simulated sheet lands on the target (mm).

The simulation mesh of the design's pattern (the verification's), each printed region one
parameter (the design keeps ribbons apart, so a region is a ribbon); target positions of the
mesh vertices through the flattening's correspondence (inverse.registration.flat_to_target).
The equilibrium is sought nearest the target: one refinement starts from the target itself
(edge angles 0), another from the verification's released state when the first solve settled
elsewhere, and the one with the lower objective is kept (these multistable sheets refine to
different ends from different states).
The refined thicknesses are rounded to layer multiples of the printer, then moved by single
layers where the objective linearised at the rounded design says so (inverse.refine.refine_layers),
and the rounded design is what is written and reported; whether release from flat reaches the same state is checked
by the verification of the rounded pattern.
"""
from __future__ import annotations

import time

import numpy as np

from shellfem.errors import SelfshapeError


def deviations(d, X, triangles, targets):
    """Both one-way closest-point deviations (% of the target's bounding-box diagonal) of the
    sheet X (n, 3), registered as the verification does (inverse.verify.deviation_both_ways):
    {"deviation_pct_bbox": [mean, max] deployed -> target,
    "deviation_target_to_deployed_pct_bbox": [mean, max]}."""
    from inverse.verify import deviation_both_ways

    _, pct, back, _ = deviation_both_ways(d, X, triangles, targets)
    return {"deviation_pct_bbox": [float(pct.mean()), float(pct.max())],
            "deviation_target_to_deployed_pct_bbox": [float(back.mean()), float(back.max())]}


def region_ribbons(pattern, sheet) -> tuple[np.ndarray, list]:
    """(parameter per triangle (m,), ribbon indices of each parameter): one parameter per
    printed region of the mesh (geometry.arrangement.region_elements)."""
    from geometry.arrangement import region_elements

    groups = region_elements(pattern)
    param = np.where(sheet.region > 0, sheet.region - 1, -1).astype(np.int64)
    if param.max(initial=-1) >= len(groups):
        raise SelfshapeError("refine: the mesh has more printed regions than the pattern")
    return param, groups


def rounded(p, layer_mm: float, bounds) -> np.ndarray:
    """Thicknesses rounded to the nearest multiple of the layer height inside the bounds (mm)."""
    lo, hi = bounds
    k_lo, k_hi = int(np.ceil(lo / layer_mm - 1e-9)), int(np.floor(hi / layer_mm + 1e-9))
    return np.clip(np.round(np.asarray(p) / layer_mm), max(k_lo, 1), k_hi) * layer_mm


#: The states a refinement starts from: the target itself (the equilibrium nearest it), then the
#: verification's released state. These sheets are multistable and soft: the two starts often
#: settle in different states, and which one refines further depends on where the stability
#: margin binds, not on which starts nearer (docs/notes.md, session 36).
STARTS = ("target", "released")
#: Two first equilibria closer than this (weighted RMS after the best rigid motion, mm) are one state.
SAME_STATE_MM = 0.05


def _refine_from_starts(prob, p0, q_target, sim, T, opts, measure, starts, parallel=None):
    """Run inverse.refine.refine_thickness from each of ``starts`` ("target": the target's
    positions, edge angles 0; "released": the verification's released state moved onto the
    target by the best rigid motion, so that the gauge holds a rigid motion of it). The released
    start is skipped when the verification did not converge, or when the solve from the target
    settled in the released state (weighted RMS apart below SAME_STATE_MM after the best rigid
    motion): the two refinements would be one. Returns ([(label, RefineResult), ...], the
    per-start records for the report); raises SelfshapeError when no start gives an equilibrium.

    ``sim``: the verification's forward.simulate.Simulation, or an inverse.verify.SimulationBeside
    whose worker is still releasing the sheet from flat: the refinement from the target needs only
    the mesh and runs meanwhile; the released start is decided once both that worker and the
    target's first solve are done (checked at each of the target's outer iterations).

    ``parallel`` (default: shellfem.forked.available(), two or more cores): once the target's
    first solve has settled elsewhere than the released state, the refinement from the released
    state runs beside it in a forked process, each on one core until both have ended (a fixed
    thread schedule). The refinement holds OpenBLAS to one thread (inverse.refine), so its
    results do not depend on the thread count: the records are the serial run's, to the same
    bits. ``measure`` is called with ``report=False`` there (no progress from the child)."""
    from inverse.refine import refine_thickness
    from inverse.registration import kabsch
    from inverse.verify import SimulationBeside
    from shellfem import forked

    for s in starts:
        if s not in ("target", "released"):
            raise ValueError(f"refine: unknown start {s!r} (target, released)")
    parallel = forked.wanted(parallel)
    pending = sim if isinstance(sim, SimulationBeside) else None
    runs, records, first_states, jobs = [], [], {}, {}
    released = {}               # "q": the released state on the target (None: none), "why": why none
    n = len(T)

    def released_state():
        """The verification's released state moved onto the target, or None (waits for the worker)."""
        if "q" not in released:
            try:
                s_ = pending.simulation() if pending is not None else sim
            except SelfshapeError as e:
                released.update(q=None, why=f"the verification's release could not run ({e})")
                return None
            if not s_.result.converged:
                released.update(q=None, why="the verification's release did not converge")
                return None
            q = s_.result.q.copy()
            R, c = kabsch(q[:3 * n].reshape(n, 3), T, prob.w)
            q[:3 * n] = (q[:3 * n].reshape(n, 3) @ R.T + c).ravel()
            released["q"] = q
        return released["q"]

    def settled_in_released():
        """The target's first solve settled in the released state: (True, note) or (False, None)."""
        x0 = first_states.get("target")
        if x0 is None:
            return False, None
        x = released["q"][:3 * n].reshape(n, 3)
        R, c = kabsch(x0, x, prob.w)
        apart = float(np.sqrt(prob.w @ np.sum((x0 @ R.T + c - x) ** 2, 1) / prob.w.sum()))
        return apart < SAME_STATE_MM, f"the solve from the target settled in it ({apart:.2g} mm apart)"

    def run(s, label, report=True, on_iteration=None):
        """(record, RefineResult or None) of the refinement from start s."""
        t0 = time.perf_counter()

        def callback(it, p, q, model):
            if it == 0:
                first_states[s] = model.split(q)[0].copy()
            if on_iteration is not None:
                on_iteration()
            return measure(it, p, q, model, label, report=report)
        try:
            res = refine_thickness(prob, p0, q_target if s == "target" else released["q"], opts, callback=callback)
        except SelfshapeError as e:
            return {"start": label, "converged": False, "reason": str(e),
                    "seconds": round(time.perf_counter() - t0, 2)}, None
        return {"start": label, "converged": True, "outer_iterations": len(res.history) - 1,
                "rms_mm_start": res.history[0]["rms_mm"], "rms_mm": res.rms_mm,
                "objective": res.objective, "reason": res.reason,
                "seconds": round(time.perf_counter() - t0, 2)}, res

    def run_in_child(s, label):
        record, res = run(s, label, report=False)
        if res is not None and res.margin is not None:
            res.margin.problem = None             # the problem stays in the parent (nothing to pickle)
        return record, res

    decided = []

    def launch_released():
        """At each of the target's outer iterations: once its first solve is done and the
        verification's release is in, start the released state's refinement beside it (once)."""
        if (decided or not parallel or "released" not in starts
                or starts.index("released") < starts.index("target") or "target" not in first_states
                or (pending is not None and not pending.done())):
            return
        decided.append(True)
        if released_state() is not None and not settled_in_released()[0]:
            jobs["released"] = forked.start(run_in_child, "released", "released state", label="refine from the released state")

    try:
        for s in starts:
            label = "target" if s == "target" else "released state"
            if s == "released":
                if released_state() is None:
                    records.append({"start": label, "skipped": released["why"]})
                    continue
                same, note = settled_in_released()
                if same:
                    records.append({"start": label, "skipped": note})
                    continue
            if s in jobs:
                record, res = jobs.pop(s).result()
                if res is not None and res.margin is not None:
                    res.margin.problem = prob
            else:
                record, res = run(s, label, on_iteration=launch_released if s == "target" else None)
            records.append(record)
            if res is not None:
                runs.append((label, res))
    finally:
        for job in jobs.values():                  # an exception here: no child left behind
            job.cancel()
    if not runs:
        raise SelfshapeError("refine: no equilibrium near the target: "
                             + "; ".join(f"from the {r['start']}: {r.get('reason') or r.get('skipped')}" for r in records))
    return runs, records


def refine_design(d, pattern, sim, printer, options=None, smoothness: float = 0.05, verbose: bool = False,
                  progress=None, layer_rounds_max: int = 8, starts=STARTS, parallel=None) -> tuple:
    """Refine the thicknesses of the design ``d`` (whose pattern is ``pattern`` and whose
    verification simulation is ``sim``, forward.simulate.Simulation, or an
    inverse.verify.SimulationBeside still running in its worker). Sets the ribbons'
    thickness_mm to the rounded refined values and returns (block, positions): the report block
    "refine" (per outer iteration objective, RMS distance (mm), deviations both ways (%),
    seconds; continuous and rounded thicknesses; the rounded design's deviations at the
    equilibrium nearest the target; the reason the iteration stopped) and that equilibrium's
    vertex positions on sim.sheet (n, 3) mm, None if its solve did not converge: the state a
    jig selects (inverse.jig) when release from flat misses it. Raises SelfshapeError if no
    equilibrium near the target can be found (the caller keeps the open-loop design).
    ``progress``: called with {"stage": "outer", "iteration", "rms_mm"} at each accepted outer
    iterate (the CLI's status line). ``layer_rounds_max``: rounds of one-layer moves after the
    rounding (inverse.refine.refine_layers; 0: none; they end at the first round none of whose
    moves lowers the objective, or whose move lowers it by less than the options' ftol), recorded
    as "layer_rounds". Why several: each round is
    linearised where the previous one left the design, and thin ribbons rounded to 0.1 mm layers
    start far from the continuous optimum, so later rounds still gain (docs/notes.md, session 26).
    ``starts``: the first states of the refinement, tried in turn (see _refine_from_starts); the
    refinement with the lowest objective is rounded and kept, and "starts" records each.
    ``parallel``: the two starts side by side on two cores (see _refine_from_starts; None: when
    the machine has two cores)."""
    from inverse.refine import (RefineOptions, ThicknessProblem, finite_or_none, follow_thickness, linear_rounding,
                                refine_layers)
    from inverse.registration import flat_to_target
    from shellfem.boundary import gauge_dofs
    from shellfem.kinematics import build_topology

    t0 = time.perf_counter()
    opts = options or RefineOptions(bounds=(printer.layer_height_mm, 1.6), verbose=verbose)
    sheet = sim.sheet
    param, groups = region_ribbons(pattern, sheet)
    if not groups:
        raise SelfshapeError("refine: the design has no printed region to refine")
    p0 = np.array([d.ribbons[g[0]].thickness_mm for g in groups])
    T = flat_to_target(sheet.points, d.flat.uv, d.F, d.goal)
    n_edges = build_topology(sheet.triangles).n_edges
    free = np.ones(3 * sheet.n_vertices + n_edges, bool)
    free[gauge_dofs(T, np.zeros(0, np.int64))] = False
    prob = ThicknessProblem(sheet, pattern.fabric, pattern.plastic, param, T, free, smoothness=smoothness)
    q_target = np.concatenate([T.ravel(), np.zeros(n_edges)])

    def measure(it, p, q, model, start=None, report=True):
        out = deviations(d, model.split(q)[0], sheet.triangles, T)
        if progress is not None and report:
            progress({"stage": "outer", "iteration": int(it), "start": start,
                      "rms_mm": prob.objective(model.split(q)[0], p)[1] ** 0.5})
        return out

    runs, starts_block = _refine_from_starts(prob, p0, q_target, sim, T, opts, measure, starts, parallel)
    start, res = min(runs, key=lambda r: r[1].objective)
    h = printer.layer_height_mm
    p_round = rounded(res.thickness, h, opts.bounds)
    first, top = rounded(list(opts.bounds), h, opts.bounds)       # the thinnest / thickest printable layer counts
    if res.model is not None:         # floor or ceil per ribbon, as the Gauss-Newton model prefers
        lo = np.minimum(rounded(res.thickness - 0.5 * h, h, opts.bounds), p_round)
        p_round = np.clip(linear_rounding(res.model, res.thickness, lo, h), lo, top)
    model_r = prob.model_at(p_round)
    rr = prob.solve(model_r, res.q, opts.newton_iterations)
    rounding_path = None
    J_r = prob.objective(model_r.split(rr.q)[0], p_round)[0] if rr.converged else np.inf
    if J_r > 2.0 * res.objective:
        # the rounded design's solve left the refined branch: follow the thicknesses from the
        # continuous to the rounded values in steps, each solve warm-started from the last
        q_path, ok = follow_thickness(prob, res.thickness, res.q, p_round, 4, opts.newton_iterations)
        J_path = prob.objective(model_r.split(q_path)[0], p_round)[0] if ok else np.inf
        rounding_path = {"direct_objective": finite_or_none(J_r), "continuation_objective": finite_or_none(J_path)}
        if J_path < J_r:
            rr.q, rr.converged, J_r = q_path, True, J_path
    layer_rounds = []
    if rr.converged and layer_rounds_max > 0:
        # one-layer moves linearised at the rounded design (the rounding's model was the continuous point's);
        # a move of many ribbons by a layer is a larger step than an outer iteration's: twice its solve cap
        p_round, rr.q, _, layer_rounds = refine_layers(prob, p_round, rr.q, h, (first, top), rounds=layer_rounds_max,
                                                       newton_iterations=2 * opts.trial_iterations, verbose=verbose,
                                                       leave_factor=opts.leave_factor, shifted_run=opts.shifted_run,
                                                       shifted_grace=opts.shifted_grace, margin=res.margin,
                                                       ftol=opts.ftol)
        model_r = prob.model_at(p_round)
    block = {
        "start": start, "starts": starts_block, "outer_iterations": len(res.history) - 1, "reason": res.reason,
        "smoothness": smoothness, "bounds_mm": list(opts.bounds), "layer_height_mm": printer.layer_height_mm,
        "n_parameters": len(groups), "iterations": res.history,
        "thickness_start_mm": p0.round(4).tolist(), "thickness_continuous_mm": res.thickness.round(4).tolist(),
        "thickness_rounded_mm": p_round.round(4).tolist(), "layer_rounds": layer_rounds,
        **({"rounding_continuation": rounding_path} if rounding_path else {}),
        "continuous": {"rms_mm": res.rms_mm, **res.history[-1]},
    }
    near = None
    if rr.converged:
        near = model_r.split(rr.q)[0]
        block["rounded"] = {"rms_mm": float(np.sqrt(prob.objective(near, p_round)[1])),
                            **deviations(d, near, sheet.triangles, T)}
    else:
        block["rounded"] = {"converged": False, "reason": rr.reason}
    for g, t in zip(groups, p_round):
        for i in g:
            d.ribbons[i].thickness_mm = float(round(t, 6))
    block["seconds"] = round(time.perf_counter() - t0, 2)
    return block, near
