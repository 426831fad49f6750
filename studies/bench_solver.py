"""Form-finding benchmark: a ~10,000-vertex sheet with a dense printed pattern to equilibrium.

The seed's C++ solver took 17-40 minutes for 7,000-12,000 vertices (seed Table 3.1).
Case (validation.cases.star_benchmark): a uniform 3-pointed-star tiling (spacing 10 mm, arms
7 x 0.8 mm, 0.3 mm TPU on the front, E_plastic / E_fabric = 3.2e3 as the seed's chapter 3
calibrated for its star sheets) on an 85 x 60 mm fabric at s = 1.35, meshed with one triangle across each arm
(``[mesh] across = 1``), free boundary: it rolls into a tube (seed Fig. 3.2).
Solved as ``selfshape simulate`` solves it: nested iteration from coarser meshes of the same
pattern (shellfem.multilevel; ``--coarse-levels 0`` for the single mesh). Prints ONE JSON line:
sizes, Newton iterations (summed over the levels, and per level), wall time (``total_s``
includes meshing every level), and the per-iteration split (assembly vs factorisation vs line
search). Target: under 60 s on 2 cores.

Run: python studies/bench_solver.py [--width 85 --height 60 --across 1] [--fabric-bending-stiffness K]
     [--coarse-levels auto|N] [--contact | --compare-contact]

``--compare-contact`` solves the case twice in one process, without and with self-contact, and
adds per run the CPU time (s, all threads), the energy (N mm) and the pairs of triangles that pass
through each other over all pairs sharing no vertex (tests/test_contact.intersecting_pairs: an
exact test independent of ipctk), and the with / without ratios of wall and CPU time. The default
85 x 60 mm sheet closes past a full turn at one end (its edges meet: a contact problem);
130 x 38 mm (12k vertices) rolls less than a turn and its edges stay apart all the way, so it
measures what contact costs a sheet that never touches itself.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from shellfem.newton import DEFAULT_METRIC_FLOOR
from validation.cases import star_benchmark


def run(width: float = 85.0, height: float = 60.0, across: float = 1.0, max_iterations: int = 300,
        fabric_bending_stiffness: float | None = None, seed: int = 0,
        metric_floor: float = DEFAULT_METRIC_FLOOR, coarse_levels="auto", contact: bool = False,
        keep: dict | None = None) -> dict:
    """The benchmark's numbers; ``keep``: a dict that receives the "simulation" and the "pattern"
    (for measures of the deployed shape, studies/rods_vs_shell.py)."""
    import os
    import tempfile

    from geometry.meshing import coarse_meshes, mesh_pattern
    from geometry.patterns import load_pattern, write_pattern
    from forward.simulate import simulate_sheet

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "bench.toml")
        write_pattern(path, star_benchmark(width, height, across, fabric_bending_stiffness, seed, metric_floor))
        pat = load_pattern(path)
    t0 = time.perf_counter()
    sheet = mesh_pattern(pat)
    t_mesh = time.perf_counter() - t0
    t0 = time.perf_counter()
    coarse = coarse_meshes(pat, sheet.n_vertices, levels=coarse_levels)
    t_coarse = time.perf_counter() - t0
    sim = simulate_sheet(sheet, pat.fabric, pat.plastic, pat.supports, seed=pat.seed, max_iterations=max_iterations,
                         metric_floor=pat.metric_floor, coarse=coarse, contact=contact)
    if keep is not None:
        keep.update(simulation=sim, pattern=pat)
    r = sim.result
    tm = r.timings
    its = max(r.iterations, 1)
    k, H, K = sim.model.curvatures(r.q)
    kabs = np.sort(np.abs(k), axis=1)
    return {
        "case": f"stars {width:g}x{height:g} mm, across={across:g}",
        "fabric_bending_stiffness_nmm": float(pat.fabric.bending_stiffness), "seed": int(pat.seed),
        "metric_floor": pat.metric_floor,
        "n_vertices": int(sheet.n_vertices), "n_triangles": int(sheet.n_triangles), "n_dofs": int(sim.model.n_dofs),
        "converged": bool(r.converged), "reason": r.reason, "newton_iterations": int(r.iterations),
        "mesh_s": round(t_mesh, 2), "coarse_mesh_s": round(t_coarse, 2),
        "solve_wall_s": round(sim.wall_time_s, 2),
        "total_s": round(t_mesh + t_coarse + sim.wall_time_s, 2),
        "levels": tm.get("levels", []),
        "assembly_s": round(tm["assembly"], 2), "factorisation_s": round(tm["factorisation"], 2),
        "line_search_s": round(tm["line_search"], 2), "factorisations": int(tm["factorisations"]),
        "negative_curvature_search_s": round(tm.get("negative_curvature_search", 0.0), 2),
        "angle_relaxation_s": round(tm.get("angle_relaxation", 0.0), 2),
        "angle_iterations": int(tm.get("angle_iterations", 0)),
        "printed_relaxation_s": round(tm.get("printed_relaxation", 0.0), 2),
        "printed_relaxations": int(tm.get("printed_relaxations", 0)),
        "newton_steps": int(tm.get("newton_steps", 0)), "projected_steps": int(tm.get("projected_steps", 0)),
        "regularised_steps": int(tm.get("regularised_steps", 0)),
        "per_iteration_s": {"assembly": round(tm["assembly"] / its, 3),
                            "factorisation": round(tm["factorisation"] / its, 3),
                            "line_search": round(tm["line_search"] / its, 3),
                            "angle_relaxation": round(tm.get("angle_relaxation", 0.0) / its, 3),
                            "printed_relaxation": round(tm.get("printed_relaxation", 0.0) / its, 3)},
        "setup_s": round(sim.wall_time_s - tm["total"], 2),
        "median_abs_curvature_ratio": round(float(np.median(kabs[:, 0] / np.maximum(kabs[:, 1], 1e-12))), 3),
        "target_s": 60.0,
        "contact": {k: v for k, v in sim.summary()["contact"].items()},
        "contact_builds": int(sim.model.contact.builds) if sim.model.contact is not None else 0,
        "contact_skips": int(sim.model.contact.skips) if sim.model.contact is not None else 0,
        "contact_cuts": int(tm.get("contact_cuts", 0)),
    }


def compare_contact(width: float = 85.0, height: float = 60.0, across: float = 1.0, max_iterations: int = 300,
                    fabric_bending_stiffness: float | None = None, seed: int = 0,
                    metric_floor: float = DEFAULT_METRIC_FLOOR, coarse_levels="auto") -> dict:
    """:func:`run` without and then with self-contact: {"off": ..., "on": ..., "wall_ratio", "cpu_ratio"},
    each run with ``cpu_s``, ``energy_nmm`` and ``crossing_pairs`` added (see the module's docstring)."""
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
    from test_contact import intersecting_pairs
    run(20.0, 15.0, across, 50, fabric_bending_stiffness, seed, metric_floor, coarse_levels, contact=True)  # warm-up:
    # loads the compiled kernels and the contact library once, so neither timed run pays for it
    out = {}
    for tag in ("off", "on"):
        keep = {}
        c0 = time.process_time()
        r = run(width, height, across, max_iterations, fabric_bending_stiffness, seed, metric_floor, coarse_levels,
                contact=tag == "on", keep=keep)
        r["cpu_s"] = round(time.process_time() - c0, 2)
        sim = keep["simulation"]
        r["energy_nmm"] = float(sim.result.energy)
        r["crossing_pairs"] = int(len(intersecting_pairs(sim.positions, sim.sheet.triangles)))
        r["load_1min_after"] = round(os.getloadavg()[0], 2)
        out[tag] = r
    out["wall_ratio"] = round(out["on"]["total_s"] / out["off"]["total_s"], 3)
    out["cpu_ratio"] = round(out["on"]["cpu_s"] / out["off"]["cpu_s"], 3)
    return out


def main(argv=None):
    from shellfem.memory import keep_freed_memory
    keep_freed_memory()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=float, default=85.0)
    ap.add_argument("--height", type=float, default=60.0)
    ap.add_argument("--across", type=float, default=1.0)
    ap.add_argument("--max-iterations", type=int, default=300)
    ap.add_argument("--fabric-bending-stiffness", type=float, default=None,
                    help="fabric k_B, N mm (default: the measured 0.0192; raising it tests how much of the "
                         "iteration count the soft bare fabric costs)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the symmetry-breaking perturbation")
    ap.add_argument("--metric-floor", type=float, default=DEFAULT_METRIC_FLOOR,
                    help="trust-region metric floor ([solver] metric_floor, default 10; 0: plain Marquardt scaling)")
    ap.add_argument("--coarse-levels", default="auto",
                    help="coarser meshes solved first (nested iteration): 'auto' (default) or a number, 0 = none")
    ap.add_argument("--contact", action="store_true",
                    help="self-contact on (shellfem.contact; as selfshape simulate has it by default)")
    ap.add_argument("--compare-contact", action="store_true",
                    help="solve without and then with self-contact in one process; one JSON line with both runs, "
                         "their crossing pairs and the time ratios")
    a = ap.parse_args(argv)
    levels = a.coarse_levels if a.coarse_levels == "auto" else int(a.coarse_levels)
    if a.compare_contact:
        print(json.dumps(compare_contact(a.width, a.height, a.across, a.max_iterations, a.fabric_bending_stiffness,
                                         a.seed, a.metric_floor, levels)))
        return
    print(json.dumps(run(a.width, a.height, a.across, a.max_iterations, a.fabric_bending_stiffness, a.seed,
                         a.metric_floor, levels, a.contact)))


if __name__ == "__main__":
    main()
