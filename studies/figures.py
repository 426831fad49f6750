"""ONE command that regenerates every validation figure and number.

    python studies/figures.py [--quick] [--only NAME[,NAME...]] [--out out/validation]
                              [--figures docs/validation] [--data validation/data]

Run from the repository root. Tasks (in this order; NAME in brackets):
  [convergence]        studies/convergence.py: mesh convergence on unstructured Gmsh meshes
  [sze]                studies/sze.py: Sze et al. 2004 end shear, end moment, slit annular plate
  [natural_curvature]  studies/natural_curvature.py: disk sphere->cylinder threshold, wide bilayer roll
  [fabric]             calibrate the fabric on DATA/fabric (validation.fabric.calibrate_fabric)
  [strips]             calibrate the modulus ratio on DATA/strips_S1.csv (validation.strips)
  [loop]               the closed loop on DATA/strips_S1.csv (validation.loop.validate_file)
  [bench_meshing]      studies/bench_meshing.py: 800 ribbons / ~300 stars meshing benchmark
  [bench_flattening]   studies/bench_flattening.py: every target refined to ~100k faces, flattened
  [bench_layout]       studies/bench_layout.py: stripe fields + ribbon layout on a ~100k-face disk
  [bench_design]       studies/bench_design.py: the whole inverse-design pipeline on the refined saddle
--quick runs the short variants (coarser meshes, shorter sweeps, ~20k-face benchmarks,
smaller meshing cases). Figures go to FIGURES (PNG), outputs to OUT/<task>/ (JSON, logs;
each task's own printed output is kept in OUT/<task>.log). Prints ONE summary JSON line
with, per task: ok, seconds, the headline numbers, the figures; a task that fails is
reported with its error and the others still run (exit status 1 if any failed).
OUT/summary.json holds the latest result of every task (--only updates those tasks).
Then `python studies/validation_page.py --runs out/validation` copies the studies' JSON to
docs/validation/json/ and writes the validation page docs/validation.md from it.
"""
from __future__ import annotations

import argparse
import contextlib
import glob
import io
import json
import os
import shutil
import sys
import time
import traceback

TASKS = ("convergence", "sze", "natural_curvature", "fabric", "strips", "loop",
         "bench_meshing", "bench_flattening", "bench_layout", "bench_design")
TARGETS = os.path.join("meshes", "targets", "*.obj")     # relative to the repository root


def _last_json(text: str):
    """The last line of text that parses as a JSON object (a script's result line)."""
    for line in reversed(text.strip().splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                return json.loads(line)
            except ValueError:
                continue
    return None


def _copy_pngs(src_dir: str, fig_dir: str, prefix: str) -> list:
    """Copy src_dir/*.png to fig_dir/<prefix>_<name>.png; returns the new paths."""
    os.makedirs(fig_dir, exist_ok=True)
    out = []
    for p in sorted(glob.glob(os.path.join(src_dir, "*.png"))):
        dst = os.path.join(fig_dir, f"{prefix}_{os.path.basename(p)}")
        shutil.copyfile(p, dst)
        out.append(dst)
    return out


def _args(quick, out, figs):
    return (["--quick"] if quick else []) + ["--out", out, "--figures", figs]


# ------------------------------------------------------------------------- tasks
# each: (quick, out_dir, fig_dir, data_dir) -> (headline dict, figures list); the studies are the
# scripts next to this one (studies/ is on sys.path when this file is run as a script)

def task_convergence(quick, out, figs, data):
    import convergence
    r = convergence.main(_args(quick, out, figs))
    s, g = r["strip"], r["thickness_gradient"]
    return {"strip_curvature_per_mm": [m["curvature_per_mm"] for m in s["meshes"]],
            "strip_sizes_mm": [m["size_mm"] for m in s["meshes"]],
            "strip_closed_form_per_mm": s["closed_form_narrow_per_mm"],
            "strip_richardson_per_mm": s["richardson_limit_per_mm"],
            "strip_order": s["observed_order_vs_richardson"],
            "gradient_rms_to_finest_mm": [m["rms_to_finest_mm"] for m in g["meshes"]],
            "gradient_order": g["observed_order"]}, [r["figure"]]


def task_sze(quick, out, figs, data):
    import sze
    r = sze.main(_args(quick, out, figs))
    return {"end_shear_tip": r["end_shear"]["tip_final"],
            "end_shear_max_error_over_L": r["end_shear"]["max_error_over_L"],
            "end_moment_max_error_over_L": r["end_moment"]["max_error_over_L"],
            "slit_meshes": [[m["mesh"].split(",")[0], round(m["w_A"], 3), round(m["w_B"], 3)]
                            for m in r["slit_plate"]["meshes"]],
            "slit_richardson_first_order": [[e["pair"], round(e["w_A"], 3), round(e["w_B"], 3)]
                                            for e in r["slit_plate"]["richardson_first_order"]],
            "slit_published": [r["slit_plate"]["published"]["w_A"], r["slit_plate"]["published"]["w_B"]]}, r["figures"]


def task_natural_curvature(quick, out, figs, data):
    import natural_curvature
    r = natural_curvature.main(_args(quick, out, figs))
    return {"disk_ritz_threshold": r["disk"]["ritz_threshold"],
            "disk_engine_threshold_bracket": r["disk"]["engine_threshold_bracket"],
            "roll_lengths_mm": r["roll"]["lengths"], "roll_deficit_vs_plate": r["roll"]["deficit"]}, r["figures"]


def task_fabric(quick, out, figs, data):
    from validation.fabric import calibrate_fabric
    d = os.path.join(out, "fabric")
    r = calibrate_fabric(os.path.join(data, "fabric"), d)
    head = {"orthotropic": r["orthotropic"], "release_modulus_mpa": r["release_modulus_mpa"],
            "bending_stiffness_mean_nmm": r["bending_stiffness_mean_nmm"]}
    return head, _copy_pngs(d, figs, "fabric")


def task_strips(quick, out, figs, data):
    from validation.strips import calibrate_strips
    d = os.path.join(out, "strips")
    r = calibrate_strips(os.path.join(data, "strips_S1.csv"), d)
    head = {k: r[k] for k in ("modulus_ratio", "modulus_ratio_rest_measured", "modulus_ratio_seed_eq3_17") if k in r}
    head["ci95"] = r["confidence_intervals_95"]["modulus_ratio"]
    return head, _copy_pngs(d, figs, "strips")


def task_loop(quick, out, figs, data):
    from validation.loop import validate_file
    d = os.path.join(out, "loop")
    r = validate_file(os.path.join(data, "strips_S1.csv"), d)
    head = {k: r[k] for k in ("error_before", "error_after", "noise_relative", "effects_added")}
    head["parameters"] = r["parameters"]
    return head, _copy_pngs(d, figs, "loop")


def task_bench_meshing(quick, out, figs, data):
    import bench_meshing
    return bench_meshing.main(["--quick"] if quick else []), []


def task_bench_flattening(quick, out, figs, data):
    from bench_flattening import bench
    faces = 20_000 if quick else 100_000
    paths = sorted(glob.glob(TARGETS))
    if quick:
        paths = [p for p in paths if "saddle" in p] or paths[:1]
    rows = []
    for p in paths:
        r = bench(p, faces)
        print(json.dumps(r), flush=True)
        rows.append({k: r[k] for k in ("target", "faces", "flattening_s", "total_s", "converged",
                                       "sigma_bound_violation", "sigma_out_of_bounds_pct")})
    return {"targets": rows}, []


def _run_main_capture(main, argv):
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        main(argv)
    text = buf.getvalue()
    print(text, end="")
    return _last_json(text)


def task_bench_layout(quick, out, figs, data):
    import bench_layout
    return _run_main_capture(bench_layout.main, ["--faces", "20000"] if quick else []), []


def task_bench_design(quick, out, figs, data):
    import bench_design
    return _run_main_capture(bench_design.main, (["--faces", "20000"] if quick else []) + ["--no-compare"]), []


def run_task(name: str, quick: bool, out: str, figs: str, data: str) -> dict:
    fn = globals()["task_" + name]
    os.makedirs(out, exist_ok=True)
    log = io.StringIO()
    t0 = time.perf_counter()
    try:
        with contextlib.redirect_stdout(log):
            head, fig_list = fn(quick, out, figs, data)
        res = {"ok": True, "results": head, "figures": fig_list}
    except Exception as e:  # a failing task is reported, the others still run
        traceback.print_exc(file=log)
        res = {"ok": False, "error": f"{type(e).__name__}: {e}"}
    res["seconds"] = round(time.perf_counter() - t0, 1)
    with open(os.path.join(out, f"{name}.log"), "w") as fh:
        fh.write(log.getvalue())
    return res


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="short variants of every task")
    ap.add_argument("--only", default="", help="comma-separated task names: " + ", ".join(TASKS))
    ap.add_argument("--out", default="out/validation")
    ap.add_argument("--figures", default="docs/validation")
    ap.add_argument("--data", default="validation/data")
    a = ap.parse_args(argv)
    names = [n.strip() for n in a.only.split(",") if n.strip()] or list(TASKS)
    unknown = [n for n in names if n not in TASKS]
    if unknown:
        ap.error(f"unknown task(s) {unknown}; choose from {', '.join(TASKS)}")
    t0 = time.perf_counter()
    summary = {"command": "python studies/figures.py" + (" --quick" if a.quick else "")
               + (f" --only {','.join(names)}" if a.only else ""), "tasks": {}}
    for n in names:
        print(f"[figures] {n} ...", file=sys.stderr, flush=True)
        summary["tasks"][n] = run_task(n, a.quick, a.out, a.figures, a.data)
        print(f"[figures] {n}: {'ok' if summary['tasks'][n]['ok'] else 'FAILED'} "
              f"({summary['tasks'][n]['seconds']} s)", file=sys.stderr, flush=True)
    summary["seconds"] = round(time.perf_counter() - t0, 1)
    summary["all_ok"] = all(t["ok"] for t in summary["tasks"].values())
    os.makedirs(a.out, exist_ok=True)
    path = os.path.join(a.out, "summary.json")
    merged = {"tasks": {}}
    if a.only and os.path.exists(path):      # --only refreshes those tasks in the full summary
        with open(path) as fh:
            merged = json.load(fh)
    merged["tasks"].update(summary["tasks"])
    merged["last_command"] = summary["command"]
    merged["all_ok"] = all(t["ok"] for t in merged["tasks"].values())
    with open(path, "w") as fh:
        json.dump(merged, fh, indent=2)
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    sys.exit(0 if main()["all_ok"] else 1)
