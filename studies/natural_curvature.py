"""Shells with natural curvature: the disk's sphere-to-cylinder transition and the roll
of a wide bilayer sheet (mm, N, MPa).

- Disk (R = 10, h = 0.1, nu = 0.3, E = 1000) with isotropic rest curvature kappa0: principal
  curvatures of the central quadric over a sweep of kappa0 R^2 / h, against the
  uniform-curvature Ritz model (threshold 8 / (1 + nu)^1.5 = 5.40; Masters & Salamon
  1994, Freund 2000). The engine's threshold is bracketed by the last spherical
  (k_min / k_max > 0.9) and the first broken-symmetry state of the sweep (the transition
  is continuous: k_min / k_max = 0.99 at 5.5, 0.49 at 5.75 with 600 triangles, 0.52 with
  1536: the bracket does not move with the mesh).
- Wide bilayer (30 mm across the roll, plastic 0.3 mm over the whole sheet, default
  materials, pre-stretch 1.05): interior curvature against the plate value of
  shellfem.strip for axis lengths 40-120 mm (the deficit is a finite-length effect).

    python studies/natural_curvature.py [--quick] [--out out/validation] [--figures docs/validation]

prints ONE JSON line, writes OUT/natural_curvature.json and FIGURES/disk_bifurcation.png,
FIGURES/bilayer_roll.png.
"""
from __future__ import annotations

import os
import time

import numpy as np

from validation import shell_cases as sc
from validation.references import disk_ritz_curvatures, disk_ritz_threshold

from study_cli import study_arguments, write_result

DISK_SWEEP = (1.0, 2.0, 3.0, 4.0, 4.5, 5.0, 5.25, 5.5, 5.75, 6.0, 6.5, 8.0, 10.0, 13.0, 16.0)
QUICK_DISK_SWEEP = (2.0, 4.0, 5.0, 6.0, 8.0, 16.0)
ROLL_LENGTHS = (40.0, 60.0, 80.0, 120.0)
QUICK_ROLL_LENGTHS = (40.0, 80.0)


def disk_study(sweep=DISK_SWEEP, nu: float = 0.3) -> dict:
    runs = [sc.natural_curvature_disk(v, nu=nu) for v in sweep]
    sph = [r["kappa0_R2_over_h"] for r in runs if r["ratio"] > 0.9]
    cyl = [r["kappa0_R2_over_h"] for r in runs if r["ratio"] <= 0.9]
    bracket = [max(sph) if sph else None, min(cyl) if cyl else None]
    return {"nu": nu, "ritz_threshold": disk_ritz_threshold(nu), "engine_threshold_bracket": bracket, "runs": runs}


def roll_study(lengths=ROLL_LENGTHS, width: float = 30.0, size: float = 2.0) -> dict:
    runs = [sc.bilayer_roll(L, width, size) for L in lengths]
    for r in runs:
        r["deficit"] = 1 - r["k_max"] / r["k_plate"]
        r["length_over_sqrt_Rh"] = r["length"] / r["sqrt_Rh"]
    return {"width": width, "size_mm": size, "runs": runs}


def plot_disk(d: dict, path: str) -> str:
    from validation.plots import new_axes, save_figure
    fig, ax = new_axes(f"free disk with natural curvature (nu = {d['nu']})", "kappa0 R^2 / h",
                       "principal curvature / kappa0")
    v = np.array([r["kappa0_R2_over_h"] for r in d["runs"]])
    ax.plot(v, [r["k_max_over_kappa0"] for r in d["runs"]], "o", color="C0", label="engine, k_max")
    ax.plot(v, [r["k_min_over_kappa0"] for r in d["runs"]], "s", color="C1", label="engine, k_min")
    vv = np.linspace(0.2, v.max(), 200)
    ritz = np.array([disk_ritz_curvatures(x, d["nu"]) for x in vv])
    ax.plot(vv, ritz[:, 0], "-", color="C0", lw=1, label="Ritz (uniform curvature)")
    ax.plot(vv, ritz[:, 1], "-", color="C1", lw=1)
    ax.axvline(d["ritz_threshold"], color="grey", ls=":", lw=1)
    ax.axhline(1 + d["nu"], color="k", ls="--", lw=0.8, label="plate limit 1 + nu")
    ax.legend(fontsize=8, loc="center right")
    return save_figure(fig, path)


def plot_roll(d: dict, path: str) -> str:
    from validation.plots import new_axes, save_figure
    fig, ax = new_axes("wide bilayer roll: interior curvature vs axis length", "axis length / sqrt(R h)",
                       "k_interior / k_plate")
    x = [r["length_over_sqrt_Rh"] for r in d["runs"]]
    ax.plot(x, [r["k_max"] / r["k_plate"] for r in d["runs"]], "o-", label="engine")
    ax.axhline(1.0, color="k", ls="--", lw=0.8, label="plate value (shellfem.strip)")
    r0 = d["runs"][0]
    ax.axhline(r0["k_narrow"] / r0["k_plate"], color="grey", ls=":", lw=1, label="narrow-strip value")
    ax.legend(fontsize=8, loc="lower right")
    return save_figure(fig, path)


def main(argv=None) -> dict:
    a = study_arguments(__doc__, "shorter sweeps", argv)
    t0 = time.perf_counter()
    disk = disk_study(QUICK_DISK_SWEEP if a.quick else DISK_SWEEP)
    roll = roll_study(QUICK_ROLL_LENGTHS if a.quick else ROLL_LENGTHS)
    figs = [plot_disk(disk, os.path.join(a.figures, "disk_bifurcation.png")),
            plot_roll(roll, os.path.join(a.figures, "bilayer_roll.png"))]
    out = {"study": "natural curvature: disk transition and wide bilayer roll", "quick": a.quick,
           "disk": {"ritz_threshold": disk["ritz_threshold"],
                    "engine_threshold_bracket": disk["engine_threshold_bracket"],
                    "kappa0_R2_over_h": [r["kappa0_R2_over_h"] for r in disk["runs"]],
                    "ratio_kmin_kmax": [round(r["ratio"], 4) for r in disk["runs"]],
                    "k_max_over_kappa0": [round(r["k_max_over_kappa0"], 4) for r in disk["runs"]]},
           "roll": {"k_plate": roll["runs"][0]["k_plate"], "k_narrow": roll["runs"][0]["k_narrow"],
                    "lengths": [r["length"] for r in roll["runs"]],
                    "k_interior": [r["k_max"] for r in roll["runs"]],
                    "deficit": [round(r["deficit"], 4) for r in roll["runs"]]},
           "figures": figs, "seconds": round(time.perf_counter() - t0, 1)}
    write_result(a.out, "natural_curvature", {**out, "disk_runs": disk["runs"], "roll_runs": roll["runs"]}, out)
    return out


if __name__ == "__main__":
    main()
