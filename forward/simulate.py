"""Form-finding: a pattern becomes a mesh, a shell model and its released equilibrium.

    from forward.simulate import simulate
    result = simulate(load_pattern("examples/strip.toml"))
    result.positions            # (n, 3) deployed vertex positions, mm

``simulate_pattern_file`` is the ``selfshape simulate`` verb: it writes deployed.vtu,
summary.json (forward.outputs) and deployed.png (forward.render) (mm, N). The supports a
pattern states are turned into held DOFs in forward.supports.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np

from shellfem.errors import SelfshapeError, check_number
from forward.outputs import write_cad, write_vtu
from forward.supports import carry_support_motion, support_constraints
from geometry.meshops import signed_areas
from shellfem.boundary import (gauge_dofs, gauge_reaction, graph_laplacian, harmonic_extension, lifted_perturbation,
                               smooth_perturbation)
from shellfem.layers import RHO_FOLDED, RHO_TRUNCATED
from shellfem.model import ShellModel
from shellfem.multilevel import prolongate
from shellfem.sheet import Sheet
from shellfem.newton import MAX_ITERATIONS_REASON, SolveResult, newton

COARSE_RTOL = 1e-5      # gradient tolerance of the coarse levels of nested iteration (relative)
#: Newton cap of an intermediate release step: max(this, max_iterations // steps). Only the last
#: step's equilibrium is the result; the others guide the path, and one need not be reached: the
#: second of 8 steps of examples/stars_tube.toml (14,317 vertices, with contact) crept on for 280
#: iterations (~3 s each) towards an equilibrium the next step's misfit moves anyway.
INTERMEDIATE_STEP_ITERATIONS = 100
#: Energy (N mm) the rigid-motion gauge may free and still count as carrying no load: 1e-9 of the
#: equilibrium energy, at least this floor (1e-18 J), so that round-off at a sheet with nothing to
#: release (stretch 1: E ~ 1e-28 N mm) is not reported as a constrained, non-converged shape.
GAUGE_ENERGY_FLOOR_NMM = 1e-15


@dataclass
class Simulation:
    sheet: Sheet
    model: ShellModel
    result: SolveResult
    fixed: np.ndarray        # held DOF indices (supports), excluding the gauge
    gauge: np.ndarray        # DOFs held only to remove rigid motions
    wall_time_s: float

    @property
    def positions(self) -> np.ndarray:
        return self.model.split(self.result.q)[0]

    def contact_report(self) -> dict:
        """The contact state of the result (shellfem.contact.Contact.report): enabled (self-contact),
        ground (height mm or None), min_distance_mm (smallest distance between non-excluded parts
        within the barrier's band, None when no pair is), active_pairs, offset_mm, the lowest free
        vertex's height above the ground, and in_contact (m,) bool per triangle."""
        c = getattr(self.model, "contact", None)
        m = self.sheet.n_triangles
        if c is None:
            return dict(enabled=False, ground=None, min_distance_mm=None, active_pairs=0,
                        in_contact=np.zeros(m, bool))
        rep = c.report(self.positions)
        return dict(enabled=bool(c.self_contact), ground=c.ground, offset_mm=c.offset, band_mm=c.dhat,
                    exclusion_mm=c.exclusion_mm, **rep)

    def fibre_report(self) -> dict:
        """max_fibre_kz: the largest |k z| of a printed fibre; fold_stop: the printed triangles
        bent past the thin-shell range (|k z| >= 0.9, RHO_TRUNCATED), where the layers' energy is
        the truncated metric's and the fold stop holds them (shellfem.layers): their number, their
        printed-state area (mm^2) and its share of the printed area."""
        rho = self.model.fibre_bending(self.result.q)
        held = rho >= RHO_TRUNCATED
        area = np.abs(signed_areas(self.sheet.points, self.sheet.triangles))
        printed = self.model.quad.thick
        return {"max_fibre_kz": float(np.sqrt(rho.max(initial=0.0))),
                "fold_stop": {"triangles": int(held.sum()), "area_mm2": float(area[held].sum()),
                              "share_of_print": float(area[held].sum() / area[printed].sum()) if held.any() else 0.0}}

    def summary(self) -> dict:
        x = self.positions
        r = self.result
        return {
            "converged": bool(r.converged),
            "reason": r.reason,
            "stable": bool(r.stable),
            "newton_iterations": int(r.iterations),
            "model": getattr(self.model, "kind", "shell"),
            "energy": float(r.energy),
            "gradient_norm": float(r.gradient_norm),
            "wall_time_s": round(self.wall_time_s, 3),
            "n_vertices": int(self.sheet.n_vertices),
            "n_triangles": int(self.sheet.n_triangles),
            "n_dofs": int(self.model.n_dofs),
            "bbox_mm": [float(v) for v in (x.max(0) - x.min(0))],
            **(self.fibre_report() if hasattr(self.model, "fibre_bending") else {}),
            "contact": {k: v for k, v in self.contact_report().items() if k != "in_contact"},
            "timings_s": {k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.timings.items()},
            **({"n_rod_edges": int(len(self.model.rods.edges)), "n_rod_stencils": int(len(self.model.rods.weight))}
               if getattr(self.model, "kind", "shell") == "rods" else {}),
        }


def contact_offset(sheet: Sheet, fabric) -> float:
    """The contact offset (mm): the sheet's largest total thickness (fabric + plastic on both
    faces), the distance two surfaces of the sheet keep apart (shellfem.contact)."""
    return float(fabric.thickness + np.max(sheet.thickness_front + sheet.thickness_back))


def support_plane(sheet: Sheet, fabric, ground: float | None) -> float:
    """The z (mm) at which supports that stand on the table hold the sheet (fix = "z", and "xyz"
    at relaxed positions): 0 without a ground; with one, the top of the ground barrier's band,
    ``ground`` + band (shellfem.contact.BAND_FRACTION x the offset), where the barrier exerts no
    force. Why not on the plane itself: the barrier is +inf there, so a held vertex on the plane
    forces its free neighbours up to where the barrier balances the sheet (most of the band,
    0.2 mm on the gallery dome) within one edge: a step at every support, which folded the
    printed triangles next to the dome's rim (|k z| 6.7) and took the solve into a state 9 %
    higher in energy. At the band's top a sheet that presses on the table next to its support
    sinks into the band like any vertex resting on it, and one that rises from it is free."""
    if ground is None:
        return 0.0
    from shellfem.contact import BAND_FRACTION
    return float(ground) + BAND_FRACTION * contact_offset(sheet, fabric)


def make_contact(sheet: Sheet, fabric, fixed: np.ndarray, self_contact: bool, ground: float | None,
                 exclusion_mm: float | None = None):
    """shellfem.contact.Contact of a sheet (None when both are off): the offset is
    :func:`contact_offset`, the ground plane at ``ground`` (mm, None: no ground) under the
    vertices whose z is not held by ``fixed``; ``exclusion_mm``: a smaller printed-state exclusion
    than the sheet's own (a coarse level takes the finest level's, see :func:`simulate_sheet`)."""
    if not self_contact and ground is None:
        return None
    from shellfem.contact import Contact
    held_z = np.zeros(sheet.n_vertices, bool)
    held_z[fixed[fixed % 3 == 2] // 3] = True
    return Contact(sheet.points, sheet.triangles, contact_offset(sheet, fabric), stretch_max=float(max(fabric.stretch)),
                   self_contact=self_contact, ground=ground, held_z=held_z, exclusion_mm=exclusion_mm)


def _level_setup(sheet: Sheet, fabric, plastic, supports, seed: int, tol_support: float | None, start=None,
                 factory=None, contact: bool = False, ground: float | None = None, exclusion_mm: float | None = None):
    """(model, perturbed flat start, held DOFs, their values, gauge DOFs, free mask) of one mesh;
    ``start``: (n_vertices, 3) start positions instead of the perturbed flat state; ``factory``:
    (sheet, fabric, plastic) -> model (default ShellModel.from_materials, exact metric). ``contact``,
    ``ground``: see :func:`make_contact` (with a ground, supports that stand on the table hold the
    sheet at :func:`support_plane`, and the flat start is the held heights carried harmonically
    into the sheet plus shellfem.boundary.lifted_perturbation, above the plane)."""
    model = (factory or ShellModel.from_materials)(sheet, fabric, plastic)
    q = model.initial_state()
    x, _ = model.split(q)
    edge = np.linalg.norm(sheet.points[sheet.triangles[:, 1]] - sheet.points[sheet.triangles[:, 0]], axis=1)
    tol = tol_support if tol_support is not None else 2.0 * float(edge.max())
    fixed, values = support_constraints(sheet, supports, fabric, tol,
                                        plane_z=support_plane(sheet, fabric, ground))
    model.contact = make_contact(sheet, fabric, fixed, contact, ground, exclusion_mm)
    if start is not None:
        x[:] = np.asarray(start, dtype=float).reshape(x.shape)
    else:
        size = float(np.linalg.norm(sheet.points.max(0) - sheet.points.min(0)))
        if ground is not None:
            # above the plane: the held z at their values, carried harmonically into the sheet,
            # plus a seeded bubble that is 0 at them (no step at a support, see lifted_perturbation)
            zf = fixed[fixed % 3 == 2]
            held = np.zeros(sheet.n_vertices, bool)
            held[zf // 3] = True
            zv = values[np.isin(fixed, zf)]
            base = np.full(sheet.n_vertices, float(ground))
            if len(zf):
                hz = harmonic_extension(graph_laplacian(sheet.n_vertices, model.topo.edges), zf // 3, zv)[:, 0]
                base[held] = hz[held]
                base[~held] = np.maximum(hz[~held], ground)
            x[:, 2] = base + lifted_perturbation(sheet.points, sheet.triangles, model.topo.edges, held, seed,
                                                 0.01 * size, model.contact.dhat)
        else:
            x[:, 2] += smooth_perturbation(sheet.points, seed, 0.01 * size)
    gravity = model.external_force is not None
    from shellfem.boundary import rigid_modes
    gauge = np.zeros(0, dtype=np.int64)
    if gravity and not np.any(fixed % 3 == 2):
        raise SelfshapeError("gravity is on (areal_weight_n_per_mm2 > 0) but no [[support]] holds the sheet "
                             "in z: the sheet would fall")
    if len(fixed) == 0 or np.linalg.matrix_rank(rigid_modes(x)[fixed]) < 6:
        gauge = gauge_dofs(x, fixed)
    free = np.ones(model.n_dofs, bool)
    free[fixed] = False
    free[gauge] = False
    return model, q, fixed, values, gauge, free


def _release(sheet, model, q, fixed, values, free, fabric, plastic, steps, newton_options, verbose, progress=None,
             factory=None):
    """Continuation from the flat start q over ``steps`` release steps: (result, iterations);
    the intermediate steps' models from ``factory`` (as for _level_setup; ``model`` is the last
    step's), every one sharing the level's Contact (its stiffness and exclusion filter). The
    intermediate steps stop at INTERMEDIATE_STEP_ITERATIONS (or max_iterations // steps, if
    larger) and at a looser gradient tolerance: only the last step's equilibrium is the result."""
    from dataclasses import replace
    start = q[fixed].copy()
    sx, sy = fabric.stretch
    total_it = 0
    q_prev = None
    result = None
    for k in range(1, steps + 1):
        t = k / steps
        if progress is not None and steps > 1:
            progress({"stage": "release", "step": k, "steps": steps})
        fab_k = replace(fabric, stretch=(1 + (sx - 1) * t, 1 + (sy - 1) * t))
        pla_k = replace(plastic, rest_curvature=plastic.rest_curvature * t)
        model_k = model if k == steps else (factory or ShellModel.from_materials)(sheet, fab_k, pla_k)
        model_k.contact = model.contact
        plain = q.copy()
        plain[fixed] = start + (values - start) * t
        plain = carry_support_motion(model_k, plain, q, fixed, free)
        guess = plain
        if q_prev is not None and result is not None and result.converged:
            # secant predictor, kept only if it beats the previous equilibrium: extrapolating
            # a rolling motion linearly can push edge angles to the edge of the admissible set
            secant = q + (q - q_prev)
            secant[fixed] = plain[fixed]
            if model_k.energy(secant) < model_k.energy(plain) and _admissible(model_k, q, secant):
                guess = secant
        last = k == steps
        opts = dict(newton_options)
        if not last:
            opts["rtol"] = 1e-5
            cap = opts["max_iterations"]
            opts["max_iterations"] = min(cap, max(INTERMEDIATE_STEP_ITERATIONS, cap // steps))
        result = newton(model_k, guess, free, **opts)
        total_it += result.iterations
        if not result.converged and not last:
            if verbose:
                print(f"  release step {k}/{steps} did not converge ({result.reason}); continuing", flush=True)
        q_prev, q = q, result.q
        if verbose:
            print(f"release step {k}/{steps}: {result.iterations} iterations, |g| {result.gradient_norm:.2e}",
                  flush=True)
    return result, total_it


def _admissible(model, q_from, q_to) -> bool:
    """A guess q_to is admissible under contact when the straight move from q_from (an
    admissible state) reaches it without a contact (always without contact)."""
    return model.contact is None or model.step_fraction(q_from, q_to) >= 1.0


def simulate_sheet(sheet: Sheet, fabric, plastic, supports=(), *, seed: int = 0, max_iterations: int = 300,
                   release_steps: int = 1, tol_support: float | None = None, verbose: bool = False,
                   rtol: float = 1e-8, metric_floor: float | None = None, coarse=(), start=None,
                   progress=None, model_factory=None, contact: bool = False,
                   ground: float | None = None, metric_predictor: bool = True,
                   exclusion_mm: float | None = None) -> Simulation:
    """Released equilibrium of a meshed sheet (printed-state mm) with the given materials.

    The start is the flat printed state with a smooth out-of-plane perturbation of 1 % of
    the sheet size seeded by ``seed`` (the flat state is a saddle). The release is followed
    by continuation: the pre-stretch, the plastic set and any support motion ("xyz" supports
    at relaxed positions) are ramped over ``release_steps`` steps, each started from a secant
    prediction of the previous two equilibria (large rotations converge in far fewer Newton
    iterations along such a path). ``max_iterations`` bounds each step; newton_iterations in
    the result is the total. Only the final step's tolerance decides ``converged``.
    ``metric_floor``: the solver's trust-region metric floor (shellfem.newton.lm_metric; None: its default).

    ``coarse``: coarser Sheets of the same pattern, coarsest first (geometry.meshing.coarse_meshes):
    nested iteration (shellfem.multilevel). The release runs on the coarsest; each finer mesh
    starts from the previous equilibrium interpolated at its vertices (or from its own flat
    start if that interpolation has no finite energy, or if the previous level stopped for
    another reason than its iteration cap). Only the given sheet's solve decides
    ``converged``; iterations and timings are summed over the levels and
    ``timings["levels"]`` lists each level's vertices, iterations and seconds.

    ``start``: (n_vertices, 3) positions of the given sheet to start from instead of the
    perturbed flat state (a chosen branch of a multistable sheet, e.g. a slight roll); only
    without ``coarse``.

    Metric predictor: every level is solved with the printed layers' truncated metric a - 2 z b
    (shellfem.layers), and the given sheet's equilibrium of it starts a last solve with the exact
    Kirchhoff-Love metric (the model returned), which decides ``converged``. Why: the truncated
    energy is convex in the curvature, the exact one is not far from equilibrium (its
    third-form terms make the angle Hessian indefinite at the sharp kinks of an interpolated
    or flat start), and the two equilibria differ by O(kappa h) only. On the 10k-vertex star
    benchmark the direct exact solve took 423 iterations to a state of higher energy (465 N mm);
    the predictor reaches the exact equilibrium of the truncated one's branch (208.09 N mm) in
    52 + 23 + 16 + 12. A sheet without exact-metric layers (bare fabric) is solved once per level.
    ``timings["levels"]`` then has one more entry, its ``metric`` "exact" (the others "truncated";
    None on a bare sheet, which has no exact metric to choose). ``metric_predictor=False``: every
    level with the exact metric (no predictor), so that the fold stop acts from the start: under
    self-contact the truncated metric's convex curl creased printed triangles that contact then
    pressed flat (the 50 x 35 mm analogue of examples/stars_tube.toml: E 6.9e8 N mm at the exact
    stage's start), and the exact metric alone converged without a crossing (docs/notes.md, session 31).

    ``contact``: self-contact (shellfem.contact; off by default here, on by default for a
    pattern's :func:`simulate`); ``ground``: the height (mm) of a ground plane under the sheet,
    None for none; with one, "z" supports and "xyz" ones at relaxed positions hold the sheet at
    :func:`support_plane` (the top of the ground barrier's band), not at z = 0. A start that intersects, or a support below the ground, ends the solve
    unconverged with that reason; an interpolated start of nested iteration that intersects or
    comes closer than the offset is dropped for the level's flat start. ``exclusion_mm``: the
    printed distance within which parts of the sheet are never in contact (shellfem.contact;
    None: the finest mesh's own; a smaller value is raised to its minimum), on every level.

    ``progress``: called with a dict per event, for a progress display (the CLI's status line):
    {"stage": "level", "level", "levels", "n_vertices"} as each mesh level starts, {"stage":
    "release", "step", "steps"} per release step, {"stage": "newton", "iteration", "energy"
    (N mm), "gradient_norm" (N)} per accepted Newton step.

    ``model_factory``: (sheet, fabric, plastic) -> the energy to minimise, instead of
    ShellModel.from_materials (the rods model, shellfem.rods.coupled); single mesh only."""
    if start is not None and len(coarse):
        raise SelfshapeError("simulate_sheet: a start state is for a single mesh (no coarse levels)")
    if model_factory is not None and len(coarse):
        raise SelfshapeError("simulate_sheet: a model factory is for a single mesh (no coarse levels)")
    t0 = time.perf_counter()
    sheets = list(coarse) + [sheet]
    steps = max(1, int(release_steps))
    total_it = 0
    level_log = []
    sums = {}
    prev = None
    exact_model = ShellModel.from_materials(sheet, fabric, plastic) if model_factory is None else None
    printed = exact_model is not None and bool(exact_model.quad.thick.any())
    two_stage = printed and metric_predictor          # truncated predictor first

    # the metric of the loop's levels: "truncated" where the exact solve follows, "exact" without
    # the predictor, None for a bare sheet or another model (no metric to choose)
    level_metric = "truncated" if two_stage else ("exact" if printed else None)

    def factory(last):
        """The model of a level: the given factory, else the shell with the truncated metric
        wherever the exact one follows (every level exact without the predictor)."""
        if model_factory is not None:
            return model_factory
        exact = (last or not metric_predictor) and not two_stage
        return lambda sh, fab, pla: ShellModel.from_materials(sh, fab, pla, exact_metric=exact)

    def log_level(result, n_vertices, iterations, interpolated, t_level, metric):
        """Sum the level's numeric timings into ``sums`` and append its entry to ``level_log``."""
        for key, v in result.timings.items():
            if isinstance(v, (int, float)):
                sums[key] = sums.get(key, 0) + v
        level_log.append(dict(n_vertices=int(n_vertices), iterations=int(iterations),
                              converged=bool(result.converged), interpolated=bool(interpolated),
                              seconds=round(time.perf_counter() - t_level, 3), metric=metric))
    # the coarse levels resolve contact with the finest level's exclusion where it is smaller (their
    # longer edges give them a larger one): with their own, parts of a tight roll one turn apart
    # were excluded on a coarse level and passed through each other there, and the finer level's
    # interpolated start intersected itself (a flat restart)
    finest_exclusion = (make_contact(sheet, fabric, np.zeros(0, np.int64), True, None, exclusion_mm).exclusion_mm
                        if contact and len(sheets) > 1 else exclusion_mm)
    for j, sh in enumerate(sheets):
        t_level = time.perf_counter()
        last = j == len(sheets) - 1
        final = last and not two_stage          # this level's solve decides the result
        model, q, fixed, values, gauge, free = _level_setup(sh, fabric, plastic, supports, seed, tol_support,
                                                            start=start if last else None, factory=factory(last),
                                                            contact=contact, ground=ground,
                                                            exclusion_mm=exclusion_mm if last else finest_exclusion)
        opts = dict(max_iterations=max_iterations, verbose=verbose, metric_floor=metric_floor,
                    rtol=rtol if final else COARSE_RTOL)
        if progress is not None:
            progress({"stage": "level", "level": j + 1, "levels": len(sheets) + two_stage,
                      "n_vertices": int(sh.n_vertices)})
            opts["callback"] = lambda h: progress({"stage": "newton", "iteration": h["iteration"],
                                                   "energy": h["energy"], "gradient_norm": h["gradient_norm"]})
        guess = None
        if prev is not None:
            psheet, px = prev
            guess = model.initial_state()
            guess[:3 * sh.n_vertices] = prolongate(psheet.points, psheet.triangles, px, sh.points).ravel()
            guess[fixed] = values
            dropped = None
            if not np.isfinite(model.energy(guess)):
                dropped = "its energy is not finite"
            elif model.contact is not None:
                dropped = model.contact.check_start(model.split(guess)[0])   # intersects, or within the offset
            if dropped is not None:
                guess = None
                if verbose:
                    print(f"level {j + 1}/{len(sheets)}: the interpolated start is dropped ({dropped}); "
                          f"the level starts from its flat sheet", flush=True)
        if guess is None:
            result, its = _release(sh, model, q, fixed, values, free, fabric, plastic, steps, opts, verbose, progress,
                                   factory=factory(last))
        else:
            result = newton(model, guess, free, **opts)
            its = result.iterations
        total_it += its
        log_level(result, sh.n_vertices, its, guess is not None, t_level, level_metric)
        if verbose and len(sheets) > 1:
            print(f"level {j + 1}/{len(sheets)} ({sh.n_vertices} vertices): {its} iterations, "
                  f"{'converged' if result.converged else result.reason}", flush=True)
        # a coarse level that stopped for another reason than its iteration cap (e.g. the trust
        # region collapsed against the edge-angle barrier: a coarse mesh cannot bend as tightly
        # as the print asks) is no predictor: the next level starts over from its flat start
        usable = result.converged or result.reason == MAX_ITERATIONS_REASON
        prev = (sh, model.split(result.q)[0]) if usable else None
    if two_stage:
        # the exact metric from the truncated equilibrium (or, if that solve stopped for another
        # reason than its cap, from the same start the truncated solve had)
        t_level = time.perf_counter()
        exact_model.contact = model.contact          # the finest level's Contact (stiffness, exclusions)
        model = exact_model
        usable = result.converged or result.reason == MAX_ITERATIONS_REASON
        if usable:
            q_exact = result.q
        else:       # the supports at their positions, their motion carried as the release does
            q_exact = q.copy()
            q_exact[fixed] = values
            q_exact = carry_support_motion(model, q_exact, q, fixed, free)
        if progress is not None:
            progress({"stage": "level", "level": len(sheets) + 1, "levels": len(sheets) + 1,
                      "n_vertices": int(sheet.n_vertices), "metric": "exact"})
        if verbose:
            print("exact metric from the truncated-metric equilibrium", flush=True)
        opts["rtol"] = rtol
        # the problem's energy scale: where the truncated solve started (the released flat
        # sheet), not the near-equilibrium start of this one (round-off at stretch 1)
        scale = [abs(float(v)) for v in [result.energy] + [h["energy"] for h in result.history[:1]]
                 if np.isfinite(v)]
        opts["energy_reference"] = max(scale) if usable and scale else None
        result = newton(model, q_exact, free, **opts)
        total_it += result.iterations
        log_level(result, sheet.n_vertices, result.iterations, False, t_level, "exact")
    if printed:
        rho = model.fibre_bending(result.q)
        folded = int(np.count_nonzero(rho >= RHO_FOLDED))
        if result.converged and folded:
            result.converged = False
            result.reason = (f"{folded} printed triangles are bent to |k z| = {np.sqrt(rho.max()):.2f} (a fibre "
                             f"shortened to zero length, past the fold stop at |k z| = {np.sqrt(RHO_TRUNCATED):.1f}): "
                             "a folded state, not an elastic equilibrium")
    result.iterations = total_it
    if result.converged and len(fixed) and np.max(np.abs(result.q[fixed] - values)) > 1e-9 * (1.0 + np.abs(values).max()):
        result.converged = False
        result.reason = "the supports did not reach their positions: no equilibrium with them held there was found"
    if len(level_log) > 1:
        result.timings = {**sums, "levels": level_log}
    if result.converged and len(gauge):
        # the gauge must be pure: a held DOF carrying load means a constrained, wrong shape
        freed = gauge_reaction(model, result.q, gauge)
        result.timings["gauge_energy"] = freed
        # relative to the energy, with a floor of 1e-15 N mm: a sheet with nothing to release
        # (stretch 1) ends at E ~ 1e-28 N mm, where a round-off reaction of 1e-30 is no load
        if freed > max(1e-9 * abs(result.energy), GAUGE_ENERGY_FLOOR_NMM):
            result.converged = False
            result.reason = (f"the rigid-motion gauge carries load (releasing it frees {freed:.3g} N mm): "
                             "the shape is constrained, not free")
    return Simulation(sheet, model, result, fixed, gauge, time.perf_counter() - t0)


def _check_held(pattern) -> None:
    if pattern.fabric.areal_weight > 0 and not pattern.supports:
        # before meshing, naming the file and the key (simulate_sheet's own check names neither);
        # the reader accepts such a pattern: meshing, exporting or designing it needs no support
        raise SelfshapeError(f"{pattern.source}: [fabric] areal_weight_n_per_mm2 > 0 (gravity) needs a [[support]] "
                             f"that holds the sheet in z: without one the sheet falls")


def mesh_for_simulation(pattern, *, size_mm=None, coarse_levels=None) -> tuple:
    """(sheet, coarse): the meshes :func:`simulate` solves a shell pattern on, the conforming
    mesh (geometry.meshing.mesh_pattern) and its coarser levels for nested iteration, coarsest
    first; ``coarse_levels`` as for :func:`simulate`. Meshed once here, they can be simulated
    elsewhere (``simulate(pattern, meshed=...)`` in a worker) while this process works on the
    same mesh (the refinement of inverse.design_refine)."""
    from geometry.meshing import coarse_meshes, mesh_pattern
    if getattr(pattern, "solver_model", "shell") == "rods":
        raise SelfshapeError(f"{pattern.source}: [solver] model = \"rods\" is meshed by simulate itself")
    _check_held(pattern)
    sheet = mesh_pattern(pattern, size_mm=size_mm)
    levels = getattr(pattern, "coarse_levels", "auto") if coarse_levels is None else coarse_levels
    return sheet, coarse_meshes(pattern, sheet.n_vertices, size_mm=size_mm, levels=levels)


def simulate(pattern, *, size_mm=None, seed=None, max_iterations=None, verbose=False,
             coarse_levels=None, progress=None, meshed=None) -> Simulation:
    """Mesh a geometry.patterns.Pattern and compute its released equilibrium.

    coarse_levels (default: the pattern's [solver] coarse_levels, "auto"): coarser meshes of the
    pattern solved first (nested iteration, shellfem.multilevel); 0 solves the mesh alone.
    progress: as for simulate_sheet, and {"stage": "mesh"} before meshing. ``meshed``: the
    (sheet, coarse) of :func:`mesh_for_simulation` for this pattern, solved instead of meshing
    again (``size_mm`` and ``coarse_levels`` are then its own).

    [solver] model = "rods" (pattern.solver_model): the seed's chapter-3 model, rods on the
    centre lines of the stars' arms and the ribbons (the fabric mesh conforming to them,
    geometry.centrelines) on a bare fabric, with the effective monolayer's rest curvature
    (shellfem.rods); one mesh level."""
    _check_held(pattern)
    if progress is not None and meshed is None:
        progress({"stage": "mesh"})
    if getattr(pattern, "solver_model", "shell") == "rods":
        from geometry.centrelines import mesh_pattern_rods
        from shellfem.rods.coupled import rod_shell_model
        rm = mesh_pattern_rods(pattern, size_mm=size_mm)

        def factory(sheet, fabric, plastic):
            return rod_shell_model(sheet, fabric, plastic, rm.edges, rm.thickness, rm.width, side=rm.side)
        mi = max_iterations or pattern.max_iterations
        sim = simulate_sheet(rm.sheet, pattern.fabric, pattern.plastic, pattern.supports,
                             seed=pattern.seed if seed is None else seed, max_iterations=mi, verbose=verbose,
                             metric_floor=pattern.metric_floor, progress=progress, model_factory=factory,
                             release_steps=getattr(pattern, "release_steps", 1))
        return sim
    sheet, coarse = meshed if meshed is not None else \
        mesh_for_simulation(pattern, size_mm=size_mm, coarse_levels=coarse_levels)
    mi = max_iterations or pattern.max_iterations
    return simulate_sheet(sheet, pattern.fabric, pattern.plastic, pattern.supports,
                          seed=pattern.seed if seed is None else seed, max_iterations=mi, verbose=verbose,
                          metric_floor=pattern.metric_floor, coarse=coarse, progress=progress,
                          release_steps=getattr(pattern, "release_steps", 1), contact=getattr(pattern, "contact", True),
                          ground=getattr(pattern, "ground", None),
                          metric_predictor=getattr(pattern, "metric_predictor", True),
                          exclusion_mm=getattr(pattern, "contact_exclusion", None))


def simulate_pattern_file(pattern_path, out_dir, *, size_mm=None, seed=None, render=True, max_iterations=None,
                          verbose=False, coarse_levels=None, progress=None) -> dict:
    """`selfshape simulate`: writes DIR/deployed.vtu, deployed.obj/.stl/.ply, pattern.dxf/.svg
    (forward.outputs.write_cad), deployed.png (``render``), index.html (forward.view: the page
    to open in a browser), DIR/summary.json.

    The output folder is checked before the work (shellfem.outfiles.OutputDir: a file, an
    unwritable folder, a symbolic link at an output name or the pattern itself as an output
    is a one-line SelfshapeError); the files an earlier run left there (forward.outputs.OUTPUTS,
    no others) are removed before the simulation starts, so a rerun never mixes with them.
    Each file is written atomically and summary.json last: a folder with a summary.json is
    complete. A simulation whose numbers are not finite (e.g. a modulus of 1e300) is a
    SelfshapeError and writes nothing. On any failure, Ctrl-C included, nothing produced by
    this run is left (nor the folder, if this run created it). ``progress``: see simulate_sheet;
    also {"stage": "write"} before the files are written."""
    from geometry.patterns import load_pattern
    from forward.outputs import OUTPUTS
    from shellfem.outfiles import OutputDir
    if max_iterations is not None:
        check_number("simulate: max_iterations", max_iterations, 1)
    pattern = load_pattern(pattern_path)
    out = OutputDir(out_dir, OUTPUTS, inputs=[pattern_path])
    with out:
        sim = simulate(pattern, size_mm=size_mm, seed=seed, max_iterations=max_iterations, verbose=verbose,
                       coarse_levels=coarse_levels, progress=progress)
        r = sim.result
        if not (np.isfinite(r.energy) and np.isfinite(r.gradient_norm) and np.isfinite(sim.positions).all()):
            raise SelfshapeError(f"{pattern_path}: the simulation gave non-finite numbers (energy {r.energy:g} N mm, "
                                 f"|grad| {r.gradient_norm:g}): a value of the pattern is far outside the physical "
                                 f"range (a modulus, thickness or length such as 1e300?); nothing is written")
        summary = sim.summary()
        summary["pattern"] = os.path.abspath(str(pattern_path))
        summary["seed"] = pattern.seed if seed is None else seed
        if progress is not None:
            progress({"stage": "write"})
        out.write("deployed.vtu", lambda tmp: write_vtu(sim, tmp))
        write_cad(out, sim, pattern)
        if render:
            from forward.render import render_deployed
            out.write("deployed.png", lambda tmp: render_deployed(sim, tmp, title=os.path.basename(str(pattern_path))))
        from forward.view import folder_page
        out.write_text("index.html", folder_page(out.path, summary, target=False))     # the 3D page (forward.view)
        out.write_json("summary.json", summary)          # last: the folder is complete
        return summary
