"""Calibration of the fabric model from its tensile, shear and cantilever tests (seed 4.3-4.4):
``calibrate_fabric`` (the ``selfshape calibrate fabric`` verb) and parameters.json. The test
folder is read by validation.fabric_files, the curves processed by validation.fabric_curves, the
engine's law fitted by validation.fabric_law.

Units: mm, N, MPa; strains are Green strains (dimensionless).

Model (the engine's convention): Voigt Green strain eps = (e11, e22, 2 e12) in the course
frame, Psi = 1/2 eps^T C eps / (1 - nu^2) - phi1(e11) - phi2(e22),
C = [[a1, sqrt(a1 a2) nu, 0], [sqrt(a1 a2) nu, a2, 0], [0, 0, a3 (1 - nu^2)]], with the
symmetric log barrier phi_i of Eq. 4.3, whose derivative is phi_i'(e) = sign(e) b_i log(1 - |e|/g_i).
So the stress is sigma = C eps / (1 - nu^2) + (-sign(e_i) b_i log(1 - |e_i| / g_i)), Eq. 4.5.

Pipeline (``calibrate_fabric``):
- tensile files -> unloading branch of the stabilised cycles -> Green strain / 2nd Piola-Kirchhoff
  stress (Eq. 4.4) -> the seed's route: fit sigma = A e - b log(1 - e/g) (Eq. 4.6-4.7) on 0 and
  90 deg -> b1, g1, b2, g2 and a1, a2 from A1 = (a1 - sqrt(a1 a2) nu^2)/(1 - nu^2), A2 likewise
  ("orthotropic_seed_eq46"); then, from there, the model-consistent fit in which the model's own
  uniaxial-stress response matches the 0 and 90 deg curves ("orthotropic", what the engine uses).
  The largest max stretch goes first (its curves reach nearest the barrier); lower ones also
  start from its parameters, since far below the barrier the seed's route alone may define
  nothing. What the curves do not determine is left out and named under "not_identifiable";
- release (pseudo-Young) modulus: slope of each orientation's unloading curve at release,
  averaged over orientations, per max stretch;
- a3: initial slope of shear stress vs shear strain, averaged over 0 and 90 deg;
- k_B per orientation/face: least squares on the heavy-elastica master curve;
- validation: the fitted model's uniaxial-stress response at every orientation (strain
  rotated into the course frame, transverse strain and shear solved so that the lateral
  and shear stresses vanish) against the measured unloading curves.
"""
from __future__ import annotations

import math
import os

import numpy as np

from shellfem.errors import SelfshapeError
from shellfem.outfiles import OutputDir
from validation import elastica
from validation.fabric_curves import (stiffness_with_se, barrier_curve, fit_barrier_curve, fit_shear_modulus,
                                      release_tangent, shear_stress_strain, stabilised_cycles,
                                      stiffness_from_uniaxial, tensile_curve)
from validation.fabric_files import (META_KEYS, number_key, find_test_files, read_cantilever, read_meta, read_shear,
                                     read_tensile)
from validation.fabric_law import fit_orthotropic_uniaxial, uniaxial_response
from validation.plots import Series, plot_series
from validation.textfiles import finite_json, refuse_overwrite

PARAM_NAMES = ("a1", "a2", "a3", "b1", "b2", "g1", "g2")
#: The files `selfshape calibrate fabric` writes: parameters.json, shear.png, master_curve.png and
#: one tensile_<deg>deg.png per orientation (FABRIC_PLOTS); an earlier run's are removed first.
FABRIC_OUTPUTS = ("shear.png", "master_curve.png", "parameters.json")
FABRIC_PLOTS = (r"tensile_\d+(?:\.\d+)?(?:e[+-]?\d+)?deg\.png",)
MAX_STRETCH_RATIO = 10.0   # tensile extension up to 10 x the gauge length (a 1000 % stretch)
MAX_LOAD_N = 1e4           # N: a textile strip breaks long before


# ----------------------------------------------------------------------------- calibration

def _pair(v, se, what="a fitted value"):
    """[value, standard error] as finite floats; a non-finite one fails the calibration
    (parameters.json holds finite numbers only)."""
    v, se = float(v), float(se)
    if not (math.isfinite(v) and math.isfinite(se)):
        raise SelfshapeError(f"calibration produced a non-finite {what} ({v!r} +- {se!r}): "
                             "the tests do not determine it")
    return [v, se]


def _mean_with_se(values, ses):
    values, ses = np.asarray(values, float), np.asarray(ses, float)
    return float(values.mean()), float(np.sqrt(np.sum(ses ** 2)) / values.size)


def interpolate_by_stretch(values_by_pct: dict, stretch_pct: float):
    """Seed rule: linear interpolation in the max stretch (percent) between measured values
    (dict pct-string -> number or dict of numbers); clamped to the nearest measured stretch
    outside the measured range."""
    keys = sorted(values_by_pct, key=float)
    xs = np.array([float(k) for k in keys])
    p = float(np.clip(stretch_pct, xs[0], xs[-1]))
    i = int(np.clip(np.searchsorted(xs, p) - 1, 0, max(len(xs) - 2, 0)))
    if len(xs) == 1:
        return values_by_pct[keys[0]]
    t = (p - xs[i]) / (xs[i + 1] - xs[i])
    lo, hi = values_by_pct[keys[i]], values_by_pct[keys[i + 1]]
    if isinstance(lo, dict):
        return {k: (1 - t) * lo[k] + t * hi[k] for k in lo}
    return (1 - t) * lo + t * hi


def _load_tensile(files: dict, meta: dict) -> dict:
    """pct -> deg -> {e, S, cycles, why, load_e, load_S, name}."""
    out = {}
    L = meta["tensile_gauge_length_mm"]
    for pct, by_deg in files.items():
        for deg, path in by_deg.items():
            name = os.path.basename(path)
            t = read_tensile(path)
            bad = np.flatnonzero(t["extension_mm"] <= -L)
            if bad.size:
                raise SelfshapeError(f"{name}: row {bad[0] + 1}, column extension_mm: below minus the gauge length")
            bad = np.flatnonzero(t["extension_mm"] > MAX_STRETCH_RATIO * L)
            if bad.size:
                raise SelfshapeError(f"{name}: row {bad[0] + 1}, column extension_mm: {t['extension_mm'][bad[0]]:g} mm is "
                                     f"beyond {MAX_STRETCH_RATIO:g} x the gauge length {L:g} mm")
            bad = np.flatnonzero(np.abs(t["load_N"]) > MAX_LOAD_N)
            if bad.size:
                raise SelfshapeError(f"{name}: row {bad[0] + 1}, column load_N: {t['load_N'][bad[0]]:g} N is beyond "
                                     f"+-{MAX_LOAD_N:g} N (not a fabric strip's load)")
            if not np.any(t["branch"] == "unload"):
                raise SelfshapeError(f"{name}: no unload rows (the calibration uses the unloading branch)")
            cycles, why = stabilised_cycles(t, meta, name)
            e, S = tensile_curve(t, meta, cycles)
            le, lS = tensile_curve(t, meta, cycles, "load")
            out.setdefault(pct, {})[deg] = {"e": e, "S": S, "cycles": cycles, "why": why,
                                           "load_e": le, "load_S": lS, "name": name}
    return out


def _shear_results(files: dict, meta: dict) -> dict:
    side, h = meta["shear_sample_side_mm"], meta["fabric_thickness_mm"]
    per = {}
    for deg, path in sorted(files.items(), key=lambda kv: float(kv[0])):
        t = read_shear(path)
        for col, top in (("lateral_displacement_mm", 2.0 * side), ("lateral_load_N", MAX_LOAD_N)):
            bad = np.flatnonzero(np.abs(t[col]) > top)
            if bad.size:
                raise SelfshapeError(f"{os.path.basename(path)}: row {bad[0] + 1}, column {col}: "
                                     f"{t[col][bad[0]]:g} is beyond +-{top:g} (twice the sample side, mm / N)")
        g, tau = shear_stress_strain(t["lateral_displacement_mm"], t["lateral_load_N"], side, h)
        try:
            per[deg] = {"gamma": g, "tau": tau, "fit": fit_shear_modulus(g, tau)}
        except SelfshapeError as e:
            raise SelfshapeError(f"{os.path.basename(path)}: {e}") from None
    res = {"per": per}
    for key in ("odd_cubic", "linear"):
        vals = [p["fit"][key]["slope"] for p in per.values()]
        ses = [p["fit"][key]["se"] for p in per.values()]
        res[key] = _mean_with_se(vals, ses)
        if "0" in per and "90" in per:
            f0, f9 = per["0"]["fit"][key], per["90"]["fit"][key]
            res[key + "_diff"] = (f0["slope"] - f9["slope"], float(np.hypot(f0["se"], f9["se"])))
    return res


def _cantilever_results(path: str) -> dict:
    t = read_cantilever(path)
    name = os.path.basename(path)
    groups = {}
    for o, f in sorted({(float(o), str(f)) for o, f in zip(t["orientation_deg"], t["face_up"])}):
        m = (t["orientation_deg"] == o) & (t["face_up"] == f)
        key = f"{number_key(o)}/{f}"
        if np.sum(m) < 2:
            raise SelfshapeError(f"{name}: {key} has one free length; need >= 2 to fit k_B with an error")
        try:
            fit = elastica.fit_bending_stiffness(t["free_length_mm"][m], t["areal_weight_N_per_mm2"][m],
                                                 t["height_over_width"][m])
        except SelfshapeError as e:
            raise SelfshapeError(f"{name}: rows of {key}: {e}") from None
        fit["L"], fit["w"], fit["h"] = t["free_length_mm"][m], t["areal_weight_N_per_mm2"][m], t["height_over_width"][m]
        groups[key] = fit
    return groups


def _model_params(by_pct_fits: dict, a3: float, nu: float) -> dict:
    f1, f2 = by_pct_fits["0"], by_pct_fits["90"]
    a1, a2 = stiffness_from_uniaxial(f1["A"], f2["A"], nu)
    return {"a1": a1, "a2": a2, "a3": a3, "b1": f1["b"], "b2": f2["b"], "g1": f1["g"], "g2": f2["g"]}


def _validation(curves: dict, params: dict, nu: float) -> dict:
    out = {}
    for deg, c in sorted(curves.items(), key=lambda kv: float(kv[0])):
        pred, _ = uniaxial_response(c["e"], float(deg), params, nu)
        ok = np.isfinite(pred)
        if not ok.any():
            out[deg] = {"rel_rms": None, "release_rel_error": None}
            continue
        err = pred[ok] - c["S"][ok]
        k = int(np.argmax(c["e"]))
        rel_rel = (pred[k] - c["S"][k]) / c["S"][k] if np.isfinite(pred[k]) and c["S"][k] != 0 else float("nan")
        out[deg] = {"rel_rms": float(np.sqrt(np.mean(err ** 2)) / np.sqrt(np.mean(c["S"][ok] ** 2))),
                    "release_rel_error": float(rel_rel) if math.isfinite(rel_rel) else None,
                    "fraction_predicted": float(ok.mean())}
    return out


def _plots(out_dir, tensile, fits, params_by_pct, nu, shear, cant) -> list:
    paths = []
    degs = sorted({d for by in tensile.values() for d in by}, key=float)
    for deg in degs:
        pts, lines = [], []
        for pct in sorted(tensile, key=float):
            c = tensile[pct].get(deg)
            if c is None:
                continue
            pts.append(Series(c["load_e"], c["load_S"], f"{pct} %: loading", style=".", alpha=0.25))
            pts.append(Series(c["e"], c["S"], f"{pct} %: unloading (cycles {c['cycles']})", style=".", alpha=0.6))
            eg = np.linspace(0.0, c["e"].max(), 200)
            f = fits[pct][deg]
            lines.append(Series(eg, barrier_curve(eg, f["A"], f["b"], f["g"]), f"{pct} %: Eq. 4.6 fit", style="-"))
            pred, _ = uniaxial_response(eg, float(deg), params_by_pct[pct], nu)
            lines.append(Series(eg, pred, f"{pct} %: model (uniaxial stress)", style="--"))
        paths.append(plot_series(os.path.join(out_dir, f"tensile_{deg}deg.png"),
                                 title=f"Tensile, {deg} deg from the course direction",
                                 xlabel="Green strain", ylabel="2nd Piola-Kirchhoff stress (MPa)",
                                 points=pts, lines=lines))
    pts, lines = [], []
    for deg, p in shear["per"].items():
        pts.append(Series(p["gamma"], p["tau"], f"{deg} deg", style="."))
        gg = np.linspace(0, p["gamma"].max(), 100)
        c = p["fit"]["odd_cubic"]["coef"]
        lines.append(Series(gg, c[0] + c[1] * gg + c[2] * gg ** 3, f"{deg} deg: c0 + a3 g + c g^3"))
        lines.append(Series(gg, c[0] + c[1] * gg, f"{deg} deg: initial slope {c[1]:.4f} MPa", style=":"))
    paths.append(plot_series(os.path.join(out_dir, "shear.png"), title="Shear test",
                             xlabel="shear strain gamma = u / side = 2 e12", ylabel="tau = F / (side h) (MPa)",
                             points=pts, lines=lines))
    g_tab, r_tab = elastica.master_curve_table()
    gmin = min(f["gamma"].min() for f in cant.values()) / 3
    gmax = max(f["gamma"].max() for f in cant.values()) * 3
    m = (g_tab >= gmin) & (g_tab <= gmax)
    pts = [Series(f["gamma"], f["h"], f"{k}: k_B = {f['k_b']:.4g} N mm") for k, f in cant.items()]
    paths.append(plot_series(os.path.join(out_dir, "master_curve.png"), title="Cantilever: heavy-elastica master curve",
                             xlabel="Gamma = w L^3 / k_B", ylabel="height / width", points=pts,
                             lines=[Series(g_tab[m], r_tab[m], "master curve")], logx=True, logy=True))
    return paths


def calibrate_fabric(folder: str, out_dir: str, plots: bool = True) -> dict:
    """Fit the fabric model on a test folder (meta.json, tensile_*, shear_*, cantilever.csv).

    Writes out_dir/parameters.json (every parameter as [value, standard error]; mm, N, MPa)
    and PNG plots (unless ``plots`` is False: studies and tests that only need the numbers);
    returns the same dict. Bad input, and tests that do not determine the parameters the
    engine uses (the 0 and 90 deg curves at the largest stretch), raise SelfshapeError before
    anything is written. Sets left undetermined at lower stretches, and the seed's route where
    it defines no parameters, are left out and named under ``not_identifiable``.
    """
    if not os.path.isdir(folder):
        raise SelfshapeError(f"{folder}: not a directory (expected a fabric test folder)")
    meta = read_meta(folder)
    nu = meta["poisson"]
    files = find_test_files(folder)
    refuse_overwrite(out_dir, [folder, os.path.join(folder, "meta.json"), files["cantilever"]]
                     + list(files["shear"].values()) + [p for by in files["tensile"].values() for p in by.values()])
    outs = OutputDir(out_dir, FABRIC_OUTPUTS, patterns=FABRIC_PLOTS).begin()   # checked, stale removed, first
    tensile = _load_tensile(files["tensile"], meta)
    shear = _shear_results(files["shear"], meta)
    cant = _cantilever_results(files["cantilever"])
    a3, a3_se = shear["odd_cubic"]
    if not a3 > 0:
        raise SelfshapeError(f"{', '.join(os.path.basename(p) for p in files['shear'].values())}: initial shear slope "
                             f"a3 = {a3:.4g} MPa is not positive (the law needs a3 > 0)")

    fits, ortho_by, seed_by, params_by, seed_params_by = {}, {}, {}, {}, {}
    release, release_by, validation, seed_validation, rms, rms_model = {}, {}, {}, {}, {}, {}
    not_identifiable = {}
    top_params = None
    # the largest max stretch first: its test reaches nearest the barrier and defines the
    # engine's parameters; lower stretches start from it (far below the barrier, the seed's
    # three-parameter curve alone does not pin A, b and g down: see fit_barrier_curve)
    for pct in sorted(tensile, key=float, reverse=True):
        fits[pct] = {}
        for deg, c in tensile[pct].items():
            try:
                fits[pct][deg] = fit_barrier_curve(c["e"], c["S"])
            except SelfshapeError as e:
                raise SelfshapeError(f"{c['name']}: unloading branch of cycles {c['cycles']}: {e}") from None
        f1, f2 = fits[pct]["0"], fits[pct]["90"]
        # the seed's route: Eq. 4.6-4.7 with e22 = -nu e11, then the small system for a1, a2
        why = None
        if not (f1["barrier_found"] and f2["barrier_found"]):
            why = "the barrier is not seen (b or g on its search bound: the test stays far below it)"
        else:
            try:
                (a1, a2), (se_a1, se_a2) = stiffness_with_se(f1["A"], f1["se"][0], f2["A"], f2["se"][0], nu)
            except SelfshapeError as e:
                why = str(e)
        if why is not None:
            not_identifiable[f"orthotropic_seed_eq46_by_stretch.{pct}"] = (
                f"the seed's route (Eq. 4.6-4.7 on 0 and 90 deg) at {pct} %: {why}")
        else:
            seed_by[pct] = {"a1": _pair(a1, se_a1), "a2": _pair(a2, se_a2), "a3": _pair(a3, a3_se),
                            "b1": _pair(f1["b"], f1["se"][1]), "b2": _pair(f2["b"], f2["se"][1]),
                            "g1": _pair(f1["g"], f1["se"][2]), "g2": _pair(f2["g"], f2["se"][2])}
            seed_params_by[pct] = _model_params(fits[pct], a3, nu)
        # model-consistent refinement: the engine's own uniaxial response fits 0 and 90 deg
        c0, c9 = tensile[pct]["0"], tensile[pct]["90"]
        # starts: the Eq. 4.6 fits (always at the largest stretch; below it only where the seed's
        # route is determined) and the largest stretch's parameters; the better fit is kept
        starts = ([None] if (pct in seed_params_by or top_params is None) else []) + \
                 ([top_params] if top_params is not None else [])
        cons = None
        for st in starts:
            trial = fit_orthotropic_uniaxial(c0["e"], c0["S"], c9["e"], c9["S"], nu, a3, start=st)
            if cons is None or trial["rms"] < cons["rms"]:
                cons = trial
        if cons["at_bound"]:
            msg = (f"{', '.join(cons['at_bound'])} on the search bound: the 0 and 90 deg curves at {pct} % "
                   f"({c0['name']}, {c9['name']}) do not determine them")
            if top_params is None:
                raise SelfshapeError(msg)
            not_identifiable[f"orthotropic_by_stretch.{pct}"] = msg + " (left out of orthotropic_by_stretch)"
        if top_params is None:
            top_params = cons["params"]
        params_by[pct] = cons["params"]
        ortho_by[pct] = {k: (_pair(a3, a3_se) if k == "a3" else _pair(cons["params"][k], cons["se"][k], k))
                         for k in PARAM_NAMES}
        rms_model[pct] = cons["rms"]
        tangents = {deg: release_tangent(f) for deg, f in sorted(fits[pct].items(), key=lambda kv: float(kv[0]))}
        release_by[pct] = {deg: _pair(*v) for deg, v in tangents.items()}
        release[pct] = _pair(*_mean_with_se([v[0] for v in tangents.values()], [v[1] for v in tangents.values()]))
        validation[pct] = _validation(tensile[pct], params_by[pct], nu)
        if pct in seed_params_by:
            seed_validation[pct] = _validation(tensile[pct], seed_params_by[pct], nu)
        rms[pct] = {deg: f["rms"] for deg, f in fits[pct].items()}
    for key in not_identifiable:
        if key.startswith("orthotropic_by_stretch."):
            ortho_by.pop(key.split(".", 1)[1], None)
    order = sorted(tensile, key=float)
    ortho_by, seed_by, release, release_by, validation, seed_validation, rms, rms_model = (
        {p: d[p] for p in order if p in d}
        for d in (ortho_by, seed_by, release, release_by, validation, seed_validation, rms, rms_model))
    top = max(tensile, key=float)
    kb = {k: _pair(f["k_b"], f["se"]) for k, f in cant.items()}
    kb_mean = _pair(*_mean_with_se([f["k_b"] for f in cant.values()], [f["se"] for f in cant.values()]))

    result = {
        "units": {"a1 a2 a3 b1 b2": "MPa", "g1 g2": "Green strain", "release_modulus_mpa": "MPa",
                  "bending_stiffness_nmm": "N mm (moment per unit width per unit curvature)"},
        "orthotropic": ortho_by[top],
        "orthotropic_max_stretch_pct": float(top),
        "orthotropic_by_stretch": ortho_by,
        "orthotropic_seed_eq46": seed_by.get(top),
        "not_identifiable": not_identifiable,
        "orthotropic_seed_eq46_by_stretch": seed_by,
        "release_modulus_mpa": release,
        "release_modulus_by_orientation_mpa": release_by,
        "bending_stiffness_nmm": kb,
        "bending_stiffness_mean_nmm": kb_mean,
        "poisson": [nu, 0.0],
        "shear": {
            "a3_by_orientation_mpa": {d: _pair(p["fit"]["odd_cubic"]["slope"], p["fit"]["odd_cubic"]["se"])
                                      for d, p in shear["per"].items()},
            "a3_0_minus_90_mpa": _pair(*shear["odd_cubic_diff"]) if "odd_cubic_diff" in shear else None,
            "seed_straight_line_mpa": _pair(*shear["linear"]),
            "seed_straight_line_by_orientation_mpa": {d: _pair(p["fit"]["linear"]["slope"], p["fit"]["linear"]["se"])
                                                      for d, p in shear["per"].items()},
            "seed_straight_line_0_minus_90_mpa": _pair(*shear["linear_diff"]) if "linear_diff" in shear else None,
        },
        "fit_quality": {
            "tensile_eq46_rms_mpa": rms,
            "tensile_model_rms_mpa": rms_model,
            "validation": validation,
            "validation_seed_eq46": seed_validation,
            "shear_rms_mpa": {d: p["fit"]["odd_cubic"]["rms"] for d, p in shear["per"].items()},
            "cantilever_rms_log": {k: f["rms_log"] for k, f in cant.items()},
        },
        "cycles_used": {c["name"]: {"cycles": c["cycles"], "why": c["why"]}
                        for by in tensile.values() for c in by.values()},
        "method": {
            "tensile": "unloading branch of the stabilised cycles, Eq. 4.4 (Green strain, 2nd PK stress). "
                       "orthotropic: a1, a2, b1, b2, g1, g2 fitted so that the model's own uniaxial-stress response "
                       "(lateral stress zero) matches the 0 and 90 deg curves, started from the seed's route. "
                       "orthotropic_seed_eq46: the seed's route, sigma = A e - b log(1 - e/g) on 0 deg (A1, b1, g1) and "
                       "90 deg (A2, b2, g2), a1, a2 from A1, A2 with e22 = -nu e11 (Eq. 4.6-4.7)",
            "validation": "every orientation's unloading curve against the model in uniaxial stress (strain rotated "
                          "into the course frame, transverse strain and shear solved); rel_rms = RMS error / RMS stress",
            "release_modulus": "slope of each orientation's fitted unloading curve at its largest strain, "
                               "mean over orientations; SE = sqrt(sum SE_i^2) / n",
            "shear": "gamma = u/side = 2 e12, tau = F/(side h); a3 = initial slope of tau = c0 + a3 gamma + c gamma^3, "
                     "mean of the orientations",
            "bending": "least squares in log(height/width) against the heavy-elastica master curve, Gamma = w L^3 / k_B",
            "poisson": "from meta.json 'poisson' if given, else the seed's 0.3 (not measured here; SE 0)",
            "interpolation": "parameters at other max stretches: linear in the percent between measured ones "
                             "(validation.fabric.interpolate_by_stretch)",
        },
        "meta": {k: meta[k] for k in META_KEYS},
    }
    if result["orthotropic_seed_eq46"] is None:
        del result["orthotropic_seed_eq46"]
    result = finite_json(result)
    with outs:                  # atomic (validation.plots.save_figure), parameters.json last
        result["plots"] = ([os.path.basename(p) for p in _plots(outs.makedirs(), tensile, fits, params_by, nu, shear,
                                                                  cant)] if plots else [])
        outs.write_json("parameters.json", result, indent=1)
    return result


def model_parameters(parameters: dict, stretch_pct: float | None = None) -> dict:
    """Plain {a1..g2} floats from a parameters.json dict, at the largest measured stretch or
    linearly interpolated at stretch_pct (seed rule, clamped outside the measured range)."""
    if stretch_pct is None:
        return {k: parameters["orthotropic"][k][0] for k in PARAM_NAMES}
    by = {p: {k: v[k][0] for k in PARAM_NAMES} for p, v in parameters["orthotropic_by_stretch"].items()}
    return interpolate_by_stretch(by, stretch_pct)
