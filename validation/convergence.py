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
(-z). A flat start can end in a second, stable state of higher energy (with the solver of
commit 0623ede the 40 x 2 mm strip did: kappa_x 0.027, kappa_y 0.051 1/mm, energy +14 %),
and a convergence study must compare the same branch on every mesh. A wider gradient sheet
(40 x 8 mm) landed on two different stable twisted shapes on different meshes (same
solver, same start), hence 3 mm.

    python -m validation.convergence [--quick] [--out out/validation] [--figures docs/validation]

prints ONE JSON line, writes OUT/convergence.json and FIGURES/convergence.png.
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from shellfem.layers import sym_to_mat
from shellfem.materials import Fabric, Plastic
from shellfem.sheet import Sheet
from shellfem.boundary import gauge_dofs, smooth_perturbation
from shellfem.model import ShellModel
from shellfem.newton import newton
from shellfem.strip import strip_curvature
from validation.shell_cases import gmsh_rectangle

SIZES = (1.0, 0.7, 0.5, 0.35)          # mm, strip study
SIZES_GRADIENT = (1.0, 0.7, 0.5, 0.35)  # mm, gradient study (last = reference)
QUICK_SIZES = (1.0, 0.7, 0.5)
QUICK_SIZES_GRADIENT = (1.0, 0.7, 0.5)


def cartesian_forms(sheet: Sheet, a: np.ndarray, b: np.ndarray):
    """Edge-basis fundamental forms (m, 3) -> (m, 2, 2) matrices in printed x, y."""
    P = sheet.points[sheet.triangles]
    Ei = np.linalg.inv(np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]], 2))
    to_xy = lambda s: np.einsum("mji,mjk,mkl->mil", Ei, sym_to_mat(s), Ei)   # noqa: E731
    return to_xy(a), to_xy(b)


def triangle_areas(sheet: Sheet) -> np.ndarray:
    P = sheet.points[sheet.triangles]
    e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def observed_order(h, err) -> float:
    """Least-squares slope of log(err) against log(h)."""
    return float(np.polyfit(np.log(np.asarray(h, float)), np.log(np.asarray(err, float)), 1)[0])


def sphere_start(points: np.ndarray, kappa: float) -> np.ndarray:
    """Printed points (n, 2) wrapped isometrically along x onto a sphere of curvature kappa
    (1/mm) centred below the sheet's centre (-z): x -> longitude, y -> latitude."""
    c = 0.5 * (points.min(0) + points.max(0))
    R = 1.0 / kappa
    psi, phi = (points[:, 0] - c[0]) / R, (points[:, 1] - c[1]) / R
    return np.column_stack([R * np.cos(phi) * np.sin(psi), R * np.sin(phi), R * (np.cos(phi) * np.cos(psi) - 1)])


def release(sheet: Sheet, fabric: Fabric, plastic: Plastic, kappa_start: float, seed: int = 0):
    """Free equilibrium from sphere_start(kappa_start) + a seeded 0.1 % perturbation.
    Returns (model, SolveResult); raises RuntimeError if not converged."""
    M = ShellModel.from_materials(sheet, fabric, plastic, gravity=False)
    q = M.initial_state()
    x, _ = M.split(q)
    size = float(np.linalg.norm(np.ptp(sheet.points, 0)))
    x[:] = sphere_start(sheet.points, kappa_start)
    x[:, 2] += smooth_perturbation(sheet.points, seed, 1e-3 * size)
    free = np.ones(M.n_dofs, bool)
    free[gauge_dofs(x, np.zeros(0, np.int64))] = False
    r = newton(M, q, free, max_iterations=400)
    if not r.converged:
        raise RuntimeError(f"release of a {sheet.n_triangles}-triangle sheet: {r.reason}")
    return M, r


def narrow_curvature(fabric: Fabric, plastic: Plastic, plastic_thickness: float) -> float:
    """Closed-form narrow-strip curvature (1/mm) of shellfem.strip for these materials."""
    return float(strip_curvature(plastic_thickness, fabric.thickness, fabric.stretch[0],
                                 plastic.young_modulus / fabric.young_modulus,
                                 plastic_poisson=plastic.poisson, fabric_poisson=fabric.poisson))


def strip_case(size: float, length: float = 40.0, width: float = 2.0, stretch: float = 1.05,
               plastic_thickness: float = 0.3, seed: int = 0) -> dict:
    """Released free bilayer strip on a Gmsh mesh of target edge ``size``: longitudinal
    curvature (1/mm, > 0 when concave on the fabric side) area-averaged over the middle half."""
    sh = gmsh_rectangle(length, width, size)
    sh = Sheet(sh.points, sh.triangles, thickness_front=np.full(sh.n_triangles, plastic_thickness))
    fabric, plastic = Fabric(stretch=stretch), Plastic()
    t0 = time.perf_counter()
    M, r = release(sh, fabric, plastic, 0.5 * narrow_curvature(fabric, plastic, plastic_thickness), seed)
    A, B = cartesian_forms(sh, *M.fundamental_forms(r.q))
    c = sh.points[sh.triangles].mean(1)
    mid = np.abs(c[:, 0] - length / 2) < length / 4
    w = triangle_areas(sh)[mid]
    kx = -B[mid, 0, 0] / A[mid, 0, 0]
    return {"size_mm": size, "n_triangles": sh.n_triangles, "curvature_per_mm": float(np.sum(w * kx) / w.sum()),
            "newton_iterations": r.iterations, "seconds": round(time.perf_counter() - t0, 2)}


def gradient_case(size: float, length: float = 40.0, width: float = 3.0, t0: float = 0.15, t1: float = 0.45,
                  stretch: float = 1.05, seed: int = 0):
    """Released free sheet with plastic thickness t0 + (t1 - t0) x / length (per triangle at
    its centroid) on a Gmsh mesh of target edge ``size``. Returns (sheet, deployed positions, info)."""
    sh = gmsh_rectangle(length, width, size)
    cx = sh.points[sh.triangles].mean(1)[:, 0]
    sh = Sheet(sh.points, sh.triangles, thickness_front=t0 + (t1 - t0) * cx / length)
    tic = time.perf_counter()
    fabric, plastic = Fabric(stretch=stretch), Plastic()
    M, r = release(sh, fabric, plastic, 0.5 * narrow_curvature(fabric, plastic, 0.5 * (t0 + t1)), seed)
    x = M.split(r.q)[0]
    tip = x[np.argmax(sh.points[:, 0])] - x[np.argmin(sh.points[:, 0])]
    return sh, x, {"size_mm": size, "n_triangles": sh.n_triangles, "end_to_end_mm": float(np.linalg.norm(tip)),
                   "newton_iterations": r.iterations, "seconds": round(time.perf_counter() - tic, 2)}


def rigid_align(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """X moved by the rotation + translation that best fits it to Y (Kabsch, least squares)."""
    from inverse.registration import kabsch
    R, t = kabsch(X, Y)
    return X @ R.T + t


def rms_to_reference(sheet: Sheet, x: np.ndarray, ref_sheet: Sheet, ref_x: np.ndarray) -> float:
    """RMS distance (mm) between deployed positions x and the reference solution linearly
    interpolated at the same printed points, after the best rigid alignment."""
    from matplotlib.tri import LinearTriInterpolator, Triangulation
    tri = Triangulation(ref_sheet.points[:, 0], ref_sheet.points[:, 1], ref_sheet.triangles)
    p = sheet.points
    y = np.column_stack([np.asarray(LinearTriInterpolator(tri, ref_x[:, k])(p[:, 0], p[:, 1]).filled(np.nan))
                         for k in range(3)])
    ok = np.isfinite(y).all(1)
    return float(np.sqrt(np.mean(np.sum((rigid_align(x[ok], y[ok]) - y[ok]) ** 2, axis=1))))


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
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 coarser meshes per study")
    ap.add_argument("--out", default="out/validation")
    ap.add_argument("--figures", default="docs/validation")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    out = run(a.quick)
    out["figure"] = plot(out, os.path.join(a.figures, "convergence.png"))
    out["seconds"] = round(time.perf_counter() - t0, 1)
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "convergence.json"), "w") as fh:
        json.dump(out, fh, indent=2)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
