"""Sze, Liu & Lo (2004) large-rotation benchmarks on the shell engine (mm, N, MPa).

- 3.1 end shear: cantilever L = 10, b = 1, h = 0.1, E = 1.2e6, nu = 0, transverse tip
  force up to P_max = 4 (40 x 2 quads split, 8 load steps); reference: the inextensible
  elastica (tip (3.289, 6.700) at P_max, Sze's value).
- 3.2 end moment: L = 12, M up to M_max = 50 pi / 3 (rolls into a full circle; 48 x 2
  quads, 16 steps); reference: the circular arc of curvature M / EI.
- 3.3 slit annular plate: R_i = 6, R_o = 10, t = 0.03, E = 21e6, nu = 0, line force up to
  q_max = 0.8 per unit length; published w_A = 13.891 (inner corner), w_B = 17.528 (outer)
  at q_max; structured polar meshes n_r x n_theta (quads split), first-order Richardson
  estimates of each consecutive pair of meshes.

    python studies/sze.py [--quick] [--out out/validation] [--figures docs/validation]

prints ONE JSON line, writes OUT/sze.json and FIGURES/sze_end_shear.png,
sze_end_moment.png, sze_slit_plate.png.
"""
from __future__ import annotations

import os
import time

import numpy as np

from validation import shell_cases as sc
from validation.references import SZE_B, SZE_E, SZE_END_MOMENT, SZE_END_SHEAR, SZE_H, SZE_SLIT, \
    elastica_end_moment, elastica_end_shear

from study_cli import study_arguments, write_result

SLIT_MESHES = ((4, 32), (6, 48), (8, 64), (10, 80))
QUICK_SLIT_MESHES = ((4, 32), (6, 48))


def _timed(f, *args, **kw):
    t0 = time.perf_counter()
    out = f(*args, **kw)
    out["seconds"] = round(time.perf_counter() - t0, 2)
    return out


def end_shear_study(nx: int = 40, steps: int = 8) -> dict:
    r = _timed(sc.end_shear, nx, steps)
    L, P = SZE_END_SHEAR["L"], SZE_END_SHEAR["P_max"]
    EI = SZE_E * SZE_B * SZE_H ** 3 / 12
    u_ref, w_ref = elastica_end_shear(L, np.asarray(r["load_fraction"]) * P * L ** 2 / EI)
    r["elastica_u"], r["elastica_w"] = u_ref.tolist(), w_ref.tolist()
    r["max_error_over_L"] = float(max(np.abs(np.subtract(r["tip_u"], u_ref)).max(),
                                      np.abs(np.subtract(r["tip_w"], w_ref)).max()) / L)
    r["published_tip"] = [SZE_END_SHEAR["tip_u"], SZE_END_SHEAR["tip_w"]]
    f = np.linspace(0.02, 1.0, 50)
    u, w = elastica_end_shear(L, f * P * L ** 2 / EI)
    r["reference_curve"] = {"load_fraction": f.tolist(), "u": u.tolist(), "w": w.tolist()}
    return r


def end_moment_study(nx: int = 48, steps: int = 16) -> dict:
    r = _timed(sc.end_moment, nx, steps)
    L = SZE_END_MOMENT["L"]
    EI = SZE_E * SZE_B * SZE_H ** 3 / 12
    u_ref, w_ref = elastica_end_moment(L, np.asarray(r["load_fraction"]) * SZE_END_MOMENT["M_max"] / EI)
    r["arc_u"], r["arc_w"] = u_ref.tolist(), w_ref.tolist()
    r["max_error_over_L"] = float(max(np.abs(np.subtract(r["tip_u"], u_ref)).max(),
                                      np.abs(np.subtract(r["tip_w"], w_ref)).max()) / L)
    f = np.linspace(0.01, 1.0, 100)
    u, w = elastica_end_moment(L, f * SZE_END_MOMENT["M_max"] / EI)
    r["reference_curve"] = {"load_fraction": f.tolist(), "u": u.tolist(), "w": w.tolist()}
    return r


def slit_plate_study(meshes=SLIT_MESHES, steps: int = 8) -> dict:
    runs = [_timed(sc.slit_annular_plate, n_r, n_t, steps=steps) for n_r, n_t in meshes]
    ref = SZE_SLIT
    out = {"published": {"w_A": ref["w_A"], "w_B": ref["w_B"]}, "meshes": []}
    for (n_r, n_t), r in zip(meshes, runs):
        out["meshes"].append({"mesh": r["mesh"], "n_triangles": r["n_triangles"], "w_A": r["w_A"][-1],
                              "w_B": r["w_B"][-1], "error_A": r["w_A"][-1] / ref["w_A"] - 1,
                              "error_B": r["w_B"][-1] / ref["w_B"] - 1, "seconds": r["seconds"],
                              "newton_iterations": int(sum(r["newton_iterations"]))})
    # first-order Richardson estimate of every consecutive pair of meshes (error ~ 1/n);
    # the increments shrink more slowly than 1/n here, so each estimate bounds the limit from
    # below only if the convergence is at most first order: compare the pairs
    out["richardson_first_order"] = []
    for ((n1, t1), r1), ((n2, t2), r2) in zip(zip(meshes, runs), zip(meshes[1:], runs[1:])):
        est = {"pair": f"{n1}x{t1} / {n2}x{t2}"}
        for key in ("w_A", "w_B"):
            w1, w2 = r1[key][-1], r2[key][-1]
            est[key] = w2 + (w2 - w1) * n1 / (n2 - n1)
            est["error_" + key[-1]] = est[key] / ref[key] - 1
        out["richardson_first_order"].append(est)
    out["richardson"] = out["richardson_first_order"][-1]
    out["curves"] = [{"mesh": r["mesh"], "q": r["q"], "w_A": r["w_A"], "w_B": r["w_B"]} for r in runs]
    return out


def plot_cantilever(r: dict, ref_label: str, title: str, path: str, published=None) -> str:
    from validation.plots import new_axes, save_figure
    fig, ax = new_axes(title, "tip displacement (mm)", "load fraction")
    f = np.asarray(r["load_fraction"])
    c = r["reference_curve"]
    f0 = np.concatenate([[0.0], c["load_fraction"]])
    ax.plot(np.concatenate([[0.0], c["u"]]), f0, "-", color="C0", lw=1.2, label=f"-u, {ref_label}")
    ax.plot(np.concatenate([[0.0], c["w"]]), f0, "-", color="C1", lw=1.2, label=f"w, {ref_label}")
    ax.plot(r["tip_u"], f, "o", color="C0", ms=4, label="-u, engine")
    ax.plot(r["tip_w"], f, "s", color="C1", ms=4, label="w, engine")
    if published:
        ax.plot(published, [1.0, 1.0], "k*", ms=9, label="Sze et al. 2004")
    ax.legend(fontsize=8, loc="lower right")
    return save_figure(fig, path)


def plot_slit(out: dict, path: str) -> str:
    from validation.plots import new_axes, save_figure
    fig, ax = new_axes("Sze 3.3 slit annular plate", "tip deflection w (mm)", "line force q")
    for i, c in enumerate(out["curves"]):
        mesh = c["mesh"].split(",")[0]
        ax.plot([0] + c["w_A"], [0] + c["q"], "--", color=f"C{i}", lw=1.1, marker=".", label=f"A, {mesh}")
        ax.plot([0] + c["w_B"], [0] + c["q"], "-", color=f"C{i}", lw=1.1, marker=".", label=f"B, {mesh}")
    p = out["published"]
    ax.plot([p["w_A"], p["w_B"]], [SZE_SLIT["q_max"]] * 2, "k*", ms=10, label="Sze et al. 2004 (q_max)")
    for i, est in enumerate(out["richardson_first_order"]):
        ax.plot([est["w_A"], est["w_B"]], [SZE_SLIT["q_max"]] * 2, "x", color="r", alpha=0.4 + 0.6 * i / max(
            1, len(out["richardson_first_order"]) - 1), ms=8, label="1st-order Richardson, " + est["pair"])
    ax.legend(fontsize=7, loc="upper left")
    return save_figure(fig, path)


def main(argv=None) -> dict:
    a = study_arguments(__doc__, "two slit-plate meshes only", argv)
    t0 = time.perf_counter()
    shear, moment = end_shear_study(), end_moment_study()
    slit = slit_plate_study(QUICK_SLIT_MESHES if a.quick else SLIT_MESHES)
    figs = [plot_cantilever(shear, "elastica",
                            "Sze 3.1 end shear (40 x 2 quads)", os.path.join(a.figures, "sze_end_shear.png"),
                            published=shear["published_tip"]),
            plot_cantilever(moment, "circular arc",
                            "Sze 3.2 end moment (48 x 2 quads)", os.path.join(a.figures, "sze_end_moment.png")),
            plot_slit(slit, os.path.join(a.figures, "sze_slit_plate.png"))]
    out = {"study": "Sze, Liu & Lo 2004 benchmarks", "quick": a.quick,
           "end_shear": {k: shear[k] for k in ("tip_u", "tip_w", "published_tip", "max_error_over_L", "n_triangles",
                                               "newton_iterations", "seconds")},
           "end_moment": {k: moment[k] for k in ("load_fraction", "tip_u", "tip_w", "max_error_over_L", "n_triangles",
                                                 "newton_iterations", "seconds")},
           "slit_plate": {k: slit[k] for k in ("published", "meshes", "richardson_first_order")},
           "figures": figs, "seconds": round(time.perf_counter() - t0, 1)}
    out["end_shear"]["tip_final"] = [shear["tip_u"][-1], shear["tip_w"][-1]]
    write_result(a.out, "sze", {**out, "slit_plate_curves": slit["curves"]}, out)
    return out


if __name__ == "__main__":
    main()
