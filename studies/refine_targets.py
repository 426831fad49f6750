"""Open-loop and refined designs of the targets in meshes/targets at 110 mm (issue 18's benchmark),
of the analytic targets of study_cli.ANALYTIC_TARGETS (a barrel vault, an S-wave, a hypar, an
ellipsoid cap, a Gaussian bump, a cone segment), or of any
target mesh named by its path.

For each TARGET.obj: `inverse.design.design_file(..., refine=True)` -> OUT/TARGET/ (pattern.toml,
G-code, pictures, deployed.vtu, report.json). Prints ONE JSON line per target: open-loop and
refined deviations (both directions, mean and max, % of the bounding-box diagonal), outer
iterations, the reason the refinement stopped, whether release from flat reaches the refined
state, seconds per stage; and a final summary line. Long: minutes to tens of minutes per
target on 2 cores; not part of the test run.

Each target is one task of shellfem.cluster.map_tasks, like a sweep's cases: one after another
in this process (--workers 0, the default), side by side on a local Dask cluster of N
single-threaded processes (--workers N), or on a running scheduler's workers (--scheduler
ADDRESS; they need this repository on their PYTHONPATH and the output folder on a shared file
system). The JSON lines come as the targets finish; the summary lists them in the order asked.
On a terminal a status line on stderr counts the targets done and the time left (-q hides it).
In this process (no --workers) on two or more cores, each target's open-loop verification (beside
the refinement from the target), its two refinement starts and its jig releases run side by side
in forked workers (inverse.design.design_file's ``parallel``);
--serial runs them one after the other (for timing).

    python studies/refine_targets.py [--mesh-size 3] [--across 1] [--max-outer N] [--stretch 1.2]
                                     [--printer inverse/data/printers/layer_0.1mm.toml] [--proxy on|off|auto]
                                     [--stretch-candidates N] [--verify-iterations 3000] [--out out/refine]
                                     [--workers N | --scheduler ADDRESS] [--serial] [-q] [names or paths...]
    python studies/refine_targets.py --table RUN.jsonl [...]     # the README table of runs' JSON lines
"""
from __future__ import annotations

import argparse
import json
import os
import time

from study_cli import ANALYTIC_TARGETS, analytic_target, target_paths



def run_target(path, out_dir, args) -> dict:
    from inverse.design import PROXY_WORDS, design_file
    from inverse.printer import Printer, load_printer
    from inverse.refine import RefineOptions

    printer = load_printer(args.printer) if args.printer else Printer(layer_height_mm=args.layer)
    opts = RefineOptions(bounds=(printer.layer_height_mm, args.max_thickness), max_outer=args.max_outer, verbose=args.verbose,
                         stability=args.stability, start_iterations=args.start_iterations)
    t0 = time.perf_counter()
    rep = design_file(path, out_dir, refine=True, mesh_size_mm=args.mesh_size, mesh_across=args.across,
                      verify_iterations=args.verify_iterations, refine_options=opts, printer=printer,
                      verbose=args.verbose, parallel=False if (args.serial or args.workers or args.scheduler) else None,
                      proxy=PROXY_WORDS.get(getattr(args, "proxy", None)),
                      stretch_candidates=getattr(args, "stretch_candidates", 1) if args.stretch is None else 1,
                      **({} if args.stretch is None else {"stretch": args.stretch}))
    ref, ol = rep.get("refine", {}), rep.get("open_loop", {})
    return {
        "target": os.path.splitext(os.path.basename(path))[0],
        "open_loop": {"deployed_to_target_pct": ol.get("deviation_pct_bbox", rep.get("deviation_pct_bbox")),
                      "target_to_deployed_pct": ol.get("deviation_target_to_deployed_pct_bbox",
                                                       rep.get("deviation_target_to_deployed_pct_bbox"))},
        "refined": {"deployed_to_target_pct": rep.get("deviation_pct_bbox"),
                    "target_to_deployed_pct": rep.get("deviation_target_to_deployed_pct_bbox"),
                    "nearest_target": ref.get("rounded")} if ref.get("ok") else None,
        "flat_sheet": {"flat_to_target_pct": rep.get("flat_deviation_pct_bbox"),
                       "target_to_flat_pct": rep.get("flat_deviation_target_to_flat_pct_bbox")},
        "refine_ok": bool(ref.get("ok")), "refine_reason": ref.get("reason"),
        "outer_iterations": ref.get("outer_iterations"), "start": ref.get("start"),
        "starts": ref.get("starts"),
        "release_reaches_refined_state": ref.get("release_reaches_refined_state"), "kept": ref.get("kept"),
        "jig": ref.get("jig"), "refined_released": ref.get("refined_released"),
        "feasibility": ref.get("feasibility"), "n_triangles": rep.get("verify_n_triangles"),
        "thickness_rounded_mm": ref.get("thickness_rounded_mm"),
        "out_of_bounds_pct": rep.get("sigma_out_of_bounds_pct"), "stages_s": rep.get("stages_s"),
        "proxy": rep.get("proxy"), "stretch": rep.get("stretch"),
        "verified": (rep.get("stretch_choice") or {}).get("verified"), "refine_s": (rep.get("stages_s") or {}).get("refine"),
        "total_s": round(time.perf_counter() - t0, 1),
    }


def target_task(job: dict) -> dict:
    """``run_target`` of one job {"path", "out_dir", "args"}: a target as a task of
    shellfem.cluster.map_tasks (module level, so that Dask workers can load it)."""
    return run_target(job["path"], job["out_dir"], job["args"])


def run_targets(jobs: list, *, workers: int | None = 0, scheduler: str | None = None, task=target_task,
                on_row=None) -> list:
    """``[task(job) for job in jobs]`` through shellfem.cluster.map_tasks (``workers=0``: in this
    process, one after another; N: a local cluster of N processes; ``scheduler``: a running
    scheduler), rows in the jobs' order. ``on_row(row, done, total)`` is called once with
    ``row=None`` before the first task and then as each task finishes, in this process."""
    from shellfem.cluster import map_tasks
    done = [0]

    def finished(i, row):
        done[0] += 1
        if on_row is not None:
            on_row(row, done[0], len(jobs))
    if on_row is not None:
        on_row(None, 0, len(jobs))
    return map_tasks(task, jobs, scheduler=scheduler, workers=workers, retries=0, on_result=finished)


def _pair(v) -> str:
    return "-" if not v else f"{v[0]:.2f} / {v[1]:.2f}"


def table(rows: list) -> str:
    """The README's markdown table of refine_targets rows (their JSON lines): per target the
    pre-stretch, the share of area out of the stretch bounds (sigma1 / sigma2, %), open-loop and
    refined deviations (mean / max, % of the bounding-box diagonal, deployed -> target and
    target -> deployed), outer iterations, how the refined design deploys, wall time (s)."""
    head = ("| target | stretch | out of bounds % | open loop | refined | outer it. | deploys | refine s / total s |\n"
            "|---|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        ol, rf = r.get("open_loop") or {}, r.get("refined") or {}
        deploy = (r.get("kept") or ("open loop kept: " + str(r.get("refine_reason")))) + (
            "" if r.get("release_reaches_refined_state") in (None, True) else " (release from flat misses the refined state)")
        lines.append(f"| {r['target']} | {r.get('stretch', '-')} | {_pair(r.get('out_of_bounds_pct'))} | "
                     f"{_pair(ol.get('deployed_to_target_pct'))} ({_pair(ol.get('target_to_deployed_pct'))}) | "
                     f"{_pair(rf.get('deployed_to_target_pct'))} ({_pair(rf.get('target_to_deployed_pct'))}) | "
                     f"{r.get('outer_iterations', '-')} | {deploy} | "
                     f"{round(r.get('refine_s') or 0)} / {round(r.get('total_s') or 0)} |")
    return "\n".join(lines)


def read_rows(paths) -> list:
    """The target rows (JSON lines with a "target" key) of refine_targets outputs, in order; a
    later row of the same target replaces an earlier one."""
    rows = {}
    for path in paths:
        with open(path) as f:
            for line in f:
                line = line.strip()
                if line.startswith("{") and '"target"' in line[:12]:
                    r = json.loads(line)
                    rows[r["target"]] = r
    return list(rows.values())


def main(argv=None) -> int:
    from selfshape.progress import StatusLine
    from shellfem.cluster import check_options
    from shellfem.errors import SelfshapeError
    from inverse.design import PROXY_WORDS
    from inverse.refine import RefineOptions
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help="target names in meshes/targets, analytic targets ("
                    + ", ".join(ANALYTIC_TARGETS) + "), or paths of other target meshes (default: all shipped targets)")
    ap.add_argument("--out", default="out/refine")
    ap.add_argument("--mesh-size", type=float, default=3.0, help="[mesh] size_mm of the simulation (mm)")
    ap.add_argument("--across", type=float, default=1.0, help="[mesh] across: triangle rows across a ribbon")
    ap.add_argument("--verify-iterations", type=int, default=3000, help="Newton cap of the release from flat")
    ap.add_argument("--max-outer", type=int, default=RefineOptions.max_outer, help="outer (Gauss-Newton) iterations")
    ap.add_argument("--start-iterations", type=int, default=RefineOptions.start_iterations,
                    help="Newton cap of the first solve from the target")
    ap.add_argument("--stability", type=float, default=RefineOptions.stability,
                    help="stability margin: keep the lowest eigenvalue above this fraction of the start's (0: off)")
    ap.add_argument("--layer", type=float, default=0.2, help="printer layer height (mm), without --printer")
    ap.add_argument("--printer", help="printer file (TOML), e.g. inverse/data/printers/layer_0.1mm.toml")
    ap.add_argument("--stretch", type=float, help="pre-stretch s (default: the design's own choice)")
    ap.add_argument("--proxy", choices=tuple(PROXY_WORDS), default=None,
                    help="design for a proxy surface within the stretch bounds (selfshape design --proxy; "
                         "default: auto, as --refine's)")
    ap.add_argument("--stretch-candidates", type=int, default=1,
                    help="without --stretch: verify the open loops at this many best stretches and keep the nearest "
                         "(selfshape design --stretch-candidates)")
    ap.add_argument("--max-thickness", type=float, default=1.6, help="thickest printable ribbon (mm)")
    ap.add_argument("-v", "--verbose", action="store_true")
    ap.add_argument("--serial", action="store_true",
                    help="one solve at a time (default on 2+ cores: the open-loop verification, the two refinement "
                         "starts and the jig releases side by side; always serial on a cluster, whose workers are "
                         "one core each)")
    ap.add_argument("--workers", type=int, default=None,
                    help="targets side by side on a local Dask cluster of this many processes "
                         "(default 0: one after another in this process)")
    ap.add_argument("--scheduler", help="run the targets on this running Dask scheduler, e.g. tcp://host:8786")
    ap.add_argument("-q", "--quiet", action="store_true", help="no progress line on a terminal")
    ap.add_argument("--table", nargs="+", metavar="JSONL", help="print the README table of earlier runs' output "
                    "(their JSON lines) instead of running")
    args = ap.parse_args(argv)
    if args.table:
        print(table(read_rows(args.table)))
        return 0
    if args.start_iterations < 1:
        ap.error(f"--start-iterations {args.start_iterations}: a Newton cap, at least 1")
    if not 0.0 <= args.stability < 1.0:
        ap.error(f"--stability {args.stability:g}: a fraction of the start's lowest eigenvalue in [0, 1) (0: off)")
    workers = args.workers if args.workers is not None or args.scheduler else 0
    try:
        check_options(args.scheduler, workers)
    except SelfshapeError as e:
        ap.error(str(e))
    files = [n for n in args.names if os.path.splitext(n)[1]]
    files += [analytic_target(n, args.out) for n in args.names if n in ANALYTIC_TARGETS]
    names = [n for n in args.names if not os.path.splitext(n)[1] and n not in ANALYTIC_TARGETS]
    paths = (target_paths(names) if names or not files else []) + files
    jobs = [{"path": p, "out_dir": os.path.join(args.out, os.path.splitext(os.path.basename(p))[0]), "args": args}
            for p in paths]
    line = StatusLine.for_stderr("refine_targets", not (args.quiet or args.verbose))

    def show(row, done, total):          # the status line: targets done / total; stdout: the target's JSON line
        line({"stage": "tasks", "done": done, "total": total, "unit": "targets", "last": row and row["target"]})
        if row is not None:
            line.print_above(json.dumps(row))
    try:
        rows = run_targets(jobs, workers=workers, scheduler=args.scheduler, on_row=show)
    except SelfshapeError as e:          # e.g. a scheduler that cannot be reached
        raise SystemExit(f"refine_targets: {e}") from None
    finally:
        line.close()                     # erased before the summary or the error
    print(json.dumps({"summary": {r["target"]: {"open": r["open_loop"], "refined": r["refined"]} for r in rows}}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
