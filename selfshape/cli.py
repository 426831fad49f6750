"""The ``selfshape`` command: mesh, simulate, design, calibrate, validate, predict, export, view,
calibration-print, law, sweep.

Every verb is a thin wrapper over a Python function (named in its help) so that
scripts can call the same thing. Bad input exits with status 2 and one line on
stderr naming the problem; an unexpected failure exits 3, also with one line.
A usage error is one line too (no usage text: ``selfshape VERB --help`` shows it), and
the warnings numpy, meshio, Gmsh or VTK print while a verb runs are kept from the
terminal (shown with ``-v``), so that the error line is the only line on stderr.
The verbs' files are checked before the work and written atomically, every number
finite (shellfem.outfiles).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import math
import os
import re
import sys
import tempfile
import warnings


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``selfshape VERB: error: MESSAGE`` and exit status 2,
    without the usage text argparse prints first (the contract: one line on stderr)."""

    def error(self, message):
        msg = " ".join(str(message).split())
        self.exit(2, f"{self.prog}: error: {msg} (see {self.prog} --help)\n")

    def _get_values(self, action, arg_strings):
        # Python 3.11's argparse turns "--size=--" into [] without calling the type
        if action.option_strings and action.nargs is None and list(arg_strings) == ["--"]:
            raise argparse.ArgumentError(action, "expected one argument, got '--'")
        return super()._get_values(action, arg_strings)


_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


def _printable(text) -> str:
    """``text`` as one printable line: whitespace runs become one space and the other control
    characters (ESC, BEL, C1 codes) their \\x escape, so that a file name or key from the
    input can neither break the one-line contract nor send terminal escape sequences."""
    one = " ".join(str(text).split())
    return _CONTROL.sub(lambda m: f"\\x{ord(m.group(0)):02x}", one)


def _number(lo=None, lo_open=False, hi=None, integer=False):
    """An argparse type: a finite number (an integer if ``integer``) within the bounds."""
    what = "an integer" if integer else "a finite number"
    rng = ((f" > {lo:g}" if lo_open else f" >= {lo:g}") if lo is not None else "") + \
        (f" <= {hi:g}" if hi is not None else "")

    def parse(text):
        try:
            v = int(text) if integer else float(text)
        except ValueError:
            v = None
        if v is None or not math.isfinite(v) or (lo is not None and (v <= lo if lo_open else v < lo)) or \
                (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"must be {what}{rng}, got {text!r}")
        return v
    return parse


def _schema_number(table: str, key: str):
    """An argparse type for an option that is a number of geometry.schema (``table`` names a
    dict of Num there): the option's range is the schema's, as for the same value in a file."""
    from geometry import schema
    spec = getattr(schema, table)[key]
    return _number(spec.lo, lo_open=spec.lo_open, hi=spec.hi, integer=spec.integer)


_POSITIVE = _number(0.0, lo_open=True)
_COUNT = _number(1, integer=True)
_SEED = _number(0, integer=True)


@contextlib.contextmanager
def _quiet(enabled: bool):
    """Keep what libraries print to stderr while a verb runs (Python warnings, rich/meshio
    notes, and C-level output of Gmsh, VTK or CHOLMOD on file descriptor 2) from the
    terminal; ``enabled=False`` (``-v``) lets it through."""
    if not enabled:
        yield
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        saved = None
        with tempfile.TemporaryFile() as sink:
            try:
                sys.stderr.flush()
                saved = os.dup(2)
            except (OSError, ValueError):       # no file descriptor 2 (embedded): Python level only
                saved = None
            if saved is not None:
                os.dup2(sink.fileno(), 2)
            try:
                with contextlib.redirect_stderr(io.StringIO()):
                    yield
            finally:
                if saved is not None:
                    with contextlib.suppress(Exception):
                        sys.stderr.flush()
                    os.dup2(saved, 2)
                    os.close(saved)


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
    """--stretch of design: 'auto' or a number in geometry.schema.DESIGN_NUMBERS["stretch"]."""
    if text == "auto":
        return text
    try:
        return _schema_number("DESIGN_NUMBERS", "stretch")(text)
    except argparse.ArgumentTypeError as e:
        raise argparse.ArgumentTypeError(str(e).replace("must be ", "must be 'auto' or ", 1)) from None


def _cmd_simulate(a):
    from forward.simulate import simulate_pattern_file
    s = simulate_pattern_file(a.pattern, a.output, size_mm=a.size, seed=a.seed, render=not a.no_png,
                              max_iterations=a.max_iterations, verbose=a.verbose, coarse_levels=a.coarse_levels,
                              progress=a.progress)
    a.progress.close()
    # a run that did not converge says why on its one line (status 1 with its reason)
    state = "converged" if s["converged"] else f"NOT converged ({_printable(s.get('reason') or 'no reason given')})"
    levels = s.get("timings_s", {}).get("levels") or []
    via = ""
    if len(levels) > 1:      # nested iteration: say where the iterations went
        via = " (" + " -> ".join(f"exact metric: {lv['iterations']}" if lv.get("metric") == "exact" and k else
                                 f"{lv['n_vertices']} vertices: {lv['iterations']}"
                                 for k, lv in enumerate(levels)) + ")"
    fold = s.get("fold_stop") or {}
    held = ""
    if s["converged"] and fold.get("triangles"):     # a converged state that is locally past the thin shell
        held = (f"; {fold['triangles']} printed triangles ({fold['area_mm2']:.2g} mm^2, "
                f"{100 * fold['share_of_print']:.2g} % of the print) bent to the thin-shell limit |k z| 0.9, "
                f"held there by the fold stop")
    print(f"{state} in {s['newton_iterations']} Newton iterations{via}, |grad| {s['gradient_norm']:.2e}, "
          f"{s['n_vertices']} vertices, {s['wall_time_s']:.1f} s{held} -> {a.output}")
    return 0 if s["converged"] else 1


def _curvature_fit(row) -> str:
    """A stretch candidate's curvature fit for the `design --stretch auto` line: the law's mean
    factor off, unless the ribbons follow directions the target hardly bends along (then that
    factor measures nothing; inverse.thickness_law.reach_warning)."""
    from inverse.thickness_law import along_twist
    if along_twist(row.get("bend_share")):
        return f"ribbons along twist directions ({100 * row['bend_share']:.0f} % of the bending)"
    return f"curvature off by x{math.exp(row['log_excess']):.2f}"


def _cmd_design(a):
    from inverse.design import PROXY_WORDS, design_file
    from inverse.printer import load_printer
    printer = load_printer(a.printer) if a.printer else None
    table = a.contraction.removesuffix(":polygon")
    if a.contraction not in ("auto", "seed", "table", "table-polygon") and not os.path.exists(table):
        from shellfem.errors import SelfshapeError
        raise SelfshapeError(f"--contraction {a.contraction!r:.80}: not 'auto', 'seed', 'table', 'table-polygon' nor "
                             f"a contraction table file (no such file)")
    if a.stretch_candidates > 1 and (a.stretch != "auto" or not (a.verify or a.refine)):
        from shellfem.errors import SelfshapeError
        raise SelfshapeError(f"--stretch-candidates {a.stretch_candidates}: needs --stretch auto and --verify or "
                             f"--refine (the candidates are verified to choose)")
    r = design_file(a.target, a.output, verify=a.verify, diagonal_mm=a.diagonal, stretch=a.stretch,
                    thickness_law=a.law, lam=a.lam, printer=printer, verify_iterations=a.verify_iterations,
                    refine=a.refine, mesh_size_mm=a.mesh_size, mesh_across=a.mesh_across, verbose=a.verbose,
                    contraction=a.contraction, proxy=PROXY_WORDS.get(a.proxy), stretch_candidates=a.stretch_candidates,
                    inputs=[p for p in (a.printer, a.contraction.removesuffix(":polygon"))
                            if p and p not in ("auto", "seed", "table", "table-polygon")],
                    progress=a.progress)
    a.progress.close()
    print(f"design written to {a.output} in {r['time_s']:.1f} s")
    for note in r.get("target_repairs") or ():
        print(f"note: {os.path.basename(a.target)}: {note}")
    if r.get("stretch_choice"):
        c = r["stretch_choice"]
        print("stretch auto: " + ", ".join(
            f"s {row['stretch']:g}: " + (f"{_curvature_fit(row)}, "
                                         f"{100 * row['out_of_bounds']:.1f} % out of bounds" if "error" not in row
                                         else "cannot be designed")
            for row in c["candidates"]) + f" -> {c['chosen']:g}" + (" (verified)" if c.get("verified") else ""))
        if c.get("verified"):
            print("verified: " + ", ".join(
                f"{v['design']} s {v['stretch']:g} " + ("did not converge" if v["deviation_means_pct"] is None else
                                                        "{:.2f} / {:.2f} %".format(*v["deviation_means_pct"]))
                for v in c["verified"]) + " (deployed -> target / target -> deployed, mean)")
    px = r.get("proxy") or {}
    auto = px.get("auto")
    if isinstance(auto, dict) and "distance_pct" in px:
        def both(m):
            return "did not converge" if m is None else f"{m[0]:.2f} / {m[1]:.2f} %"
        print(f"proxy auto: designed for the target it deploys {both(auto['target'])}, for a proxy surface "
              f"{px['distance_pct'][0]:.2f} % from the target {both(auto['proxy'])} (deployed -> target / "
              f"target -> deployed, mean) -> kept the {auto['kept']}'s design")
    elif isinstance(auto, dict):
        print(f"proxy auto: the target's flattening is within the stretch bounds at s {auto['stretch']:g}; "
              f"designed for the target")
    elif auto:
        print(f"proxy auto: {auto}")
    if px.get("used"):
        dp, oob = px["distance_pct"], px["out_of_bounds_pct"]
        print(f"designed for a proxy surface within the stretch bounds, {dp[0]:.2f} / {dp[1]:.2f} % from the target "
              f"(mean / max): the target's flattening is out of them on {oob[0]:.1f} / {oob[1]:.1f} % of the area")
    warning = (r.get("curvature_reach") or {}).get("warning")
    if warning:
        print(f"warning: {warning}")
    if r.get("deviation_pct_bbox"):
        dev, back = r["deviation_pct_bbox"], r["deviation_target_to_deployed_pct_bbox"]
        print(f"deployed -> target {dev[0]:.2f} / {dev[1]:.2f} %, target -> deployed {back[0]:.2f} / {back[1]:.2f} % "
              f"(mean / max, % of the bounding-box diagonal)")
        flat = r.get("flat_deviation_pct_bbox")
        if flat:
            fb = r["flat_deviation_target_to_flat_pct_bbox"]
            print(f"a flat sheet of the target's area: {flat[0]:.2f} / {flat[1]:.2f} %, {fb[0]:.2f} / {fb[1]:.2f} %")
        if r.get("verify_warning"):
            print(f"warning: {r['verify_warning']}")
    elif "verify_converged" in r:
        print(f"verification: {r.get('verify_note', r.get('verify_reason'))}")
    for line in _refine_lines(r):
        print(line)


def _refine_lines(r) -> list:
    """The lines `selfshape design --refine` prints about the refinement of the report ``r``."""
    ref = r.get("refine")
    if ref is None:
        return []
    if not ref.get("ok"):
        return [f"refinement failed, open-loop design kept: {ref['reason']}"]
    if ref.get("kept") == "open loop":
        lines = [f"refined in {ref['outer_iterations']} outer iterations, {ref['seconds']:.0f} s, not kept: "
                 f"{ref['kept_note']}"]
    else:
        ol = r.get("open_loop", {})
        was = ""
        if ol.get("deviation_pct_bbox"):
            was = "; open loop was " + ", ".join(f"{v[0]:.2f} / {v[1]:.2f} %" for v in (
                ol["deviation_pct_bbox"], ol.get("deviation_target_to_deployed_pct_bbox")) if v)
        lines = [f"refined in {ref['outer_iterations']} outer iterations, {ref['seconds']:.0f} s ({ref['reason']}){was}"]
    ran = [x for x in ref.get("starts", []) if x.get("converged")]
    if len(ran) > 1:
        lines.append("refined from " + " and from ".join(
            f"the {x['start']} (rms {x['rms_mm_start']:.2f} -> {x['rms_mm']:.2f} mm)" for x in ran)
            + f"; kept the one from the {ref['start']}")
    failed = [x for x in ref.get("starts", []) if x.get("converged") is False]
    if ran and failed:
        lines.append(f"refined from the {ref['start']} only; " + "; ".join(
            f"from the {x['start']}: {x['reason'].removeprefix('refine: ')}" for x in failed))
    if ref.get("kept") == "refined, on a jig":
        lines.append(ref["release_note"])
    return lines


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
    r = validate_file(a.data, a.output, seed=a.seed, progress=a.progress)
    a.progress.close()
    print(f"error before {r['error_before']:.4f}, after {r['error_after']:.4f}; "
          f"effects added: {', '.join(r['effects_added']) or 'none'} -> {a.output}")


def _cmd_predict(a):
    from validation.model_file import check_predict  # input contract (issue 19): model.json, rows, -o
    check_predict(a.model, a.data, a.output)
    from validation.loop import predict_file
    n = predict_file(a.model, a.data, a.output)
    print(f"wrote {n} predictions to {a.output}")


def _cmd_export(a):
    from geometry.cad import export_pattern_file
    r = export_pattern_file(a.pattern, a.output)
    print(f"wrote {r['path']}: {r['n_shapes']} polylines on layers {', '.join(r['layers'])} (mm)")


def _cmd_view(a):
    from forward.view import write_view
    path = write_view(a.folder)
    if a.open:
        import webbrowser
        webbrowser.open("file://" + os.path.abspath(path))
    print(f"wrote {path}: open it in a browser (works offline)")


# ---------------------------------------------------------------- calibration prints (issue 23)
def _cmd_calibration_print(a):
    from inverse.printer import load_printer
    from validation import calibration_prints as cp
    printer = load_printer(a.printer) if a.printer else None
    common = dict(layer_height_mm=a.layer_height, gap_mm=a.gap, inputs=[a.printer] if a.printer else (),
                  thickness_mm=a.thickness, sides=a.sides, shuffle=a.shuffle)
    if a.kind == "strips":
        s = cp.calibration_strips(a.output, printer, repetitions=a.repetitions, stretch=a.stretch,
                                  orientation_deg=a.orientation, width_mm=a.width, length_mm=a.length,
                                  fabric_thickness_mm=a.fabric_thickness, **common)
        what, table = f"{s['specimens']} strips", "strips.csv"
    else:
        sim = dict(mesh_size=a.mesh_size, across=a.across, max_iterations=a.max_iterations,
                   start_curvature=a.start_curvature, start_direction=a.start_direction, seed=a.seed)
        s = cp.calibration_law(a.output, printer, spacing_mm=a.spacing, stretch=a.stretch, rows=a.rows,
                               motifs=a.motifs, repetitions=a.repetitions, simulate=a.simulate, from_rows=a.from_rows, mirror_back=a.mirror_back,
                               sim_options=sim, calibration=a.calibration, **common)
        what, table = f"{s['patches']} patches", "law_measurements.csv"
        if "fill" in s:
            f = s["fill"]
            table += (f" (filled from {f['source']}: {f['simulated']} simulated, {f['not_converged']} not converged, "
                      f"{f['mirrored']} mirrored, {f['missing']} missing)")
    print(f"{what} on {len(s['frames'])} frame(s), layer height {s['layer_height_mm']:g} mm -> {a.output} "
          f"(G-code, maps, {table})")


def _cmd_law(a):
    from validation.law_build import build_law
    r = build_law(a.measured, a.output, thickness=a.thickness, spacing=a.spacing, mirror_back=a.mirror_back,
                  plastic_young_modulus_mpa=a.plastic_modulus, calibration=a.calibration)
    plastic = (f"plastic E {r['plastic_young_modulus_mpa']:.6g} MPa" if r["plastic_young_modulus_mpa"] is not None
               else "no plastic modulus stated: design --law simulates it with the default plastic "
                    "(--calibration or --plastic-modulus)")
    print(f"law at stretch {r['stretch']:g}: {r['cells']} rows from {r['patches']} patches, {plastic} -> {r['output']}")


def _add_calibration_verbs(sub):
    """``calibration-print strips|law`` and ``law build`` (validation.calibration_prints, validation.law_build)."""
    c = sub.add_parser("calibration-print", help="G-code, map and template of calibration specimens "
                       "(validation.calibration_prints)")
    kinds = c.add_subparsers(dest="kind", required=True)
    st = kinds.add_parser("strips", help="bilayer strips for `calibrate strips` (seed section 3.3)")
    lw = kinds.add_parser("law", help="parallel-ribbon patches for `law build` (seed Fig. 5.7)")
    for q in (st, lw):
        q.add_argument("-o", "--output", required=True, help="output directory")
        q.add_argument("--printer", default=None, help="printer TOML (inverse.printer.Printer fields)")
        q.add_argument("--thickness", type=_POSITIVE, nargs="+", default=None, help="plastic thicknesses, mm")
        q.add_argument("--sides", nargs="+", choices=["front", "back"], default=None)
        q.add_argument("--layer-height", type=_POSITIVE, default=None,
                       help="mm (default: the printer's, or the largest printer height / k dividing every thickness)")
        q.add_argument("--gap", type=_number(0.0), default=8.0, help="fabric between specimens, mm")
        q.add_argument("--shuffle", type=_SEED, default=None, metavar="SEED",
                       help="place specimens of one size in a seeded random order (default: in order)")
    st.add_argument("--repetitions", type=_COUNT, default=None, help="strips per thickness, side, orientation, stretch")
    lw.add_argument("--repetitions", type=_COUNT, default=None, help="patches per side, thickness and spacing (1)")
    st.add_argument("--stretch", type=_number(1.0, lo_open=True), nargs="+", default=None,
                    help="fabric pre-stretches (one frame set each)")
    st.add_argument("--orientation", type=_number(), nargs="+", default=None, help="strip axes from x, degrees")
    st.add_argument("--width", type=_POSITIVE, default=None, help="strip width, mm")
    st.add_argument("--length", type=_POSITIVE, default=None, help="strip length, mm")
    st.add_argument("--fabric-thickness", type=_POSITIVE, default=None, help="measured fabric thickness, mm")
    lw.add_argument("--spacing", type=_POSITIVE, nargs="+", default=None, help="transverse spacings mu2, mm")
    lw.add_argument("--stretch", type=_number(1.0, lo_open=True), default=None, help="fabric pre-stretch")
    lw.add_argument("--rows", type=_COUNT, default=None, help="ribbon rows per patch")
    lw.add_argument("--motifs", type=_COUNT, default=None, help="dash periods along a patch (at least)")
    lw.add_argument("--simulate", action="store_true", help="fill the measured columns by simulating each patch")
    lw.add_argument("--from-rows", default=None, help="fill them from a rows JSON of studies/thickness_law_sim.py")
    lw.add_argument("--mirror-back", action="store_true", help="back cells = front cells (not simulated/looked up)")
    lw.add_argument("--calibration", default=None, help="calibrate strips parameters.json for the simulated plastic")
    lw.add_argument("--mesh-size", type=_POSITIVE, default=None, help="--simulate: fabric edge length, mm (3)")
    lw.add_argument("--across", type=_POSITIVE, default=None, help="--simulate: triangle rows across a ribbon (2)")
    lw.add_argument("--max-iterations", type=_COUNT, default=None, help="--simulate: Newton cap (800)")
    lw.add_argument("--start-curvature", type=_number(0.0), default=None, help="--simulate: start rolled, 1/mm")
    lw.add_argument("--start-direction", choices=["along", "across"], default=None)
    lw.add_argument("--seed", type=_SEED, default=None, help="--simulate: seed of the start perturbation")
    c.set_defaults(fn=_cmd_calibration_print)

    lb = sub.add_parser("law", help="build a curvature-law table from patch measurements (validation.law_build)")
    lb.add_argument("action", choices=["build"])
    lb.add_argument("measured", help="law_measurements.csv")
    lb.add_argument("-o", "--output", required=True, help="law CSV (for design --law)")
    lb.add_argument("--thickness", type=_POSITIVE, nargs="+", default=None, help="use only these thicknesses, mm")
    lb.add_argument("--spacing", type=_POSITIVE, nargs="+", default=None, help="use only these spacings, mm")
    lb.add_argument("--mirror-back", action="store_true", help="the back grid is the front one")
    lb.add_argument("--plastic-modulus", type=_POSITIVE, default=None,
                    help="plastic_young_modulus_mpa the law states (MPa; default: the template's, if any)")
    lb.add_argument("--calibration", default=None,
                    help="calibrate strips parameters.json: the law states its plastic (modulus ratio x fabric E)")
    lb.set_defaults(fn=_cmd_law)


# ---------------------------------------------------------------- sweeps (issue 21)
def _cmd_sweep(a):
    from validation.sweep import run_sweep

    def line(row, done, total):
        # the status line (terminal): cases done / total and the time left; stdout: a line per finished case
        a.progress({"stage": "tasks", "done": done, "total": total, "unit": "cases",
                    "last": row and f"#{row['index']} {row['status']}"})
        if row is not None:
            a.progress.print_above(f"case {done}/{total} #{row['index']} {row['status']} "
                                   f"({row.get('time_s') or 0:.1f} s) {row['case']}")
    r = run_sweep(a.sweep, a.output, scheduler=a.scheduler, workers=a.workers, progress=line)
    a.progress.close()
    print(f"{r['cases']} cases: {r['ran']} run, {r['reused']} reused, {r['failed']} not ok "
          f"({', '.join(f'{k} {v}' for k, v in sorted(r['statuses'].items()))}), {r['time_s']:.1f} s -> "
          f"{os.path.join(a.output, 'results.csv')}")
    return 1 if r["failed"] else 0


def _add_sweep_verb(sub):
    """``sweep SWEEP.toml -o DIR`` (validation.sweep.run_sweep)."""
    w = sub.add_parser("sweep", help="many simulations or designs of a sweep file as Dask tasks, one table "
                                     "(validation.sweep.run_sweep)")
    w.add_argument("sweep", help="sweep .toml (docs/sweeps.md)")
    w.add_argument("-o", "--output", required=True, help="output directory (resumable: finished cases are kept)")
    w.add_argument("--scheduler", default=None, help="address of a running Dask scheduler, e.g. tcp://host:8786")
    w.add_argument("--workers", type=_number(0, integer=True), default=None,
                   help="local worker processes (default: one per core; 0: serially in this process)")
    w.add_argument("-v", "--verbose", action="store_true", help="show the libraries' and Dask's messages")
    w.add_argument("-q", "--quiet", action="store_true", help="no progress line on a terminal")
    w.set_defaults(fn=_cmd_sweep)


def build_parser() -> argparse.ArgumentParser:
    from inverse.to_pattern import VERIFY_ITERATIONS, VERIFY_MESH_ACROSS, VERIFY_MESH_SIZE_MM
    p = _Parser(prog="selfshape", description="Self-shaping textiles: simulate, design, calibrate.")
    sub = p.add_subparsers(dest="verb", required=True)

    m = sub.add_parser("mesh", help="conforming Gmsh mesh of a pattern (geometry.meshing.mesh_pattern_file)")
    m.add_argument("pattern", help="pattern .toml or .gcode")
    m.add_argument("-o", "--output", required=True, help="output .msh")
    m.add_argument("--size", type=_POSITIVE, default=None, help="override [mesh] size_mm")
    m.set_defaults(fn=_cmd_mesh)

    s = sub.add_parser("simulate", help="released equilibrium of a pattern (forward.simulate.simulate_pattern_file)")
    s.add_argument("pattern")
    s.add_argument("-o", "--output", required=True, help="output directory")
    s.add_argument("--size", type=_POSITIVE, default=None, help="override [mesh] size_mm")
    s.add_argument("--seed", type=_SEED, default=None, help="override [solver] seed")
    s.add_argument("--max-iterations", type=_COUNT, default=None, help="override [solver] max_iterations")
    s.add_argument("--coarse-levels", type=_levels, default=None,
                   help="override [solver] coarse_levels: 'auto' or N >= 0 coarser meshes solved first (0: none)")
    s.add_argument("--no-png", action="store_true", help="skip deployed.png")
    s.add_argument("-v", "--verbose", action="store_true")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress line on a terminal")
    s.set_defaults(fn=_cmd_simulate)

    d = sub.add_parser("design", help="inverse design from a target surface (inverse.design.design_file)")
    d.add_argument("target")
    d.add_argument("-o", "--output", required=True)
    d.add_argument("--verify", action="store_true", help="simulate the design and report its deviation")
    d.add_argument("--verify-iterations", type=_COUNT, default=VERIFY_ITERATIONS,
                   help=f"Newton iteration cap of --verify, also written to pattern.toml [solver] (default {VERIFY_ITERATIONS})")
    d.add_argument("--refine", action="store_true",
                   help="refine the ribbon thicknesses with the shell in the loop (implies --verify)")
    d.add_argument("--mesh-size", type=_POSITIVE, default=VERIFY_MESH_SIZE_MM,
                   help=f"pattern.toml [mesh] size_mm of the verification, mm (default {VERIFY_MESH_SIZE_MM:g})")
    d.add_argument("--mesh-across", type=_POSITIVE, default=VERIFY_MESH_ACROSS,
                   help=f"pattern.toml [mesh] across: triangle rows across a ribbon (default {VERIFY_MESH_ACROSS:g}; "
                        "2, the thickness laws' own, moves a design's deviation by ~0.05 %% mean at 3x the time)")
    d.add_argument("-v", "--verbose", action="store_true")
    d.add_argument("-q", "--quiet", action="store_true", help="no progress line on a terminal")
    d.add_argument("--diagonal", type=_schema_number("DESIGN_NUMBERS", "diagonal_mm"), default=110.0,
                   help="scale the target to this bounding-box diagonal, mm (10-5000)")
    d.add_argument("--stretch", type=_stretch, default="auto",
                   help="fabric pre-stretch s, or 'auto' (default): the shipped law's stretch that fits the target best")
    d.add_argument("--stretch-candidates", type=_schema_number("DESIGN_NUMBERS", "stretch_candidates"), default=1,
                   metavar="N", help="with --stretch auto and --verify or --refine: verify the designs at the N best "
                                     "stretches by the choice's score and keep the one that deploys nearest (default 1)")
    d.add_argument("--law", default=None, help="curvature-law CSV (default: the shipped inverse/data table)")
    d.add_argument("--contraction", default="auto",
                   help="how stretch maps to ribbon spacing: 'auto' (default: the shipped table of simulated patches "
                        "at the stretch where there is one, else the seed's Eq. 5.15), 'seed', 'table', "
                        "'table-polygon' (its admissible stretches bound the flattening too) or a table CSV")
    d.add_argument("--lam", type=_schema_number("DESIGN_NUMBERS", "lam"), default=0.0, help="line-field lambda of the seed (<= 0, 1/mm^2)")
    d.add_argument("--printer", default=None,
                   help="printer TOML (inverse.printer.Printer fields: bed_size, nozzle_mm, print_speed_mm_s, ...)")
    d.add_argument("--proxy", nargs="?", const="on", default=None, choices=PROXY_VALUES,
                   help="where the target's flattening is far out of the stretch bounds, design for the nearest smooth "
                        "surface within them (still verified and refined against the target); 'auto' (with --verify "
                        "or --refine): verify the designs for the target and for the proxy, keep the nearer "
                        "(default: 'auto' with --refine, else 'off')")
    d.set_defaults(fn=_cmd_design)

    c = sub.add_parser("calibrate", help="fit material parameters (validation.strips / validation.fabric)")
    c.add_argument("kind", choices=["strips", "fabric"])
    c.add_argument("data")
    c.add_argument("-o", "--output", required=True)
    c.set_defaults(fn=_cmd_calibrate)

    v = sub.add_parser("validate", help="the closed validation loop (validation.loop.validate_file)")
    v.add_argument("data")
    v.add_argument("-o", "--output", required=True)
    v.add_argument("--seed", type=_SEED, default=0, help="seed of the cross-validation splits")
    v.add_argument("-q", "--quiet", action="store_true", help="no progress line on a terminal")
    v.set_defaults(fn=_cmd_validate)

    r = sub.add_parser("predict", help="apply a fitted model.json (validation.loop.predict_file)")
    r.add_argument("model")
    r.add_argument("data")
    r.add_argument("-o", "--output", required=True)
    r.set_defaults(fn=_cmd_predict)
    x = sub.add_parser("export", help="the flat pattern as DXF or SVG in mm, without simulating "
                                      "(geometry.cad.export_pattern_file)")
    x.add_argument("pattern", help="pattern .toml or .gcode")
    x.add_argument("-o", "--output", required=True, help="output .dxf or .svg")
    x.set_defaults(fn=_cmd_export)
    w = sub.add_parser("view", help="DIR/index.html: the 3D page of a simulate or design folder (forward.view.write_view)")
    w.add_argument("folder", help="an output folder of selfshape simulate or design")
    w.add_argument("--open", action="store_true", help="also open it in the default browser")
    w.set_defaults(fn=_cmd_view)

    _add_calibration_verbs(sub)
    _add_sweep_verb(sub)
    return p


PROXY_VALUES = ("on", "off", "auto")


def _bare_proxy_is_on(argv: list) -> list:
    """``--proxy`` not followed by one of PROXY_VALUES means ``--proxy on`` (its meaning before
    it took a value): argparse would otherwise take the target path after it as the value."""
    out = []
    for i, a in enumerate(argv):
        out.append(a)
        if a == "--proxy" and (i + 1 == len(argv) or argv[i + 1] not in PROXY_VALUES):
            out.append("on")
    return out


def main(argv=None) -> int:
    """Run ``selfshape ARGV``; returns the exit status (0, 1 not converged, 2 bad input or
    usage, 3 internal error, 130 interrupted) instead of exiting, so tests can call it."""
    from shellfem.errors import SelfshapeError
    argv = _bare_proxy_is_on(sys.argv[1:] if argv is None else list(argv))
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:       # a usage error (one line, status 2) or --help (status 0)
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    from shellfem.memory import keep_freed_memory
    keep_freed_memory()
    from selfshape.progress import StatusLine
    # the status line of the long verbs (those with --quiet): a terminal's stderr only, erased
    # before the result or error line (selfshape.progress)
    args.progress = StatusLine.for_stderr(
        args.verb, "quiet" in args and not args.quiet and not getattr(args, "verbose", False))
    try:
        try:
            with _quiet(not getattr(args, "verbose", False)):
                rc = args.fn(args)
        finally:
            args.progress.close()
    except SelfshapeError as e:
        print(f"selfshape {args.verb}: error: {_printable(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"selfshape {args.verb}: interrupted", file=sys.stderr)
        return 130
    except (Exception, SystemExit) as e:  # never a traceback: one line, and a distinct status
        # (SystemExit: a library that calls exit() inside a verb is an internal error, not status 1)
        msg = _printable(e.code if isinstance(e, SystemExit) else e) or type(e).__name__
        print(f"selfshape {args.verb}: internal error ({type(e).__name__}): {msg}", file=sys.stderr)
        return 3
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
