"""Verification of a design: simulate the designed pattern (forward.simulate), register the
deployed surface rigidly to the target and measure closest-point distances both ways, in % of
the target's bounding-box diagonal (mm for the diagonal)."""
from __future__ import annotations

import time

import numpy as np

from inverse.record import Design
from shellfem.errors import SelfshapeError


def deviation_both_ways(d: Design, X: np.ndarray, triangles: np.ndarray, Y0: np.ndarray | None = None):
    """A deployed sheet X (n, 3) with ``triangles`` registered rigidly to the target of design d
    (Kabsch on the correspondences Y0, then ICP: inverse.registration.register) and its
    closest-point distances both ways in % of the target's bounding-box diagonal: (registered X,
    deployed -> target (n,), target -> deployed (one per target vertex), ICP iterations)."""
    import igl

    from inverse.registration import register

    diag = float(np.linalg.norm(d.V_input.max(0) - d.V_input.min(0)))
    Xr, dist, icp_it = register(X, d.V_input, d.F_input, Y0)
    back = np.sqrt(igl.point_mesh_squared_distance(d.V_input, Xr, np.ascontiguousarray(triangles, dtype=np.int64))[0])
    return Xr, 100.0 * dist / diag, 100.0 * back / diag, icp_it


def register_simulation(d: Design, sim):
    """:func:`deviation_both_ways` of a simulation of the design d (forward.simulate.Simulation),
    its correspondences from the flattening: (registered positions (n, 3) mm, deployed -> target
    % (n,), target -> deployed %, ICP iterations). Made once per simulation and target: the
    result is kept on the simulation (refine.png draws simulations the verification registered)."""
    from inverse.registration import flat_to_target
    state = sim.result.q if hasattr(sim, "result") else sim.positions
    key = (id(d.V_input), id(d.flat.uv), id(state))
    hit = getattr(sim, "_registration", None)
    if hit is not None and hit[0] == key:
        return hit[1]
    Y0 = flat_to_target(sim.sheet.points, d.flat.uv, d.F, d.goal)
    result = deviation_both_ways(d, sim.positions, sim.sheet.triangles, Y0)
    sim._registration = (key, result)
    return result


class SimulationBeside:
    """A pattern's simulation (forward.simulate.simulate) run in a forked worker on one core
    (shellfem.forked) while this process works on the same mesh: ``sheet`` is here at once, the
    Simulation when :meth:`simulation` is asked. Why: `design --refine` refines from the target's
    own positions, which needs only the mesh, while the open-loop verification releases the
    sheet from flat; side by side they share the two cores. The worker's Simulation has the bits
    this process would have computed (the solver's results do not depend on its thread count)."""

    def __init__(self, pattern, label: str = "the verification"):
        from forward.simulate import mesh_for_simulation, simulate
        from shellfem import forked

        self.sheet, coarse = mesh_for_simulation(pattern)       # its SelfshapeError: raised here
        self.job = forked.start(lambda: simulate(pattern, meshed=(self.sheet, coarse)), label=label)

    def done(self) -> bool:
        """The worker has finished (its Simulation, or its error, is waiting)."""
        return self.job.done()

    def simulation(self):
        """Wait for the worker: its Simulation; its SelfshapeError is raised here."""
        return self.job.result()

    def cancel(self) -> None:
        self.job.cancel()


#: a verification warns when its two mean deviations sum to more than this times the flat sheet's
FLAT_MARGIN = 0.95


def flat_sheet_deviation(d: Design):
    """The deviations both ways (% of the target's bounding-box diagonal, as a verification's)
    of the nearest flat sheet: the design's flattening scaled to the target's area and
    registered like a deployed sheet (Kabsch on the flattening's correspondences, then ICP).
    The reference a verification is read against: a design whose deployed sheet is not nearer
    to the target than this has not shaped the sheet towards it. Returns (flat -> target (n,),
    target -> flat (one per target vertex))."""
    from geometry.meshops import face_areas
    uv = np.asarray(d.flat.uv, float)
    X = np.column_stack([uv, np.zeros(len(uv))])
    c = float(np.sqrt(face_areas(d.goal, d.F).sum() / face_areas(X, d.F).sum()))
    _, pct, back, _ = deviation_both_ways(d, c * X, d.F, d.goal)
    return pct, back


def verify_design(d: Design, pattern, out_dir: str | None = None, written: list | None = None,
                  sims: list | None = None, progress=None, simulation=None, beside=None) -> dict:
    """Simulate ``pattern`` (the geometry.patterns.Pattern of the design d), register the deployed
    surface to the target and return the report entries: verify_converged, verify_reason,
    Newton iterations, deviation_pct_bbox [mean, max] (deployed -> target),
    deviation_target_to_deployed_pct_bbox [mean, max], deviation_p99_pct_bbox, and the same two
    of the nearest flat sheet (flat_deviation_pct_bbox, flat_deviation_target_to_flat_pct_bbox:
    flat_sheet_deviation) with a verify_warning when the deployed sheet is not nearer than it
    (sum of the two means) by more than 1 - FLAT_MARGIN. A simulation that fails or does not
    converge reports no deviation. With ``out_dir`` (a folder or the design's
    shellfem.outfiles.OutputDir), deployed.vtu, deployed.obj/.stl/.ply (registered, mm) and
    verify.png are written there atomically and their paths appended to ``written``; the
    Simulation is appended to ``sims`` if given (the refinement starts from it). ``progress``:
    the simulation's progress callback (forward.simulate.simulate_sheet). ``simulation``: an
    earlier Simulation of this same pattern, registered and written instead of simulating again
    (the solver is deterministic, so it is the state a new run would reach;
    verify_simulation_s is then its own wall time). ``beside``: a :class:`SimulationBeside` of
    this pattern, whose worker's Simulation is waited for instead of simulating here (its error
    is reported as a simulation here would fail)."""
    from forward.simulate import simulate
    from inverse.plots import plot_verify
    from inverse.vtu import write_deployed_vtu

    t0 = time.perf_counter()
    if simulation is not None:
        sim = simulation
    else:
        try:
            sim = beside.simulation() if beside is not None else simulate(pattern, progress=progress)
        except SelfshapeError as e:      # the design stays valid; the verification could not run
            return {"verify_converged": False, "verify_reason": f"simulation failed: {e}", "deviation_pct_bbox": None,
                    "verify_note": "the simulation could not run; no deviation reported",
                    "verify_simulation_s": round(time.perf_counter() - t0, 2)}
    if sims is not None:
        sims.append(sim)
    s = sim.summary()
    seconds = s.get("wall_time_s", 0.0) if simulation is not None or beside is not None else time.perf_counter() - t0
    out = {"verify_converged": bool(s["converged"]), "verify_reason": s["reason"],
           "verify_newton_iterations": s["newton_iterations"], "verify_n_triangles": s["n_triangles"],
           "verify_simulation_s": round(seconds, 2)}
    if not s["converged"]:
        out["deviation_pct_bbox"] = None
        out["verify_note"] = f"simulation did not converge ({s['reason']}); no deviation reported"
        return out
    Xr, pct, back, icp_it = register_simulation(d, sim)
    out.update({"deviation_pct_bbox": [float(pct.mean()), float(pct.max())],
                "deviation_target_to_deployed_pct_bbox": [float(back.mean()), float(back.max())],
                "deviation_p99_pct_bbox": float(np.percentile(pct, 99)), "icp_iterations": int(icp_it),
                "bbox_diagonal_mm": float(np.linalg.norm(d.V_input.max(0) - d.V_input.min(0)))})
    f_pct, f_back = flat_sheet_deviation(d)
    out["flat_deviation_pct_bbox"] = [float(f_pct.mean()), float(f_pct.max())]
    out["flat_deviation_target_to_flat_pct_bbox"] = [float(f_back.mean()), float(f_back.max())]
    if pct.mean() + back.mean() >= FLAT_MARGIN * (f_pct.mean() + f_back.mean()):
        out["verify_warning"] = (f"the deployed sheet is not clearly nearer to the target than a flat sheet of its "
                                 f"area ({pct.mean():.2f} / {back.mean():.2f} % against {f_pct.mean():.2f} / "
                                 f"{f_back.mean():.2f} %, mean both ways): this design does not shape the sheet "
                                 f"towards the target")
    if out_dir is not None:
        from shellfem.outfiles import OutputDir
        from geometry.cad import write_surface
        from forward.outputs import SURFACES
        files = out_dir if isinstance(out_dir, OutputDir) else \
            OutputDir(out_dir, ("deployed.vtu", *SURFACES, "verify.png"))
        paths = [files.write("deployed.vtu", lambda tmp: write_deployed_vtu(tmp, Xr, sim.sheet, pct))]
        paths += [files.write(n, lambda tmp: write_surface(tmp, Xr, sim.sheet.triangles)) for n in SURFACES]
        paths.append(files.write("verify.png", lambda tmp: plot_verify(d, Xr, sim.sheet.triangles, pct, tmp)))
        if written is not None:
            written += paths
    return out
