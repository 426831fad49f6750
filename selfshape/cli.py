"""The ``selfshape`` command: mesh, simulate, design, calibrate, validate, predict.

Every verb is a thin wrapper over a Python function (named in its help) so that
scripts can call the same thing. Bad input exits with status 2 and one line on
stderr naming the problem; an unexpected failure exits 3, also with one line.
"""
from __future__ import annotations

import argparse
import math
import os
import sys


def _cmd_mesh(a):
    from geometry.meshing import mesh_pattern_file
    info = mesh_pattern_file(a.pattern, a.output, size_mm=a.size)
    print(f"wrote {a.output}: {info['n_vertices']} vertices, {info['n_triangles']} triangles, "
          f"{info['n_regions']} printed regions, min angle {info['min_angle_deg']:.1f} deg")


def _levels(text):
    if text == "auto":
        return text
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"must be 'auto' or an integer >= 0, got {text!r}")
    return n


def _stretch(text):
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number > 1 or 'auto', got {text!r}") from None


def _cmd_simulate(a):
    from forward.simulate import simulate_pattern_file
    s = simulate_pattern_file(a.pattern, a.output, size_mm=a.size, seed=a.seed, render=not a.no_png,
                              max_iterations=a.max_iterations, verbose=a.verbose, coarse_levels=a.coarse_levels)
    state = "converged" if s["converged"] else "NOT converged"
    levels = s.get("timings_s", {}).get("levels") or []
    via = ""
    if len(levels) > 1:      # nested iteration: say where the iterations went
        via = " (" + " -> ".join(f"{lv['n_vertices']} vertices: {lv['iterations']}" for lv in levels) + ")"
    print(f"{state} in {s['newton_iterations']} Newton iterations{via}, |grad| {s['gradient_norm']:.2e}, "
          f"{s['n_vertices']} vertices, {s['wall_time_s']:.1f} s -> {a.output}")
    return 0 if s["converged"] else 1


def _cmd_design(a):
    from inverse.design import design_file
    from inverse.printer import load_printer
    printer = load_printer(a.printer) if a.printer else None
    r = design_file(a.target, a.output, verify=a.verify, diagonal_mm=a.diagonal, stretch=a.stretch,
                    thickness_law=a.law, lam=a.lam, printer=printer, verify_iterations=a.verify_iterations,
                    refine=a.refine, mesh_size_mm=a.mesh_size, mesh_across=a.mesh_across, verbose=a.verbose)
    print(f"design written to {a.output} in {r['time_s']:.1f} s")
    if r.get("stretch_choice"):
        c = r["stretch_choice"]
        print("stretch auto: " + ", ".join(f"s {row['stretch']:g}: curvature off by x{math.exp(row['log_excess']):.2f}, "
                                         f"{100 * row['out_of_bounds']:.1f} % out of bounds" for row in c["candidates"])
              + f" -> {c['chosen']:g}")
    warning = (r.get("curvature_reach") or {}).get("warning")
    if warning:
        print(f"warning: {warning}")
    if r.get("deviation_pct_bbox"):
        dev, back = r["deviation_pct_bbox"], r["deviation_target_to_deployed_pct_bbox"]
        print(f"deployed -> target {dev[0]:.2f} / {dev[1]:.2f} %, target -> deployed {back[0]:.2f} / {back[1]:.2f} % "
              f"(mean / max, % of the bounding-box diagonal)")
    elif "verify_converged" in r:
        print(f"verification: {r.get('verify_note', r.get('verify_reason'))}")
    ref = r.get("refine")
    if ref is not None:
        if ref.get("ok"):
            o = ref and r.get("open_loop", {}).get("deviation_pct_bbox")
            print(f"refined in {ref['outer_iterations']} outer iterations, {ref['seconds']:.0f} s ({ref['reason']})"
                  + (f"; open loop was {o[0]:.2f} / {o[1]:.2f} %" if o else ""))
        else:
            print(f"refinement failed, open-loop design kept: {ref['reason']}")


def _cmd_calibrate(a):
    if a.kind == "strips":
        from validation.strips import calibrate_strips as fn
    elif a.kind == "fabric":
        from validation.fabric import calibrate_fabric as fn
    else:  # argparse restricts choices; kept for the Python API
        raise ValueError(a.kind)
    fn(a.data, a.output)
    print(f"parameters written to {os.path.join(a.output, 'parameters.json')}")


def _cmd_validate(a):
    from validation.strips import check_for_validation  # input contract (issue 19): checked before the loop
    check_for_validation(a.data, [a.output])
    from validation.loop import validate_file
    r = validate_file(a.data, a.output, seed=a.seed)
    print(f"error before {r['error_before']:.4f}, after {r['error_after']:.4f}; "
          f"effects added: {', '.join(r['effects_added']) or 'none'} -> {a.output}")


def _cmd_predict(a):
    from validation.model_file import check_predict  # input contract (issue 19): model.json, rows, -o
    check_predict(a.model, a.data, a.output)
    from validation.loop import predict_file
    n = predict_file(a.model, a.data, a.output)
    print(f"wrote {n} predictions to {a.output}")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="selfshape", description="Self-shaping textiles: simulate, design, calibrate.")
    sub = p.add_subparsers(dest="verb", required=True)

    m = sub.add_parser("mesh", help="conforming Gmsh mesh of a pattern (geometry.meshing.mesh_pattern_file)")
    m.add_argument("pattern", help="pattern .toml or .gcode")
    m.add_argument("-o", "--output", required=True, help="output .msh")
    m.add_argument("--size", type=float, default=None, help="override [mesh] size_mm")
    m.set_defaults(fn=_cmd_mesh)

    s = sub.add_parser("simulate", help="released equilibrium of a pattern (forward.simulate.simulate_pattern_file)")
    s.add_argument("pattern")
    s.add_argument("-o", "--output", required=True, help="output directory")
    s.add_argument("--size", type=float, default=None, help="override [mesh] size_mm")
    s.add_argument("--seed", type=int, default=None, help="override [solver] seed")
    s.add_argument("--max-iterations", type=int, default=None)
    s.add_argument("--coarse-levels", type=_levels, default=None,
                   help="override [solver] coarse_levels: 'auto' or N >= 0 coarser meshes solved first (0: none)")
    s.add_argument("--no-png", action="store_true", help="skip deployed.png")
    s.add_argument("-v", "--verbose", action="store_true")
    s.set_defaults(fn=_cmd_simulate)

    d = sub.add_parser("design", help="inverse design from a target surface (inverse.design.design_file)")
    d.add_argument("target")
    d.add_argument("-o", "--output", required=True)
    d.add_argument("--verify", action="store_true", help="simulate the design and report its deviation")
    d.add_argument("--verify-iterations", type=int, default=None,
                   help="Newton iteration cap of --verify, also written to pattern.toml [solver] (default 300)")
    d.add_argument("--refine", action="store_true",
                   help="refine the ribbon thicknesses with the shell in the loop (implies --verify)")
    d.add_argument("--mesh-size", type=float, default=2.0, help="pattern.toml [mesh] size_mm of the verification, mm")
    d.add_argument("--mesh-across", type=float, default=None,
                   help="pattern.toml [mesh] across: triangle rows across a ribbon (default 2)")
    d.add_argument("-v", "--verbose", action="store_true")
    d.add_argument("--diagonal", type=float, default=110.0, help="scale the target to this bounding-box diagonal, mm")
    d.add_argument("--stretch", type=_stretch, default=1.6,
                   help="fabric pre-stretch s, or 'auto': the shipped law's stretch that fits the target best")
    d.add_argument("--law", default=None, help="curvature-law CSV (default: the shipped inverse/data table)")
    d.add_argument("--lam", type=float, default=0.0, help="line-field lambda of the seed (<= 0, 1/mm^2)")
    d.add_argument("--printer", default=None,
                   help="printer TOML (inverse.printer.Printer fields: bed_size, nozzle_mm, print_speed_mm_s, ...)")
    d.set_defaults(fn=_cmd_design)

    c = sub.add_parser("calibrate", help="fit material parameters (validation.strips / validation.fabric)")
    c.add_argument("kind", choices=["strips", "fabric"])
    c.add_argument("data")
    c.add_argument("-o", "--output", required=True)
    c.set_defaults(fn=_cmd_calibrate)

    v = sub.add_parser("validate", help="the closed validation loop (validation.loop.validate_file)")
    v.add_argument("data")
    v.add_argument("-o", "--output", required=True)
    v.add_argument("--seed", type=int, default=0, help="seed of the cross-validation splits")
    v.set_defaults(fn=_cmd_validate)

    r = sub.add_parser("predict", help="apply a fitted model.json (validation.loop.predict_file)")
    r.add_argument("model")
    r.add_argument("data")
    r.add_argument("-o", "--output", required=True)
    r.set_defaults(fn=_cmd_predict)
    return p


def main(argv=None) -> int:
    from shellfem.errors import SelfshapeError
    args = build_parser().parse_args(argv)
    from shellfem.memory import keep_freed_memory
    keep_freed_memory()
    try:
        rc = args.fn(args)
    except SelfshapeError as e:
        print(f"selfshape {args.verb}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"selfshape {args.verb}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # never a traceback: one line, and a distinct status
        msg = " ".join(str(e).split()) or type(e).__name__
        print(f"selfshape {args.verb}: internal error ({type(e).__name__}): {msg}", file=sys.stderr)
        return 3
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
