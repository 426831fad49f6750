"""The seed's chapter-3 rods model beside the shell model on the gallery's cases (issue 22).

Each case of validation.cases.GALLERY_CASES is simulated with [solver] model = "shell" (the
default: printed areas as bilayer shell regions) and model = "rods" (rods on the centre lines
of the stars' arms and the ribbons, bare fabric; shellfem.rods), and measured with
validation.measures.gallery_measure. Prints ONE JSON line: per case and model the measures,
Newton iterations, vertices, convergence and wall time (s).
Run: python studies/rods_vs_shell.py [--only NAME ...] [--models shell rods]
"""
from __future__ import annotations

import argparse
import copy
import json
import time

from validation.cases import GALLERY_CASES
from validation.measures import gallery_measure


def run(names=None, models=("shell", "rods"), max_iterations=400):
    from forward.simulate import simulate
    from geometry.patterns import parse_pattern
    out = {}
    for name in names or list(GALLERY_CASES):
        out[name] = {}
        for model in models:
            raw = copy.deepcopy(GALLERY_CASES[name]())
            raw.setdefault("solver", {})["model"] = model
            t0 = time.perf_counter()
            sim = simulate(parse_pattern(raw, f"{name} ({model})"), max_iterations=max_iterations)
            row = {"converged": bool(sim.result.converged), "newton_iterations": int(sim.result.iterations),
                   "n_vertices": int(sim.sheet.n_vertices), "wall_s": round(time.perf_counter() - t0, 1)}
            row.update(gallery_measure(name, sim))
            out[name][model] = row
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", default=None, choices=list(GALLERY_CASES))
    ap.add_argument("--models", nargs="*", default=["shell", "rods"], choices=["shell", "rods"])
    a = ap.parse_args()
    print(json.dumps(run(a.only, a.models)))
