"""Design every target in meshes/targets (+ --verify where feasible) for the README.

For each TARGET.obj: `inverse.design.design_file` -> out/design/TARGET/ (all outputs), then
docs/design/TARGET_{target,flat,ribbons,simulated}.png pictures and docs/design/table.md, a
Markdown table with the seed's Table 5.1 columns, the chosen pre-stretch and the simulated
deviation. The defaults are `selfshape design TARGET --verify`'s (the stretch chosen per target,
the verification's mesh and Newton cap). Prints ONE JSON line per target and a final summary line.

    python studies/design_targets.py [--no-verify] [--stretch auto|S] [--printer PRINTER.toml]
                                        [--mesh-size 3] [--across 1] [--verify-iterations 3000]
                                        [--law LAW.csv] [--out out/design] [--docs docs/design] [names...]
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import time

import numpy as np
from study_cli import target_paths

from inverse.to_pattern import (
    VERIFY_ITERATIONS,
    VERIFY_MESH_ACROSS,
    VERIFY_MESH_SIZE_MM,
)


def _plot_target(V, F, path, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from geometry.curvature import principal_curvature
    c = principal_curvature(V, F)
    fig = plt.figure(figsize=(5, 4.2))
    ax = fig.add_subplot(projection="3d")
    s = ax.plot_trisurf(V[:, 0], V[:, 1], V[:, 2], triangles=F, cmap="coolwarm", linewidth=0)
    k = c.face_k1
    lim = max(float(np.percentile(np.abs(k), 98)), 1e-9)
    s.set_array(k)
    s.set_clim(-lim, lim)
    ax.set_box_aspect(np.ptp(V, axis=0))
    ax.set_axis_off()
    fig.colorbar(s, ax=ax, shrink=0.6, label="k1 (1/mm)")
    ax.set_title(title, fontsize=9)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_flat(out_dir, path, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import meshio

    m = meshio.read(os.path.join(out_dir, "flat.vtu"))
    P, T = m.points[:, :2], m.cells_dict["triangle"]
    s1 = m.cell_data["sigma1"][0]
    fig, ax = plt.subplots(figsize=(5.5, 4.8))
    tp = ax.tripcolor(P[:, 0], P[:, 1], T, facecolors=s1, cmap="viridis", vmin=1.0, vmax=1.3)
    fig.colorbar(tp, ax=ax, label="sigma1 (stretch along the ribbons)")
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fmt(v, nd=3):
    if v is None:
        return "-"
    if isinstance(v, (list, tuple)):
        return " / ".join(_fmt(x, nd) for x in v)
    return f"{v:.{nd}g}" if isinstance(v, float) else str(v)


def table_markdown(rows) -> str:
    head = ("| target | stretch | faces | time (s) | lambda | dev. % bbox (mean / max) | target to deployed % (mean / max) | "
            "k1 dev. (deg) | max bound dev. (s1 / s2) | out of bounds % (s1 / s2) | residual energy | "
            "ribbons (front / back) | thickness (mm) |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        hist = {**r["thickness_histogram"]["front"], **r["thickness_histogram"]["back"]}
        th = sorted(float(k) for k in hist) if hist else []
        thick = f"{th[0]:g}-{th[-1]:g}" if th else "-"
        back = _fmt(r.get("deviation_target_to_deployed_pct_bbox"))
        if r.get("deviation_pct_bbox"):
            dev = _fmt(r["deviation_pct_bbox"])
        elif "verify_converged" in r:
            dev = f"not converged ({r.get('verify_reason')})"
        else:
            dev = "not run"
        sides = r["ribbons_per_side"]
        lines.append(f"| {r['name']} | {_fmt(r.get('stretch'))} | {r['n_faces']} | {r['time_s']:.1f} | {r.get('lambda', 0):g} | {dev} | {back} | "
                     f"{r['k1_deviation_deg']:.3f} | {_fmt(r['sigma_bound_violation'], 2)} | "
                     f"{_fmt(r['sigma_out_of_bounds_pct'], 3)} | {r['residual_energy']:.2e} | "
                     f"{sides['front']} / {sides['back']} | {thick} |")
    return head + "\n".join(lines) + "\n"


def main(argv=None):
    from shellfem.memory import keep_freed_memory
    keep_freed_memory()
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("names", nargs="*", help="target names (default: all)")
    ap.add_argument("--no-verify", action="store_true")
    ap.add_argument("--out", default="out/design")
    ap.add_argument("--docs", default="docs/design")
    ap.add_argument("--edge", type=float, default=1.0, help="refine until the mean edge is below (mm)")
    ap.add_argument("--mesh-size", type=float, default=VERIFY_MESH_SIZE_MM, help="[mesh] size_mm written to pattern.toml (verify)")
    ap.add_argument("--across", type=float, default=VERIFY_MESH_ACROSS, help="[mesh] across written to pattern.toml (verify)")
    ap.add_argument("--verify-iterations", type=int, default=VERIFY_ITERATIONS, help="Newton cap of the verification")
    ap.add_argument("--stretch", default="auto", help="fabric pre-stretch, or auto (the CLI's choice per target)")
    ap.add_argument("--printer", default=None, help="printer file (TOML), e.g. inverse/data/printers/layer_0.1mm.toml")
    ap.add_argument("--law", default=None, help="curvature-law CSV (default: the shipped law)")
    ap.add_argument("--metric-floor", type=float, default=None,
                    help="[solver] metric_floor of the verification (default: the solver's 10; shellfem.newton.lm_metric)")
    ap.add_argument("--table", action="store_true", help="only rebuild DOCS/table.md from OUT/*/report.json")
    a = ap.parse_args(argv)
    if a.table:
        os.makedirs(a.docs, exist_ok=True)
        write_table(a.out, a.docs)
        print(json.dumps({"table": os.path.join(a.docs, "table.md")}))
        return
    np.seterr(all="ignore")
    from geometry.target import load_target
    from inverse.design import design_file
    from inverse.printer import load_printer

    extra = {"stretch": a.stretch if a.stretch == "auto" else float(a.stretch)}
    if a.printer:
        extra["printer"] = load_printer(a.printer)

    os.makedirs(a.docs, exist_ok=True)
    paths = target_paths(a.names)
    rows = []
    for path in paths:
        name = os.path.splitext(os.path.basename(path))[0]
        out = os.path.join(a.out, name)
        t0 = time.perf_counter()
        try:
            rep = design_file(path, out, verify=not a.no_verify, edge_mm=a.edge, mesh_size_mm=a.mesh_size,
                              mesh_across=a.across, verify_iterations=a.verify_iterations, thickness_law=a.law,
                              metric_floor=a.metric_floor, **extra)
        except Exception as e:  # report and go on with the other targets
            print(json.dumps({"name": name, "error": f"{type(e).__name__}: {e}"}), flush=True)
            continue
        rep["name"] = name
        rows.append(rep)
        V, F = load_target(path)
        _plot_target(V, F, os.path.join(a.docs, f"{name}_target.png"), f"{name}: target, k1")
        _plot_flat(out, os.path.join(a.docs, f"{name}_flat.png"), f"{name}: flattening (printed mm)")
        import shutil
        shutil.copy(os.path.join(out, "pattern.png"), os.path.join(a.docs, f"{name}_ribbons.png"))
        if os.path.exists(os.path.join(out, "verify.png")):
            shutil.copy(os.path.join(out, "verify.png"), os.path.join(a.docs, f"{name}_simulated.png"))
        keys = ("name", "stretch", "n_faces", "time_s", "k1_deviation_deg", "sigma_bound_violation", "sigma_out_of_bounds_pct",
                "residual_energy", "ribbons_per_side", "flatten_iterations", "flatten_converged",
                "verify_converged", "verify_reason", "deviation_pct_bbox", "verify_simulation_s", "stages_s")
        print(json.dumps({k: rep.get(k) for k in keys} | {"wall_s": round(time.perf_counter() - t0, 1)}), flush=True)
        write_table(a.out, a.docs)
    print(json.dumps({"targets": len(paths), "designed": len(rows), "table": os.path.join(a.docs, "table.md")}))


def write_table(out_root: str, docs: str):
    """docs/table.md from every out_root/*/report.json (so targets can be re-run one by one)."""
    rows = []
    for path in sorted(glob.glob(os.path.join(out_root, "*", "report.json"))):
        with open(path) as f:
            rep = json.load(f)
        rep["name"] = os.path.basename(os.path.dirname(path))
        rows.append(rep)
    with open(os.path.join(docs, "table.md"), "w") as f:
        f.write(table_markdown(rows))


if __name__ == "__main__":
    main()
