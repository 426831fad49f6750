"""The closed validation loop on bilayer-strip measurements.

1. fit the base model (project's bilayer model, plastic flat at rest; one
   parameter, the modulus ratio);
2. test its residuals against every recorded covariate (permutation F tests,
   Holm-Bonferroni, family-wise false-positive rate 5 %);
3. while structure remains, try every applicable catalogue effect
   (validation.effects) and rank them by K-fold cross-validated squared error;
   add the best one only if it pays: its paired CV gain exceeds Z_GAIN standard
   errors and GAIN_NOISE_FRACTION of the noise variance;
4. report (report.json, plots, model.json). The errors before/after are relative
   RMS on held-out rows of an outer K-fold split; each outer training part runs
   the whole selection on its own, so held-out rows never take part in it.

Units: curvatures 1/mm, thicknesses mm.
"""
from __future__ import annotations

import csv
import json
import os

import numpy as np

from shellfem.errors import SelfshapeError
from shellfem.outfiles import OutputDir, check_finite_arrays, check_output_file, write_atomic
from validation import effects as fx
from validation import stats
from validation.strips import MEASURED, REST, model_source, n_rows, read_strips, strip_model, subset

Z_GAIN = 2.0                # paired CV gain must exceed this many standard errors
GAIN_NOISE_FRACTION = 0.05  # ... and this fraction of the noise variance
ALPHA = 0.05                # family-wise false-positive rate of the residual tests
N_PERM = 999
COVARIATES = ("side", "stretch", "orientation_deg", "plastic_thickness_mm", "fabric_thickness_mm",
              "width_mm", "length_mm", REST)
DESIGN = ("side", "stretch", "orientation_deg", "plastic_thickness_mm", "fabric_thickness_mm",
          "width_mm", "length_mm")
FORMAT = "selfshape-strip-model/1"
#: The files `selfshape validate` writes (an earlier run's are removed first; report.json last).
VALIDATE_OUTPUTS = ("residuals_before.png", "residuals_after.png", "model.json", "report.json")


# ---------------------------------------------------------------------------
# fitting


def _scan_modulus_ratio(rows, y):
    """Best modulus ratio of the base model on a log grid (vectorised)."""
    grid = np.exp(np.linspace(np.log(3.0), np.log(3e6), 61))[:, None]
    k = strip_model(rows["plastic_thickness_mm"][None], rows["fabric_thickness_mm"][None],
                    rows["stretch"][None], grid)
    return float(grid[np.argmin(((k - y[None]) ** 2).sum(1)), 0])


def fit(rows, effects, start=None, aux=None):
    """Least-squares fit of base + ``effects`` to the measured curvatures of rows.
    ``start``: natural parameter values to start from (default: grid-scanned
    modulus ratio and the effects' initial values). Returns a dict: effects
    (names), names, theta, se (natural units, delta method for log parameters),
    aux, ssr, sigma, n, residuals (measured - predicted)."""
    effects = list(effects)
    aux = {e.name: e.prepare(rows) for e in effects} if aux is None else aux
    y = rows[MEASURED]
    if start is None:
        start = [_scan_modulus_ratio(rows, y)] + [v for e in effects for v in e.init]
    u0, flags = fx.to_internal(effects, start)
    lo, hi = fx.bounds_internal(effects)
    fun = lambda u: fx.predict(rows, effects, fx.natural(effects, u), aux) - y  # noqa: E731
    r = stats.nls_fit(fun, u0, lo, hi, batch_fn=fun)
    theta = fx.natural(effects, r["theta"])
    se = np.where(flags, theta * r["se"], r["se"])
    return {"effects": [e.name for e in effects], "names": fx.parameter_names(effects),
            "theta": theta, "se": se, "aux": aux, "ssr": r["ssr"], "sigma": r["sigma"],
            "n": r["n"], "residuals": -r["residuals"]}


def _effects_of(names):
    return [fx.BY_NAME[n] for n in names]


def _theta_without(f, name):
    """Natural parameters of fit f with effect ``name``'s parameters left out."""
    keep = [i for i, q in enumerate(f["names"]) if not q.startswith(name + ".")]
    return [f["theta"][i] for i in keep]


def predict_fit(rows, f):
    return fx.predict(rows, _effects_of(f["effects"]), f["theta"], f["aux"])


def cv_errors(rows, effects, folds, start=None):
    """Out-of-fold errors (predicted - measured) per row for base + effects."""
    err = np.empty(n_rows(rows))
    for tr, te in folds:
        f = fit(subset(rows, tr), effects, start=start)
        t = subset(rows, te)
        err[te] = fx.predict(t, effects, f["theta"], f["aux"]) - t[MEASURED]
    return err


# ---------------------------------------------------------------------------
# residual analysis


def covariate_table(rows, fitted=None):
    """{name: values} of the covariates the residual tests look at."""
    out = {}
    for c in COVARIATES:
        out[c] = (rows[c] == "back").astype(float) if c == "side" else np.asarray(rows[c], float)
    if fitted is not None:
        out["predicted_curvature"] = np.asarray(fitted, float)
    return out


def residual_analysis(rows, residuals, fitted, seed=0):
    """Permutation F tests of residuals against each covariate, the fitted value
    and the replicate groups (lack of fit), Holm-adjusted at ALPHA."""
    cov = covariate_table(rows, fitted)
    g = replicate_groups(rows)
    within = None
    if np.unique(g).size < n_rows(rows):
        cov["replicate_groups"] = g.astype(float)
        rest = rows[REST]
        m = np.isfinite(rest)
        if m.sum() > np.unique(g[m]).size + 2:  # the rest curvature varies inside replicate groups
            within = (g, {REST: rest})
    return stats.residual_tests(residuals, cov, alpha=ALPHA, n_perm=N_PERM, seed=seed, within=within)


def replicate_groups(rows):
    """Integer label per row: rows sharing every design covariate are replicates."""
    keys = np.array(["|".join(str(rows[c][i]) for c in DESIGN) for i in range(n_rows(rows))])
    return np.unique(keys, return_inverse=True)[1]


def noise_estimate(rows, residuals, fallback_rms):
    """Noise standard deviation of the measured curvature: pooled scatter of a
    model's residuals within replicate groups (rows sharing every design covariate;
    residuals rather than raw values so that per-row covariates the model uses,
    such as a measured rest curvature, do not count as noise) when replicates give
    >= 5 degrees of freedom, else ``fallback_rms``."""
    r = stats.noise_level(residuals, replicate_groups(rows))
    if r is None:
        return {"sigma": float(fallback_rms), "dof": None, "method": "CV RMS of the base model (no replicates)"}
    r["method"] = "pooled within-replicate-group scatter of the residuals"
    return r


# ---------------------------------------------------------------------------
# selection


def select_effects(rows, seed=0, folds=5, candidates=fx.CATALOGUE):
    """Greedy forward selection of catalogue effects on ``rows`` (see module doc).
    Returns dict: fit (final), added, rejected {name: reason}, steps, indistinguishable,
    noise, tests_before, tests_after, cv_rms_before, cv_rms_after."""
    n = n_rows(rows)
    split = stats.kfold(n, folds, seed, groups=rows["specimen"])
    y = rows[MEASURED]
    cur = fit(rows, [])
    err_cur = cv_errors(rows, [], split, start=cur["theta"])
    fallback = float(np.sqrt(np.mean(err_cur ** 2)))
    noise = noise_estimate(rows, cur["residuals"], fallback)
    sig2 = noise["sigma"] ** 2
    rejected, pool = {}, []
    for e in candidates:
        ok, why = e.applicable(rows)
        (pool.append(e) if ok else rejected.__setitem__(e.name, why))
    added, steps, confounded, history = [], [], [], {}
    tests_before = tests = residual_analysis(rows, cur["residuals"], y - cur["residuals"], seed)
    while pool:
        sig = [t["name"] for t in tests if t.get("significant")]
        if not sig:
            for e in pool:
                rejected[e.name] = (history.get(e.name, "") + f"no residual structure left against any covariate "
                                    f"(permutation F tests, Holm, alpha {ALPHA})")
            break
        trials = []
        for e in pool:
            eff = _effects_of(added) + [e]
            start = list(cur["theta"]) + list(e.init)
            f = fit(rows, eff, start=start)
            if (cur["ssr"] - f["ssr"]) / n <= GAIN_NOISE_FRACTION * sig2:
                # the in-sample gain bounds the CV gain: it cannot pay, skip the CV
                trials.append({"effect": e, "fit": f, "err": err_cur, "gain": (cur["ssr"] - f["ssr"]) / n,
                               "se": None, "cv_rms": None, "in_sample_only": True})
                continue
            err = cv_errors(rows, eff, split, start=f["theta"])
            gain, se = stats.paired_gain(err_cur, err)
            trials.append({"effect": e, "fit": f, "err": err, "gain": gain, "se": se,
                           "cv_rms": float(np.sqrt(np.mean(err ** 2)))})
        trials.sort(key=lambda t: (bool(t.get("in_sample_only")), -t["gain"]))
        for t in trials:
            t["pays"] = bool(not t.get("in_sample_only") and t["gain"] > Z_GAIN * t["se"]
                             and t["gain"] > GAIN_NOISE_FRACTION * sig2)
        paying = [t for t in trials if t["pays"]]
        best = paying[0] if paying else trials[0]
        if best is not trials[0]:  # the best-paying effect leads; the others compare with it
            trials.remove(best)
            trials.insert(0, best)
        if best["pays"]:
            pb = predict_fit(rows, best["fit"])
            for t in trials[1:]:
                if t["pays"]:
                    d, dse = stats.paired_gain(t["err"], best["err"])
                    diff = float(np.sqrt(np.mean((predict_fit(rows, t["fit"]) - pb) ** 2)))
                    t["vs_best"] = {"cv_gain_difference": d, "cv_gain_difference_se": dse,
                                    "prediction_rms_difference_per_mm": diff}
                    t["confounded"] = bool(abs(d) <= Z_GAIN * dse and diff <= noise["sigma"])
        steps.append({"structure_in": sig, "cv_rms_current": float(np.sqrt(np.mean(err_cur ** 2))),
                      "aicc_current": stats.information_criteria(cur["ssr"], n, len(cur["theta"]))["aicc"],
                      "candidates": [{"effect": t["effect"].name, "cv_rms": t["cv_rms"], "gain": t["gain"],
                                      "aicc": stats.information_criteria(t["fit"]["ssr"], n,
                                                                         len(t["fit"]["theta"]))["aicc"],
                                      "gain_se": t["se"], "pays": t["pays"],
                                      "scored_by": "in-sample (cannot pay)" if t.get("in_sample_only") else "CV",
                                      **t.get("vs_best", {})}
                                     for t in trials]})
        if not best["pays"]:
            for t in trials:
                rejected[t["effect"].name] = (
                    f"does not pay: in-sample squared-error gain {t['gain']:.3g} (1/mm)^2 is below "
                    f"{GAIN_NOISE_FRACTION:g} x noise variance {sig2:.3g}" if t.get("in_sample_only") else
                    f"does not pay: CV squared-error gain {t['gain']:.3g} +- {t['se']:.3g} (1/mm)^2 "
                    f"needs > {Z_GAIN:g} SE and > {GAIN_NOISE_FRACTION:g} x noise variance {sig2:.3g}")
            break
        for t in trials[1:]:
            if t.get("confounded"):
                confounded.append({"effects": [best["effect"].name, t["effect"].name],
                                   "cv_rms": [best["cv_rms"], t["cv_rms"]], **t["vs_best"],
                                   "noise_sigma_per_mm": noise["sigma"]})
                rejected[t["effect"].name] = (f"indistinguishable from {best['effect'].name} "
                                              f"(CV errors and predictions agree within the noise); "
                                              f"{best['effect'].name} was added")
        for t in trials[1:]:
            if t["effect"].name not in rejected:
                how = (f"CV RMS {t['cv_rms']:.3g} vs {best['cv_rms']:.3g} 1/mm" if t["cv_rms"] is not None
                       else "its in-sample gain was below the noise threshold")
                history[t["effect"].name] = (f"at step {len(steps)} {best['effect'].name} was added instead "
                                             f"({how}); then ")
        added.append(best["effect"].name)
        pool = [e for e in pool if e.name != best["effect"].name and e.name not in rejected]
        cur, err_cur = best["fit"], best["err"]
        if noise["dof"] is not None:
            noise = noise_estimate(rows, cur["residuals"], fallback)
            sig2 = noise["sigma"] ** 2
        tests = residual_analysis(rows, cur["residuals"], y - cur["residuals"], seed)
    removed = []
    while len(added) > 1:  # backward pass: drop an effect the others made redundant
        worst = None
        for name in added:
            keep = [a for a in added if a != name]
            f = fit(rows, _effects_of(keep), start=_theta_without(cur, name))
            err = cv_errors(rows, _effects_of(keep), split, start=f["theta"])
            loss, se = stats.paired_gain(err, err_cur)
            if not (loss > Z_GAIN * se and loss > GAIN_NOISE_FRACTION * sig2):
                if worst is None or loss < worst[1]:
                    worst = (name, loss, se, f, err)
        if worst is None:
            break
        name, loss, se, f, err = worst
        added.remove(name)
        removed.append(name)
        rejected[name] = (f"added, then removed in the backward pass: without it the CV squared error rises "
                          f"only {loss:.3g} +- {se:.3g} (1/mm)^2, the other effects explain it")
        cur, err_cur = f, err
    if removed:
        tests = residual_analysis(rows, cur["residuals"], y - cur["residuals"], seed)
        if noise["dof"] is not None:
            noise = noise_estimate(rows, cur["residuals"], fallback)
    return {"fit": cur, "added": added, "rejected": rejected, "steps": steps, "removed": removed,
            "indistinguishable": confounded, "noise": noise, "tests_before": tests_before,
            "tests_after": tests, "cv_rms_after": float(np.sqrt(np.mean(err_cur ** 2)))}


# ---------------------------------------------------------------------------
# the loop with honest held-out errors


def validate(rows, seed=0, outer_folds=5, inner_folds=5):
    """Run the loop on rows (from read_strips). Returns the report dict plus
    ``_final`` (the selection on all rows) and ``_heldout`` (out-of-fold
    predictions before/after) for writing model.json and plots."""
    n = n_rows(rows)
    if n < 2 * outer_folds:
        raise SelfshapeError(f"{rows.get('_file', 'data')}: {n} rows, validation needs at least "
                             f"{2 * outer_folds}")
    y = rows[MEASURED]
    before, after = np.empty(n), np.empty(n)
    per_fold = []
    for j, (tr, te) in enumerate(stats.kfold(n, outer_folds, seed, groups=rows["specimen"])):
        train, test = subset(rows, tr), subset(rows, te)
        base = fit(train, [])
        before[te] = predict_fit(test, base)
        sel = select_effects(train, seed=seed + 1 + j, folds=inner_folds)
        after[te] = predict_fit(test, sel["fit"])
        per_fold.append(sel["added"])
    final = select_effects(rows, seed=seed, folds=inner_folds)
    f = final["fit"]
    noise = final["noise"]
    rms_y = float(np.sqrt(np.mean(y ** 2)))
    report = {
        "data": rows.get("_file"), "n_rows": n, "model": model_source(), "seed": seed,
        "error_definition": "relative RMS on held-out rows: RMS(predicted - measured) / RMS(measured), "
                            f"outer {outer_folds}-fold split grouped by specimen; selection nested inside "
                            "each outer training part",
        "error_before": stats.rel_rms(before, y),
        "error_after": stats.rel_rms(after, y),
        "noise_relative": noise["sigma"] / rms_y,
        "noise": noise,
        "effects_added": list(final["added"]),
        "effects_rejected": [{"name": k, "reason": v} for k, v in final["rejected"].items()],
        "parameters": _parameters(f),
        "indistinguishable": final["indistinguishable"],
        "residual_tests_before": final["tests_before"],
        "residual_tests_after": final["tests_after"],
        "selection_steps": final["steps"],
        "effects_added_per_outer_fold": per_fold,
        "selection_rule": f"greedy forward; add the best effect while its paired {inner_folds}-fold CV "
                          f"squared-error gain > {Z_GAIN:g} SE and > {GAIN_NOISE_FRACTION:g} x noise variance, "
                          f"and only while residual tests (Holm, alpha {ALPHA}) find structure",
        "fit_rms_per_mm": float(np.sqrt(f["ssr"] / n)),
    }
    report["_final"] = final
    report["_heldout"] = {"before": before, "after": after}
    return report


def _parameters(f):
    """name: [value, standard error] of a fit, including laws effects fitted to
    auxiliary columns (e.g. the smoothed measured rest curvature)."""
    out = {nm: [float(v), float(s)] for nm, v, s in zip(f["names"], f["theta"], f["se"])}
    for name in f["effects"]:
        for q, vs in f["aux"].get(name, {}).get("parameters", {}).items():
            out[f"{name}.{q}"] = [float(vs[0]), float(vs[1])]
    return out


def model_dict(f) -> dict:
    """Everything predict needs, JSON-ready."""
    return {"format": FORMAT, "model": model_source(), "mode": "narrow",
            "measured_column": MEASURED,
            "effects": [{"name": nm, "parameters": {q: float(v) for q, v in zip(f["names"], f["theta"])
                                                    if q.startswith(nm + ".")}} for nm in f["effects"]],
            "parameter_names": list(f["names"]),
            "theta": [float(v) for v in f["theta"]],
            "standard_errors": [float(v) for v in f["se"]],
            "aux": f["aux"],
            "reference_stretch": fx.REFERENCE_STRETCH,
            "reference_thickness_mm": fx.REFERENCE_THICKNESS}


def _public(report):
    return _finite({k: v for k, v in report.items() if not k.startswith("_")})


def _finite(o):
    """JSON-safe copy: numpy to Python, NaN/inf to None."""
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    if isinstance(o, np.ndarray):
        return _finite(o.tolist())
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not np.isfinite(o):
        return None
    return o


def validate_file(csv_path, out_dir, seed=0) -> dict:
    """Run :func:`validate` on a strips CSV; write report.json, model.json and
    residual plots (residuals_before.png, residuals_after.png) to out_dir."""
    rows = read_strips(csv_path)
    outs = OutputDir(out_dir, VALIDATE_OUTPUTS, inputs=[csv_path]).begin()   # checked, stale removed, first
    rep = validate(rows, seed=seed)
    with outs:                  # atomic, every number finite, report.json last
        _plot_residuals(rows, rep, outs.makedirs())
        outs.write_json("model.json", model_dict(rep["_final"]["fit"]))
        outs.write_json("report.json", _public(rep))
    return _public(rep)


def _plot_residuals(rows, rep, out_dir):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    y = rows[MEASURED]
    cov = covariate_table(rows)
    names = [c for c in cov if np.unique(cov[c][np.isfinite(cov[c])]).size > 1] or ["plastic_thickness_mm"]
    for tag in ("before", "after"):
        r = y - rep["_heldout"][tag]
        fig, axs = plt.subplots(1, len(names), figsize=(3.2 * len(names), 3.0), squeeze=False)
        for ax, c in zip(axs[0], names):
            ax.axhline(0, color="0.6", lw=0.8)
            ax.plot(cov[c], r, ".", ms=4)
            ax.set_xlabel(c if c != "side" else "side (0 front, 1 back)")
        axs[0][0].set_ylabel("held-out residual (1/mm)")
        fig.suptitle(f"{rep['data']}: residuals {tag} "
                     f"(rel. RMS {rep['error_' + tag]:.3f})", fontsize=9)
        fig.tight_layout()
        write_atomic(os.path.join(out_dir, f"residuals_{tag}.png"), lambda tmp: fig.savefig(tmp, dpi=110))
        plt.close(fig)


# ---------------------------------------------------------------------------
# prediction


def load_model(path) -> dict:
    name = os.path.basename(str(path))
    try:
        with open(path) as fh:
            m = json.load(fh)
    except (OSError, json.JSONDecodeError) as e:
        raise SelfshapeError(f"{name}: cannot read model JSON: {e}") from None
    if not isinstance(m, dict) or m.get("format") != FORMAT:
        raise SelfshapeError(f"{name}: not a selfshape strip model (format {FORMAT!r} expected)")
    for e in m.get("effects", []):
        if e.get("name") not in fx.BY_NAME:
            raise SelfshapeError(f"{name}: unknown effect {e.get('name')!r}")
    eff = _effects_of([e["name"] for e in m["effects"]])
    if len(m.get("theta", [])) != len(fx.parameter_names(eff)):
        raise SelfshapeError(f"{name}: theta has {len(m.get('theta', []))} values, "
                             f"effects need {len(fx.parameter_names(eff))}")
    return m


def predict_rows(model, rows):
    """Predicted curvature (1/mm) of each row under a model dict (model.json)."""
    eff = _effects_of([e["name"] for e in model["effects"]])
    return fx.predict(rows, eff, np.asarray(model["theta"], float), model.get("aux", {}))


def predict_file(model_json, csv_path, out_csv) -> int:
    """Apply model.json to a strips CSV (the measured column may be absent); write
    every input column plus ``curvature_per_mm_predicted``. Returns the row count."""
    model = load_model(model_json)
    rows = read_strips(csv_path, require_measured=False)
    out_csv = check_output_file(out_csv, inputs=[model_json, csv_path])     # before the work
    pred = predict_rows(model, rows)
    header, body = rows["_raw"]
    col = model.get("measured_column", MEASURED) + "_predicted"
    check_finite_arrays(f"{os.path.basename(out_csv)} (from {os.path.basename(str(model_json))})", {col: pred})
    os.makedirs(os.path.dirname(os.path.abspath(out_csv)), exist_ok=True)

    def write(tmp):
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(list(header) + [col])
            for r, p in zip(body, pred):
                w.writerow(list(r) + [f"{p:.8g}"])
    write_atomic(out_csv, write)
    return len(body)
