"""Write the validation page (docs/validation.md) from the studies' JSON outputs.

    python studies/validation_page.py [--runs out/validation] [--json docs/validation/json]
                                      [--page docs/validation.md] [--figures docs/validation]

Run from the repository root. With --runs DIR, the JSON that the studies wrote to DIR
(studies/figures.py --out DIR, or each study's --out) is first copied to --json:
convergence.json, sze.json, natural_curvature.json, fabric/parameters.json -> fabric.json,
strips/parameters.json -> strips.json, loop/report.json -> loop.json. Without --runs the page
is rebuilt from the JSON already in --json (committed with the page), so the page always says
what its JSON says. For every verified figure the page gives the quantity, our number, the
exact or published reference and its source, the error, the picture (from --figures) and the
command that regenerates it; a study whose JSON is missing is listed as not run.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil

from shellfem.materials import Fabric
from shellfem.materials.orthotropic import TABLE_4_1_ORTHOTROPIC
from validation.references import SZE_END_MOMENT

#: the studies' JSON in a --runs directory -> its name in --json
SOURCES = {"convergence": "convergence.json", "sze": "sze.json", "natural_curvature": "natural_curvature.json",
           "fabric": os.path.join("fabric", "parameters.json"), "strips": os.path.join("strips", "parameters.json"),
           "loop": os.path.join("loop", "report.json"), "loop_recovery": "loop_recovery.json"}
SZE = ("K. Y. Sze, X. H. Liu, S. H. Lo (2004), Popular benchmark problems for geometric nonlinear "
       "analysis of shells, Finite Elements in Analysis and Design 40")
SEED = "the seed"


def copy_runs(runs: str, json_dir: str) -> list:
    """Copy the studies' JSON from a run directory to json_dir; returns the names copied."""
    os.makedirs(json_dir, exist_ok=True)
    copied = []
    for name, rel in SOURCES.items():
        src = os.path.join(runs, rel)
        if os.path.exists(src):
            shutil.copyfile(src, os.path.join(json_dir, f"{name}.json"))
            copied.append(name)
    return copied


def _load(json_dir: str) -> dict:
    out = {}
    for name in SOURCES:
        path = os.path.join(json_dir, f"{name}.json")
        if os.path.exists(path):
            with open(path) as fh:
                out[name] = json.load(fh)
    return out


def _g(v, nd=4) -> str:
    """A number to nd significant digits (lists joined with ' / ')."""
    if isinstance(v, (list, tuple)):
        return " / ".join(_g(x, nd) for x in v)
    return f"{v:.{nd}g}"


def _pct(ours, ref, nd=2) -> str:
    """Relative error ours / ref - 1 in percent (lists element-wise)."""
    if isinstance(ours, (list, tuple)):
        return " / ".join(_pct(a, b, nd) for a, b in zip(ours, ref))
    return f"{100.0 * (ours / ref - 1):+.{nd}f} %"


def _table(rows) -> list:
    lines = ["| quantity | ours | reference | source | error |", "|---|---|---|---|---|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines


class Page:
    """Markdown lines; pictures linked relative to the page."""

    def __init__(self, page: str, figures: str):
        self.lines, self.page, self.figures = [], page, figures

    def add(self, *lines):
        self.lines.extend(lines)

    def pictures(self, *names):
        here = os.path.dirname(os.path.abspath(self.page))
        links = [f"![{os.path.splitext(n)[0]}]({os.path.relpath(os.path.join(self.figures, n), here)})"
                 for n in names]
        self.add("", " ".join(links))

    def command(self, cmd: str, quick: bool | None = None):
        note = "" if quick is None else (" (these numbers: the `--quick` variant)" if quick
                                         else " (these numbers: the full study)")
        self.add("", f"Regenerate: `{cmd}`, then `python studies/validation_page.py --runs out/validation`{note}.")

    def missing(self, title: str, cmd: str):
        self.add(f"## {title}", "", f"Not run: no JSON. Run `{cmd}`, then "
                 "`python studies/validation_page.py --runs out/validation`.", "")


# --------------------------------------------------------------------------- sections


def sze_section(p: Page, d: dict):
    cmd = "python studies/sze.py" + (" --quick" if d["quick"] else "")
    es, em, sp = d["end_shear"], d["end_moment"], d["slit_plate"]
    p.add("## Large rotations: Sze, Liu & Lo (2004)", "",
          "Cantilever L = 10 (3.1) and L = 12 (3.2), b = 1, h = 0.1, E = 1.2e6, nu = 0, one held row of "
          "elements as the clamp; slit annular plate (3.3) R_i = 6, R_o = 10, t = 0.03, E = 21e6, nu = 0, "
          "line force q up to 0.8 on one slit edge, structured polar meshes (quads split in two).", "")
    rows = [["3.1 end shear, tip (-u, w) at P_max (40 x 2 quads)", _g(es["tip_final"]), _g(es["published_tip"]),
             "Sze et al. 2004; the elastica (validation.references.elastica_end_shear)",
             _pct(es["tip_final"], es["published_tip"])],
            ["3.1 end shear, worst tip error over 8 load steps / L", _g(es["max_error_over_L"], 3), "0",
             "the inextensible elastica (collocation BVP)", f"{100 * es['max_error_over_L']:.2f} % of L"],
            ["3.2 end moment, worst tip error over 16 load steps / L", _g(em["max_error_over_L"], 3), "0",
             "circular arc of curvature M / EI (exact)", f"{100 * em['max_error_over_L']:.2f} % of L"]]
    for frac, tip in SZE_END_MOMENT["tip"].items():
        if frac in em["load_fraction"] and frac < 1.0:
            k = em["load_fraction"].index(frac)
            ours = [em["tip_u"][k], em["tip_w"][k]]
            rows.append([f"3.2 end moment, tip (-u, w) at M / M_max = {frac:g}", _g(ours), _g(list(tip)),
                         "Sze et al. 2004", _pct(ours, list(tip))])
    pub = sp["published"]
    for m in sp["meshes"]:
        rows.append([f"3.3 slit plate, w_A / w_B at q_max, {m['mesh'].split(',')[0]}",
                     _g([m["w_A"], m["w_B"]]), _g([pub["w_A"], pub["w_B"]]), "Sze et al. 2004",
                     _pct([m["w_A"], m["w_B"]], [pub["w_A"], pub["w_B"]])])
    for e in sp["richardson_first_order"]:
        rows.append([f"3.3 slit plate, first-order Richardson estimate {e['pair']}", _g([e["w_A"], e["w_B"]]),
                     _g([pub["w_A"], pub["w_B"]]), "Sze et al. 2004",
                     _pct([e["w_A"], e["w_B"]], [pub["w_A"], pub["w_B"]])])
    p.add(*_table(rows))
    p.add("", "The slit plate converges monotonically from below, more slowly than first order; the first-order "
          "Richardson estimates of successive mesh pairs bracket the published values.", "", f"Source: {SZE}.")
    p.pictures("sze_end_shear.png", "sze_end_moment.png", "sze_slit_plate.png")
    p.command(cmd, d["quick"])
    p.add("")


def natural_curvature_section(p: Page, d: dict):
    cmd = "python studies/natural_curvature.py" + (" --quick" if d["quick"] else "")
    disk, roll = d["disk"], d["roll"]
    lo, hi = disk["engine_threshold_bracket"]
    ritz = disk["ritz_threshold"]
    p.add("## Natural curvature: disk bifurcation and wide bilayer roll", "",
          "Free disk R = 10, h = 0.1, nu = 0.3 with isotropic rest curvature kappa0, swept in kappa0 R^2 / h: "
          "spherical (k_min / k_max > 0.9) below a threshold, cylindrical above. Wide bilayer: plastic 0.3 mm "
          "over the whole 30 mm wide sheet on 0.8 mm fabric, s = 1.05, axis length L.", "")
    rows = [["disk: sphere-to-cylinder threshold kappa0 R^2 / h (last spherical, first cylindrical state)",
             f"{lo:g} - {hi:g}", _g(ritz, 3),
             "uniform-curvature Ritz model 8 / (1 + nu)^1.5 (as Masters & Salamon 1994, Freund 2000)",
             f"{_pct(lo, ritz, 1)} to {_pct(hi, ritz, 1)}"]]
    for L, k, dfc in zip(roll["lengths"], roll["k_interior"], roll["deficit"]):
        rows.append([f"roll: interior curvature (1/mm), axis {L:g} mm", _g(k), _g(roll["k_plate"]),
                     "plate curvature of the uniform-state bilayer (shellfem.strip, closed form)",
                     f"{-100 * dfc:+.1f} %"])
    p.add(*_table(rows))
    p.add("", "The roll's deficit is a finite-length effect: it falls as the axis grows (the closed form is the "
          "infinite-plate limit).")
    p.pictures("disk_bifurcation.png", "bilayer_roll.png")
    p.command(cmd, d["quick"])
    p.add("")


def convergence_section(p: Page, d: dict):
    cmd = "python studies/convergence.py" + (" --quick" if d["quick"] else "")
    s, g = d["strip"], d["thickness_gradient"]
    closed = s["closed_form_narrow_per_mm"]
    p.add("## Mesh convergence on unstructured Gmsh meshes", "",
          "(a) Free 40 x 2 mm bilayer strip (plastic 0.3 mm on 0.8 mm fabric, s = 1.05): longitudinal curvature "
          "over the middle half. (b) 40 x 3 mm sheet with plastic thickness linear in x from 0.15 to 0.45 mm: "
          "RMS distance of the deployed positions to the finest mesh's, after the best rigid alignment.", "")
    rows = [[f"strip curvature (1/mm), mesh {m['size_mm']:g} mm", _g(m["curvature_per_mm"], 6), _g(closed, 6),
             "narrow-strip closed form (shellfem.strip, zero-width limit)", _pct(m["curvature_per_mm"], closed, 3)]
            for m in s["meshes"]]
    rows.append(["strip curvature, Richardson limit of the two finest meshes", _g(s["richardson_limit_per_mm"], 6),
                 _g(closed, 6), "narrow-strip closed form (the 2 mm strip's own limit lies below it)",
                 _pct(s["richardson_limit_per_mm"], closed, 3)])
    rows.append(["strip: observed order against the Richardson limit", _g(s["observed_order_vs_richardson"], 3),
                 "-", "slope of log error vs log mesh size", "-"])
    ref = g["reference"]["size_mm"]
    rows += [[f"gradient sheet: RMS to the {ref:g} mm mesh (mm), mesh {m['size_mm']:g} mm",
              _g(m["rms_to_finest_mm"], 3), "0", f"the {ref:g} mm mesh (self-convergence)", "-"]
             for m in g["meshes"]]
    rows.append(["gradient sheet: observed order", _g(g["observed_order"], 3), "-",
                 "slope of log RMS vs log mesh size", "-"])
    p.add(*_table(rows))
    p.pictures("convergence.png")
    p.command(cmd, d["quick"])
    p.add("")


def fabric_section(p: Page, d: dict):
    o = d["orthotropic"]
    pct = _g(d["orthotropic_max_stretch_pct"], 3)
    p.add("## Fabric calibration (validation/data/fabric)", "",
          f"Orthotropic log-barrier parameters fitted at {pct} % stretch so that the model in uniaxial stress "
          "reproduces the 0 and 90 deg tensile curves; the 15-75 deg curves validate it. The data are synthetic "
          "lab measurements (validation/data/README.md); the seed's Table 4.1 is the seed's own fabric, the "
          "closest published reference. Values [value, standard error], MPa (g1, g2: Green strain).", "")
    rows = [[f"{k} ({'Green strain' if k[0] == 'g' else 'MPa'})", f"{_g(o[k][0])} +- {_g(o[k][1], 2)}",
             _g(TABLE_4_1_ORTHOTROPIC[k]), f"{SEED}, Table 4.1", _pct(o[k][0], TABLE_4_1_ORTHOTROPIC[k])]
            for k in ("a1", "a2", "a3", "b1", "b2", "g1", "g2")]
    val = d["fit_quality"]["validation"][max(d["fit_quality"]["validation"], key=float)]   # at pct
    for deg, v in sorted(val.items(), key=lambda kv: float(kv[0])):
        if v.get("rel_rms") is not None and deg not in ("0", "90"):
            rows.append([f"tensile curve {deg} deg (held out): model vs measured stress", "-", "measured curve",
                         f"validation/data/fabric/tensile_{int(float(deg)):02d}deg_*.csv",
                         f"{100 * v['rel_rms']:.2f} % RMS"])
    kb = d["bending_stiffness_mean_nmm"]
    kb_ref = Fabric().bending_stiffness
    rows.append(["bending stiffness k_B, mean of orientations and faces (N mm)", f"{_g(kb[0])} +- {_g(kb[1], 2)}",
                 _g(kb_ref), f"{SEED} (the engine's default)", _pct(kb[0], kb_ref)])
    p.add(*_table(rows))
    p.pictures(*[f"fabric_tensile_{deg}deg.png" for deg in ("0", "15", "30", "45", "60", "75", "90")],
               "fabric_shear.png", "fabric_master_curve.png")
    p.command("python studies/figures.py --only fabric")
    p.add("", "The same fit as a user runs it: `selfshape calibrate fabric validation/data/fabric -o DIR`.")
    p.add("")


def strips_section(p: Page, d: dict):
    v, se = d["modulus_ratio"]
    lo, hi = d["confidence_intervals_95"]["modulus_ratio"]
    f = d["fit"]
    p.add("## Strip calibration (validation/data/strips_S1.csv)", "",
          f"E_plastic / E_fabric by nonlinear least squares on the engine's narrow-strip model, plastic flat at rest "
          f"({f['n_rows']} strips). No closed form: the reference is the measurement.", "")
    rows = [["modulus ratio E_plastic / E_fabric", f"{_g(v)} +- {_g(se, 2)} (95 % CI {_g(lo)} - {_g(hi)})",
             "-", "fitted to the measured curvatures", "-"],
            ["curvature fit residual (1/mm)", _g(f["rms_residual_per_mm"], 3), "measured curvatures",
             "validation/data/strips_S1.csv", f"{100 * f['relative_rms']:.1f} % RMS"]]
    if "modulus_ratio_rest_measured" in d:
        w, wse = d["modulus_ratio_rest_measured"]
        rows.append(["modulus ratio with the measured rest curvature", f"{_g(w)} +- {_g(wse, 2)}", "-",
                     "fitted with rest_curvature_per_mm", "-"])
    s, sse = d["modulus_ratio_seed_eq3_17"]
    rows.append(["modulus ratio by the seed's Eq. 3.17 regression", f"{_g(s)} +- {_g(sse, 2)}", "3.2e3",
                 f"{SEED}, section 3.3 (on the seed's own strips)", _pct(s, 3.2e3, 1)])
    p.add(*_table(rows))
    p.pictures("strips_strips_fit.png")
    p.command("python studies/figures.py --only strips")
    p.add("", "The same fit as a user runs it: `selfshape calibrate strips validation/data/strips_S1.csv -o DIR`.")
    p.add("")


def loop_section(p: Page, d: dict):
    p.add("## The closed validation loop (validation/data/strips_S1.csv)", "",
          "Relative RMS error on rows held out by an outer 5-fold split grouped by specimen, before (base model) "
          "and after the effects the loop adds; the reference is the noise floor, the scatter of the "
          "residuals within groups of replicate specimens (variance a + b kappa^2, additive and relative noise, "
          "fitted over the groups; the better of the additive-only and relative-only laws, both terms only "
          "when a likelihood-ratio test at 5 % prefers them). The held-out floor is that noise times "
          "sqrt(1 + p / n_train): a correct model with p parameters fitted on n_train rows has its own noise plus "
          "its parameters' estimation error on rows held out (`validation.loop.held_out_floor`).", "")
    rows = [["held-out error, base model", _g(d["error_before"], 3), _g(d["noise_relative"], 3),
             "noise floor (replicates)", f"{d['error_before'] / d['noise_relative']:.2f} x noise"],
            ["held-out error, with the effects added", _g(d["error_after"], 3), _g(d["noise_relative"], 3),
             "noise floor (replicates)", f"{d['error_after'] / d['noise_relative']:.2f} x noise"]]
    if "noise_relative_held_out" in d:
        rows.append(["held-out error, with the effects added", _g(d["error_after"], 3),
                     _g(d["noise_relative_held_out"], 3), "held-out floor (a correct model's held-out error)",
                     f"{d['error_after'] / d['noise_relative_held_out']:.2f} x held-out floor"])
    p.add(*_table(rows))
    added = ", ".join(f"`{e}`" for e in d["effects_added"]) or "none"
    p.add("", f"Effects added: {added}.")
    p.pictures("loop_residuals_before.png", "loop_residuals_after.png")
    p.command("python studies/figures.py --only loop")
    p.add("", "The same loop as a user runs it: `selfshape validate validation/data/strips_S1.csv -o DIR`.")
    p.add("")


def loop_recovery_section(p: Page, d: dict):
    p.add("## The closed loop on unseen sets with several effects (synthetic, known truth)", "",
          f"Strip sets of {d['n_points']} design points x {d['reps']} replicates from `validation.strip_sets` "
          "(the project's strip model with two or three undeclared catalogue effects, written independently of "
          f"`validation.effects`, and {100 * d.get('noise_relative', 0.015):g} % relative noise); the loop as "
          "`selfshape validate` runs it. Recovery: the effect was added or reported indistinguishable from an "
          "added one. Held-out / floor: the outer 5-fold held-out relative error over the loop's own noise-floor "
          "estimate, over its held-out floor (the estimate x sqrt(1 + p / n_train)) and over the true noise. Noncentrality: sum (misfit / sigma)^2 of the true model without "
          "the effect, fitted to the noise-free data (below ~20 the data cannot show the effect).", "")

    def table(summary):
        ho = all("heldout_over_held_out_floor_mean" in t for t in summary)
        lines = ["| case | seeds | recovery per effect | false additions | held-out / floor, mean (max) | "
                 + ("held-out / held-out floor, mean (max) | " if ho else "")
                 + "held-out / true noise | min noncentrality |", "|---|---|---|---|---|---|" + ("---|" if ho else "") + "---|"]
        for t in summary:
            rec = ", ".join(f"{e} {v:.2f}" for e, v in t["recovery"].items()) or "-"
            nc = ", ".join(f"{v:.0f}" for v in t.get("oracle_min_noncentrality", {}).values()) or "-"
            lines.append(f"| {t['case']} | {t['seeds']} | {rec} | {t['false_additions']} | "
                         f"{t['heldout_over_floor_mean']:.3f} ({t['heldout_over_floor_max']:.3f}) | "
                         + (f"{t['heldout_over_held_out_floor_mean']:.3f} ({t['heldout_over_held_out_floor_max']:.3f}) | "
                            if ho else "")
                         + f"{t['heldout_over_true_noise_mean']:.3f} | {nc} |")
        return lines

    p.add(*table(d["summary"]))
    for c in d.get("clean_false_additions", []):
        p.add("", f"Clean sets of {c['n_points']} points x {c['reps']} (selection on all rows): "
                  f"{c['with_additions']} of {c['sets']} with a false addition.")
    if "baseline" in d:
        p.add("", f"Before, the baseline: {d['baseline'].get('note') or 'the loop before issue 19'}.", "")
        p.add(*table(d["baseline"]["summary"]))
    p.command(d["command"])
    p.add("")


SECTIONS = (("sze", "Large rotations: Sze, Liu & Lo (2004)", "python studies/sze.py", sze_section),
            ("natural_curvature", "Natural curvature", "python studies/natural_curvature.py",
             natural_curvature_section),
            ("convergence", "Mesh convergence", "python studies/convergence.py", convergence_section),
            ("fabric", "Fabric calibration", "python studies/figures.py --only fabric", fabric_section),
            ("strips", "Strip calibration", "python studies/figures.py --only strips", strips_section),
            ("loop", "The closed validation loop", "python studies/figures.py --only loop", loop_section),
            ("loop_recovery", "The closed loop on sets with several effects", "python studies/loop_recovery.py",
             loop_recovery_section))


def render(data: dict, page: str, figures: str, json_dir: str) -> str:
    """The page's Markdown from the loaded JSON (a dict by study name)."""
    p = Page(page, figures)
    p.add("# Validation", "",
          "The engine against exact and published answers, and the calibration against the measurements. "
          f"Generated by `python studies/validation_page.py` from the studies' JSON in `{json_dir}/` "
          "(do not edit by hand). All runs: `python studies/figures.py` (add `--quick` for short variants), then "
          "`python studies/validation_page.py --runs out/validation`. Units: mm, N, MPa; errors are "
          "ours / reference - 1 unless stated. \"The seed\" is the thesis this project started from; its tables "
          "are quoted where no exact answer exists.", "")
    for name, title, cmd, section in SECTIONS:
        if name in data:
            section(p, data[name])
        else:
            p.missing(title, cmd)
    return "\n".join(p.lines).rstrip("\n") + "\n"


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", default=None, help="copy the studies' JSON from this run directory first")
    ap.add_argument("--json", default=os.path.join("docs", "validation", "json"))
    ap.add_argument("--page", default=os.path.join("docs", "validation.md"))
    ap.add_argument("--figures", default=os.path.join("docs", "validation"))
    a = ap.parse_args(argv)
    copied = copy_runs(a.runs, a.json) if a.runs else []
    data = _load(a.json)
    text = render(data, a.page, a.figures, a.json)
    os.makedirs(os.path.dirname(os.path.abspath(a.page)), exist_ok=True)
    with open(a.page, "w") as fh:
        fh.write(text)
    print(json.dumps({"page": a.page, "studies": sorted(data), "copied": copied}))
    return text


if __name__ == "__main__":
    main()
