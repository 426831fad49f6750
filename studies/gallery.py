"""The seed's qualitative results, simulated, each with the number that asserts it.

Cases (validation.cases.GALLERY_CASES, measured by validation.measures.gallery_measure; pattern
files written to examples/gallery/, results to out/gallery/<name>/, pictures to
docs/gallery/<name>.png):
  tube          uniform star field, free boundary (seed Fig. 3.2): one principal curvature
                dominates: median |k_max| / |k_min| over the printed sheet.
  dome          hexagon, arm length decreasing towards the rim, boundary held on the ground
                (Fig. 3.7/3.8): the Gaussian curvature of a quadric fitted to the deployed
                centre (inner 30 % of the radius) is > 0. Per-triangle curvature would
                measure the bumps each star makes, not the sheet's shape.
  flat_centre   the same with arm length increasing towards the rim: a flatter centre, i.e.
                the fitted mean curvature |H| at the centre well below the dome's.
  ribbons       parallel ribbons along x (Fig. 4.8): a cylinder about the axis across
                the ribbons: median curvature along / across the ribbons.
  ortho_0, ortho_90   the same ribbons on the orthotropic fabric with its course direction
                at 0 and 90 deg to the ribbons (seed section 4.1): curvature along / across.
  half_annulus  ribbons along circular arcs on a half annulus, denser outside (Fig. 5.2/5.8):
                the inner edge contracts more than the outer one (deployed / printed length).
Prints ONE JSON line with every case's numbers, wall time and convergence.
Run: python studies/gallery.py [--only NAME ...] [--table]
"""
from __future__ import annotations

import argparse
import json
import os
import time

from validation.cases import GALLERY_CASES
from validation.measures import gallery_measure


def run(names=None, out_root="out/gallery", docs="docs/gallery", examples="examples/gallery", max_iterations=400):
    from geometry.patterns import load_pattern, write_pattern
    from forward.outputs import write_vtu
    from forward.simulate import simulate
    os.makedirs(examples, exist_ok=True)
    os.makedirs(docs, exist_ok=True)
    results = {}
    for name in names or list(GALLERY_CASES):
        raw = GALLERY_CASES[name]()
        path = os.path.join(examples, f"{name}.toml")
        write_pattern(path, raw)
        t0 = time.perf_counter()
        sim = simulate(load_pattern(path), max_iterations=max_iterations)
        row = {"pattern": path, "converged": bool(sim.result.converged), "newton_iterations": sim.result.iterations,
               "n_vertices": int(sim.sheet.n_vertices), "wall_s": round(time.perf_counter() - t0, 1)}
        row.update(gallery_measure(name, sim))
        d = os.path.join(out_root, name)
        os.makedirs(d, exist_ok=True)
        write_vtu(sim, os.path.join(d, "deployed.vtu"))
        try:
            from forward.render import render_deployed
            render_deployed(sim, os.path.join(docs, f"{name}.png"), title=name)
        except Exception as e:  # a picture must not lose the numbers
            row["render_error"] = str(e)
        with open(os.path.join(d, "result.json"), "w") as f:
            json.dump(row, f, indent=2)
        results[name] = row
    return results


CLAIMS = {
    "tube": ("median \\|k_max\\| / \\|k_min\\|", "median_kmax_over_kmin", "> 2: one curvature dominates"),
    "dome": ("Gaussian curvature of the centre fit (1/mm^2)", "gauss_centre_fit", "> 0: dome"),
    "flat_centre": ("\\|mean curvature\\| of the centre fit (1/mm)", "mean_curv_centre_fit", "well below the dome's"),
    "ribbons": ("curvature along / across ribbons", "along_over_across", "> 1: axis across the ribbons"),
    "ortho_0": ("curvature along / across ribbons", "along_over_across", "seed 4.1: one of 0/90 along, one across"),
    "ortho_90": ("curvature along / across ribbons", "along_over_across", "seed 4.1: one of 0/90 along, one across"),
    "half_annulus": ("inner / outer edge length ratio", None, "inner < outer"),
}


def markdown_table(out_root="out/gallery", docs="docs/gallery") -> str:
    """README table of the cases that have a result.json."""
    rows = ["| case | pattern | vertices | Newton it. | converged | measure | value | expected |",
            "|---|---|---|---|---|---|---|---|"]
    imgs = []
    for name, (label, key, expect) in CLAIMS.items():
        p = os.path.join(out_root, name, "result.json")
        if not os.path.exists(p):
            continue
        r = json.load(open(p))
        if key is None:
            value = f"{r['inner_length_ratio']:.3f} / {r['outer_length_ratio']:.3f}"
        else:
            value = f"{r[key]:.3g}"
        imgs.append(f'<img src="{docs}/{name}.png" width="210" alt="{name}">')
        rows.append(f"| {name} | `{r['pattern']}` | {r['n_vertices']} | "
                    f"{r['newton_iterations']} | {r['converged']} | {label} | {value} | {expect} |")
    return "\n".join(rows) + "\n\n" + " ".join(imgs)


def main(argv=None):
    from shellfem.memory import keep_freed_memory
    keep_freed_memory()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", choices=list(GALLERY_CASES))
    ap.add_argument("--max-iterations", type=int, default=400)
    ap.add_argument("--table", action="store_true", help="print the README table of existing results and stop")
    a = ap.parse_args(argv)
    if a.table:
        print(markdown_table())
        return
    print(json.dumps(run(a.only, max_iterations=a.max_iterations)))


if __name__ == "__main__":
    main()
