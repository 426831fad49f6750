"""Benchmark: every target refined to ~100k faces, time per stage of the flattening pipeline.

Prints one JSON line per target: faces, seconds per stage (load, refine, curvature, field,
tutte, slim, isometric, local_global), iterations, converged and the seed Table 5.1 columns.
Usage: python studies/bench_flattening.py [target.obj ...] [--faces 100000] [--lam 0] (default: every
meshes/targets/*.obj)
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import time

import numpy as np

from geometry.flattening import flatten_surface
from geometry.target import levels_for_faces, load_target, refine

TARGETS = os.path.join("meshes", "targets", "*.obj")     # relative to the repository root


def bench(path: str, faces: int = 100_000, lam: float = 0.0, slim_iterations: int = 2) -> dict:
    t0 = time.perf_counter()
    V, F = load_target(path)
    t1 = time.perf_counter()
    V, F = refine(V, F, levels_for_faces(len(F), faces))
    t2 = time.perf_counter()
    res, lf, _ = flatten_surface(V, F, lam=lam, slim_iterations=slim_iterations)
    stages = {"load": t1 - t0, "refine": t2 - t1, **res.times}
    iso_it = stages.pop("isometric_iterations", 0)
    flat_s = stages.get("isometric", 0.0) + stages["local_global"]
    return {
        "target": os.path.basename(path), "faces": int(len(F)), "vertices": int(len(V)), "lambda": lam,
        "seconds": {k: round(v, 3) for k, v in stages.items()},
        "flattening_s": round(flat_s, 3),
        "total_s": round(sum(stages.values()), 3),
        "iterations": res.iterations, "isometric_iterations": iso_it, "converged": res.converged,
        "k1_deviation_deg": round(res.k1_deviation_deg, 4),
        "sigma_bound_violation": [round(x, 5) for x in res.sigma_bound_violation],
        "sigma_out_of_bounds_pct": [round(x, 3) for x in res.sigma_out_of_bounds_pct],
        "residual_energy": float(f"{res.residual_energy:.4g}"),
        "flipped": res.flipped, "field_t": float(f"{lf.t:.4g}"),
        "sigma1_range": [round(float(res.sigma1.min()), 4), round(float(res.sigma1.max()), 4)],
        "sigma2_range": [round(float(res.sigma2.min()), 4), round(float(res.sigma2.max()), 4)],
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("targets", nargs="*")
    ap.add_argument("--faces", type=int, default=100_000)
    ap.add_argument("--lam", type=float, default=0.0)
    ap.add_argument("--slim", type=int, default=2)
    a = ap.parse_args(argv)
    for path in a.targets or sorted(glob.glob(TARGETS)):
        print(json.dumps(bench(path, a.faces, a.lam, a.slim)), flush=True)


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
