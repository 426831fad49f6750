"""Mesh-convergence study of the shell engine on unstructured Gmsh meshes (mm, N, MPa).

(a) Free bilayer strip (40 x 2 mm, plastic 0.3 mm over the whole strip, fabric 0.8 mm,
    default Fabric/Plastic, pre-stretch 1.05): the longitudinal curvature -B_xx / A_xx
    (printed Cartesian frame, area-weighted over the middle half) at 4 mesh sizes, against
    the closed-form narrow-strip value of shellfem.strip.strip_curvature and against the
    Richardson limit of the two finest meshes.
(b) Free sheet with a thickness gradient (40 x 3 mm, plastic thickness linear in x from
    0.15 to 0.45 mm, per triangle at its centroid; pre-stretch 1.05): RMS distance of the
    deployed vertex positions to the finest mesh's (interpolated at the same printed
    points, after the best rigid alignment), at 3 sizes against a 4th, finest one.
Observed order = slope of log(error) against log(mesh size) (least squares).

Every solve starts from the same smooth guess on every mesh: the printed sheet wrapped on
a sphere of curvature 1/2 of the closed-form narrow-strip value, bending towards the fabric
(-z). A flat start can end in a second, stable state of higher energy, and a convergence
study must compare the same branch on every mesh. A wider gradient sheet
(40 x 8 mm) landed on two different stable twisted shapes on different meshes (same
solver, same start), hence 3 mm. Cases: validation.shell_cases.strip_case, gradient_case;
reference: validation.references.narrow_curvature; measures: validation.measures.

    python studies/convergence.py [--quick] [--out out/validation] [--figures docs/validation]

prints ONE JSON line, writes OUT/convergence.json and FIGURES/convergence.png.
"""
from __future__ import annotations

import os
import time

import numpy as np

from shellfem.materials import Fabric, Plastic
from validation.measures import observed_order, rms_to_reference
from validation.references import narrow_curvature
from validation.shell_cases import gradient_case, strip_case

from study_cli import study_arguments, write_result

SIZES = (1.0, 0.7, 0.5, 0.35)          # mm, strip study
SIZES_GRADIENT = (1.0, 0.7, 0.5, 0.35)  # mm, gradient study (last = reference)
QUICK_SIZES = (1.0, 0.7, 0.5)
QUICK_SIZES_GRADIENT = (1.0, 0.7, 0.5)


def run(quick: bool = False) -> dict:
    sizes = QUICK_SIZES if quick else SIZES
    closed = narrow_curvature(Fabric(stretch=1.05), Plastic(), 0.3)
    strips = [strip_case(s) for s in sizes]
    k = np.array([r["curvature_per_mm"] for r in strips])
    h = np.array(sizes)
    rich = float(k[-1] + (k[-1] - k[-2]) * h[-1] / (h[-2] - h[-1]))       # first-order Richardson
    for r in strips:
        r["error_vs_closed_form"] = r["curvature_per_mm"] / closed - 1
        r["error_vs_richardson"] = r["curvature_per_mm"] / rich - 1
    # the closed form is the zero-width limit: the 2 mm strip's own limit lies ~0.15 % below it
    strip_out = {"closed_form_narrow_per_mm": closed, "richardson_limit_per_mm": rich,
                 "richardson_vs_closed_form": rich / closed - 1, "meshes": strips,
                 "observed_order_vs_richardson": observed_order(h[:-1], np.abs(k[:-1] - rich))}

    gsizes = QUICK_SIZES_GRADIENT if quick else SIZES_GRADIENT
    cases = [gradient_case(s) for s in gsizes]
    ref_sheet, ref_x, ref_info = cases[-1]
    grad = []
    for sh, x, info in cases[:-1]:
        info["rms_to_finest_mm"] = rms_to_reference(sh, x, ref_sheet, ref_x)
        grad.append(info)
    gh = np.array([g["size_mm"] for g in grad])
    ge = np.array([g["rms_to_finest_mm"] for g in grad])
    grad_out = {"reference": ref_info, "meshes": grad, "observed_order": observed_order(gh, ge)}
    return {"study": "mesh convergence (unstructured gmsh)", "quick": quick, "strip": strip_out,
            "thickness_gradient": grad_out}


def plot(out: dict, path: str) -> str:
    import matplotlib.pyplot as plt

    from validation.plots import save_figure
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    fig.subplots_adjust(left=0.1, right=0.98, bottom=0.13, top=0.9, wspace=0.28)
    s = out["strip"]
    h = np.array([m["size_mm"] for m in s["meshes"]])
    k = np.array([m["curvature_per_mm"] for m in s["meshes"]])
    ax = axes[0]
    ax.plot(h, k, "o-", label="engine, Gmsh meshes")
    ax.axhline(s["closed_form_narrow_per_mm"], color="k", ls="--", lw=1, label="closed form (zero-width strip)")
    ax.axhline(s["richardson_limit_per_mm"], color="C1", ls=":", lw=1.5,
               label=f"Richardson limit (order {s['observed_order_vs_richardson']:.2f})")
    ax.set_xscale("log")
    ax.set_title("(a) free 40 x 2 mm bilayer strip: curvature", fontsize=10)
    ax.set_xlabel("mesh size (mm)")
    ax.set_ylabel("curvature (1/mm)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    g = out["thickness_gradient"]
    gh = np.array([m["size_mm"] for m in g["meshes"]])
    ge = np.array([m["rms_to_finest_mm"] for m in g["meshes"]])
    ax = axes[1]
    ax.loglog(gh, ge, "o-", label=f"observed order {g['observed_order']:.2f}")
    ax.loglog(gh, ge[-1] * gh / gh[-1], ":", color="grey", label="slope 1")
    ax.set_title(f"(b) thickness gradient: RMS to the {g['reference']['size_mm']} mm mesh", fontsize=10)
    ax.set_xlabel("mesh size (mm)")
    ax.set_ylabel("RMS position difference (mm)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def main(argv=None) -> dict:
    from shellfem.memory import keep_freed_memory
    keep_freed_memory()
    a = study_arguments(__doc__, "3 coarser meshes per study", argv)
    t0 = time.perf_counter()
    out = run(a.quick)
    out["figure"] = plot(out, os.path.join(a.figures, "convergence.png"))
    out["seconds"] = round(time.perf_counter() - t0, 1)
    write_result(a.out, "convergence", out, out)
    return out


if __name__ == "__main__":
    main()
