"""Bilayer-strip data and the calibration of the plastic/fabric modulus ratio.

A strips CSV (schema: validation/data/README.md) lists plastic strips printed on
pre-stretched fabric, released and photographed from the side. This module reads
and validates such files, evaluates the project's bilayer model for them and fits
the modulus ratio E_plastic / E_fabric by nonlinear least squares on that model.

Units: mm, 1/mm for curvatures, dimensionless stretch and modulus ratio.

Model: ``shellfem.strip.strip_curvature``, the engine's layered Kirchhoff energy
(fabric with rest metric I/s^2, plastic above it with rest metric I and optional
rest curvature) minimised over uniform states of a fully printed strip.
:func:`_timoshenko_curvature` is the closed form the seed quotes after Eq. 3.17
(its Eq. 3.13 coefficient), kept for comparison.
"""
from __future__ import annotations

import os

import numpy as np

from shellfem.errors import SelfshapeError, check_number
from shellfem.outfiles import OutputDir
from validation.textfiles import finite_json, read_csv_rows, refuse_overwrite

MEASURED = "curvature_per_mm"
REST = "rest_curvature_per_mm"
#: The files `selfshape calibrate strips` writes (an earlier run's are removed first).
STRIPS_OUTPUTS = ("strips_fit.png", "parameters.json")
NUMERIC = ("stretch", "orientation_deg", "plastic_thickness_mm", "fabric_thickness_mm",
           "width_mm", "length_mm")
REQUIRED = ("specimen", "side") + NUMERIC
SIDES = ("front", "back")
#: Most data rows a strips CSV may hold: a lab measures tens to hundreds of strips; the
#: calibration evaluates the strip model at ~70 ratios per row (20 us each) and the validation
#: loop refits it per fold and effect, so 100,000 rows ran out of memory (1.9 GB) or minutes.
MAX_ROWS = 10_000
PLASTIC_POISSON = 0.5
FABRIC_POISSON = 0.3

# ---------------------------------------------------------------------------
# reading


#: physical range of each numeric column (value within [lo, hi]): a strip a lab can print,
#: a fabric it can stretch, a curvature a strip of these thicknesses can take (radius >= 0.1 mm)
RANGES = {"stretch": (1.0, 5.0), "orientation_deg": (-360.0, 360.0),
          "plastic_thickness_mm": (1e-3, 10.0), "fabric_thickness_mm": (1e-3, 10.0),
          "width_mm": (1e-2, 1e4), "length_mm": (1e-2, 1e4),
          MEASURED: (-10.0, 10.0), REST: (-10.0, 10.0)}


def _number(text, where, col):
    """The cell ``text`` of column ``col`` as a finite float within RANGES[col], else a
    SelfshapeError naming the row and the column."""
    lo, hi = RANGES[col]
    return check_number(f"{where}, column {col}:", text, lo=lo, hi=hi)


def read_strips(path, require_measured=True) -> dict:
    """Read and validate a strips CSV. Returns a dict of column arrays (n rows):
    specimen, side (str arrays), the numeric columns (float), ``curvature_per_mm``
    (NaN where absent when ``require_measured`` is False), ``rest_curvature_per_mm``
    (NaN where empty), plus ``_raw`` (header, raw rows) and ``_file``.
    Raises SelfshapeError naming file, row and column on any bad entry (values outside
    their physical RANGES included), and naming file and line for a file that is not CSV
    text (binary, not UTF-8, a field over the csv module's limit)."""
    name = os.path.basename(str(path))
    table = read_csv_rows(path, "strips CSV")
    table = [r for r in table if any(c.strip() for c in r)]
    if not table:
        raise SelfshapeError(f"{name}: empty file, expected a strips CSV header")
    header = [h.strip() for h in table[0]]
    missing = [c for c in REQUIRED if c not in header]
    if require_measured and MEASURED not in header:
        missing.append(MEASURED)
    if missing:
        raise SelfshapeError(f"{name}: missing column(s) {', '.join(missing)} in header")
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise SelfshapeError(f"{name}: duplicate column name(s) in header: {', '.join(repr(h[:40]) for h in dup[:3])}")
    body = table[1:]
    if not body:
        raise SelfshapeError(f"{name}: no data rows")
    if len(body) > MAX_ROWS:
        raise SelfshapeError(f"{name}: {len(body)} data rows, more than the {MAX_ROWS:,} a strips CSV may hold "
                             f"(a lab's strip set is tens to hundreds; the fits' time grows with the rows)")
    col = {h: i for i, h in enumerate(header)}
    n = len(body)
    out = {"specimen": np.empty(n, dtype=object), "side": np.empty(n, dtype=object)}
    for c in NUMERIC + (MEASURED, REST):
        out[c] = np.full(n, np.nan)
    for i, r in enumerate(body):
        where = f"{name}: row {i + 1}"
        if len(r) != len(header):
            raise SelfshapeError(f"{where}: {len(r)} fields, header has {len(header)}")
        get = lambda c: r[col[c]].strip()  # noqa: E731
        spec = get("specimen")
        if not spec:
            raise SelfshapeError(f"{where}, column specimen: empty")
        where = f"{name}: row {i + 1} (specimen {spec if len(spec) <= 40 else spec[:37] + '...'})"
        side = get("side").lower()
        if side not in SIDES:
            raise SelfshapeError(f"{where}, column side: must be front or back, got {get('side')!r}")
        out["specimen"][i], out["side"][i] = spec, side
        for c in NUMERIC:
            out[c][i] = _number(get(c), where, c)
        if MEASURED in col:
            t = get(MEASURED)
            if t or require_measured:
                if not t:
                    raise SelfshapeError(f"{where}, column {MEASURED}: empty")
                out[MEASURED][i] = _number(t, where, MEASURED)
        if REST in col and get(REST):
            out[REST][i] = _number(get(REST), where, REST)
    out["_raw"] = (header, body)
    out["_file"] = name
    return out


def n_rows(rows) -> int:
    return len(rows["specimen"])


def subset(rows, idx) -> dict:
    """Rows ``idx`` (index array or boolean mask) of a rows dict."""
    out = {k: (v[idx] if isinstance(v, np.ndarray) else v) for k, v in rows.items() if k != "_raw"}
    return out


# ---------------------------------------------------------------------------
# the bilayer model

def _timoshenko_curvature(plastic_thickness, fabric_thickness, misfit, modulus_ratio):
    """Timoshenko's bimetal curvature (seed after Eq. 3.17, written as Eq. 3.13):
    kappa = 6 E1 E2 h1 h2 (h1 + h2) eps / (E1^2 h1^4 + 2 E1 E2 h1 h2 (2h1^2 + 3h1h2 + 2h2^2)
    + E2^2 h2^4), with 1 = plastic, 2 = fabric, eps the misfit strain (1/mm out)."""
    h1, h2, n = (np.asarray(v, float) for v in (plastic_thickness, fabric_thickness, modulus_ratio))
    den = n * n * h1 ** 4 + 2 * n * h1 * h2 * (2 * h1 ** 2 + 3 * h1 * h2 + 2 * h2 ** 2) + h2 ** 4
    return 6 * n * h1 * h2 * (h1 + h2) * np.asarray(misfit, float) / den


def model_source() -> str:
    """The implementation :func:`strip_model` uses."""
    return "shellfem.strip.strip_curvature"


def strip_model(plastic_thickness, fabric_thickness, stretch, modulus_ratio, *,
                rest_curvature=0.0, mode="narrow"):
    """Curvature (1/mm, > 0 concave on the fabric side) of a fully printed bilayer
    strip: the project's model, shellfem.strip. Thicknesses in mm; arrays broadcast."""
    from shellfem.strip import strip_curvature
    return np.asarray(strip_curvature(plastic_thickness, fabric_thickness, stretch, modulus_ratio,
                                      plastic_poisson=PLASTIC_POISSON, fabric_poisson=FABRIC_POISSON,
                                      rest_curvature=rest_curvature, mode=mode), float)


# ---------------------------------------------------------------------------
# calibration

RATIO_RANGE = (1.0, 1e7)


def specimen_count(rows) -> int:
    """Distinct specimens: rows of one specimen are repeated measurements of it, not
    independent strips, so they count once towards the residual degrees of freedom."""
    if "specimen" not in rows:   # a rows dict built in code: every row its own strip
        return int(np.asarray(rows[MEASURED]).size)
    return int(np.unique(np.asarray(rows["specimen"]).astype(str)).size)


def fit_modulus_ratio(rows, rest_curvature=0.0, what="modulus_ratio"):
    """Least-squares modulus ratio of the base model (narrow strip, plastic rest
    curvature ``rest_curvature``) to the measured curvatures. Returns dict: value,
    se (delta method from log space), ci95 (profile likelihood, F-based; an end that does
    not close inside RATIO_RANGE is None), ssr, residuals (measured - fitted), fitted.

    Raises SelfshapeError ("not identifiable", naming the file) when the rows cannot
    determine the ratio or its standard error: fewer than two specimens (no residual
    degrees of freedom), curvatures that do not change with the ratio (no misfit: stretch
    1), or a least-squares optimum on a bound of RATIO_RANGE (e.g. curvatures <= 0, which
    the bilayer reaches only as the ratio runs to 0 or infinity)."""
    from validation import stats
    name = rows.get("_file", "data")
    y = rows[MEASURED]
    n_spec = specimen_count(rows)
    if n_spec < 2:
        raise SelfshapeError(f"{name}: {y.size} row(s) from {n_spec} specimen: {what} has no residual degrees of "
                             f"freedom, its standard error is not identifiable (need rows from >= 2 specimens)")
    args = (rows["plastic_thickness_mm"], rows["fabric_thickness_mm"], rows["stretch"])
    kb = np.asarray(rest_curvature, float)
    grid = np.exp(np.linspace(*np.log(RATIO_RANGE), 71))
    k = strip_model(*(a[None] for a in args), grid[:, None], rest_curvature=kb)
    bad = ~np.all(np.isfinite(k), axis=0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise SelfshapeError(f"{name}: row {i + 1} (specimen {rows['specimen'][i]}): the bilayer model has no "
                             f"finite curvature for this strip")
    span = np.ptp(k, axis=0)
    scale = max(float(np.abs(y).max()), float(np.abs(k).max()), 1e-300)
    if float(span.max()) <= 1e-9 * scale:
        raise SelfshapeError(f"{name}: {what} is not identifiable: the model's curvatures do not change with it "
                             f"over {RATIO_RANGE[0]:g}-{RATIO_RANGE[1]:g} (no misfit: every stretch is 1?)")
    t0 = np.log(grid[np.argmin(((k - y) ** 2).sum(1))])

    def res(t):  # t: (1,) or (m, 1) log ratio
        t = np.asarray(t, float)
        return strip_model(*args, np.exp(t[..., :1]), rest_curvature=kb) - y

    lo, hi = np.log(RATIO_RANGE)
    r = stats.nls_fit(res, [t0], [lo], [hi], batch_fn=res)
    t_hat = float(r["theta"][0])
    if r["at_bound"][0]:
        end = RATIO_RANGE[int(t_hat > 0.5 * (lo + hi))]
        raise SelfshapeError(f"{name}: {what} is not identifiable: the least-squares fit runs to the search bound "
                             f"{end:g} (the curvatures do not determine it; e.g. all curvatures <= 0 or at the "
                             f"model's limit)")
    ssr_of = lambda t: float((res(np.array([t])) ** 2).sum())  # noqa: E731
    ci = stats.profile_interval(ssr_of, t_hat, r["ssr"], y.size, 1, lo, hi)
    value = float(np.exp(t_hat))
    fitted = y + r["residuals"]
    return {"value": value, "se": value * float(r["se"][0]),
            "ci95": [None if c is None else float(np.exp(c)) for c in ci],
            "ssr": r["ssr"], "residuals": -r["residuals"], "fitted": fitted}


def seed_linear_fit(rows):
    """The seed's calibration (section 3.3): linear regression through the origin
    of kappa - kbar on 6 h2 (h1 + h2)(1 - 1/s^2) / h1^3 (Eq. 3.17), slope E2/E1.
    Missing rest curvatures count as 0. Returns (E1/E2, standard error); raises
    SelfshapeError when the regression defines no positive ratio with an error
    (no misfit, a slope <= 0, fewer than 2 specimens)."""
    h1, h2, s = rows["plastic_thickness_mm"], rows["fabric_thickness_mm"], rows["stretch"]
    x = 6 * h2 * (h1 + h2) * (1 - 1 / s ** 2) / h1 ** 3
    y = rows[MEASURED] - np.nan_to_num(rows[REST], nan=0.0)
    if specimen_count(rows) < 2:
        raise SelfshapeError("fewer than 2 specimens: no residual degrees of freedom")
    xx = float(x @ x)
    if not xx > 0:
        raise SelfshapeError("no misfit in any row (stretch 1)")
    slope = float(x @ y) / xx
    if not slope > 0:
        raise SelfshapeError(f"slope {slope:.3g} <= 0 defines no modulus ratio")
    dof = x.size - 1
    se = float(np.sqrt(((y - slope * x) ** 2).sum() / dof / xx))
    return 1.0 / slope, se / slope ** 2


def calibrate_strips(csv_path, out_dir) -> dict:
    """Fit the plastic/fabric modulus ratio to a strips CSV with the base model
    (plastic flat at rest: step 1 of the validation loop). Writes out_dir/parameters.json
    (``modulus_ratio`` [value, standard error], its 95 % profile-likelihood
    interval, the fit residuals; for comparison the ratio with the measured rest
    curvatures and the seed's Eq. 3.17 linear regression) and
    out_dir/strips_fit.png (checked before the fit, written atomically, parameters.json last,
    every number finite: shellfem.outfiles). Returns the parameters dict.

    A ratio the rows cannot determine, or determine without residual degrees of freedom,
    is a SelfshapeError (see fit_modulus_ratio), written nowhere. The comparison fits are
    left out, with the reason under ``not_identifiable``, when only they fail; an interval
    end that does not close inside the search range is null, with the reason there too."""
    refuse_overwrite(out_dir, [csv_path])
    rows = read_strips(csv_path)
    outs = OutputDir(out_dir, STRIPS_OUTPUTS, inputs=[csv_path]).begin()   # checked, stale removed, before the fit
    base = fit_modulus_ratio(rows)
    out = {"modulus_ratio": [base["value"], base["se"]]}
    not_identifiable = {}
    rest = rows[REST]
    wr = None
    if np.isfinite(rest).all():
        try:
            wr = fit_modulus_ratio(rows, rest_curvature=rest, what="modulus_ratio_rest_measured")
        except SelfshapeError as e:
            not_identifiable["modulus_ratio_rest_measured"] = str(e)
        else:
            out["modulus_ratio_rest_measured"] = [wr["value"], wr["se"]]
    try:
        out["modulus_ratio_seed_eq3_17"] = list(seed_linear_fit(rows))
    except SelfshapeError as e:
        not_identifiable["modulus_ratio_seed_eq3_17"] = f"the seed's Eq. 3.17 regression: {e}"
    n = n_rows(rows)
    out["confidence_intervals_95"] = {"modulus_ratio": base["ci95"]}
    if wr is not None:
        out["confidence_intervals_95"]["modulus_ratio_rest_measured"] = wr["ci95"]
    for key, ci in out["confidence_intervals_95"].items():
        for end, v, bound in (("lower", ci[0], RATIO_RANGE[0]), ("upper", ci[1], RATIO_RANGE[1])):
            if v is None:
                not_identifiable[f"confidence_intervals_95.{key}.{end}"] = (
                    f"the 95 % interval does not close before the search bound {bound:g}: "
                    f"the data do not bound {key} from this side")
    out["not_identifiable"] = not_identifiable
    out["fit"] = {"data": rows["_file"], "n_rows": n, "n_specimens": specimen_count(rows),
                  "model": model_source() + ", mode narrow",
                  "base_model": "plastic flat at rest (rest curvature 0); only the modulus ratio is fitted",
                  "method": "nonlinear least squares on log(modulus_ratio); standard error by the delta "
                            "method; 95 % interval by profile likelihood (F test)",
                  "rms_residual_per_mm": float(np.sqrt(base["ssr"] / n)),
                  "relative_rms": float(np.sqrt(base["ssr"] / n) / np.sqrt(np.mean(rows[MEASURED] ** 2))),
                  "poisson": {"plastic": PLASTIC_POISSON, "fabric": FABRIC_POISSON}}
    out["residuals"] = {"specimen": [str(s) for s in rows["specimen"]],
                        "measured_per_mm": [float(v) for v in rows[MEASURED]],
                        "fitted_per_mm": [float(v) for v in base["fitted"]],
                        "residual_per_mm": [float(v) for v in base["residuals"]]}
    out = finite_json(out)
    with outs:                  # atomic, parameters.json last; nothing left on failure
        outs.write("strips_fit.png", lambda tmp: _plot_fit(rows, base["value"], tmp))
        outs.write_json("parameters.json", out)
    return out


def check_for_validation(csv_path, outputs=(), min_specimens=10) -> dict:
    """The strips CSV of ``selfshape validate``, checked before the loop runs: readable, at
    least ``min_specimens`` specimens (its 5-fold split is grouped by specimen, each outer
    training part split again), a base model the rows determine (fit_modulus_ratio), and no
    output path equal to the input. Returns the rows."""
    for o in outputs:
        refuse_overwrite(o, [csv_path])
    rows = read_strips(csv_path)
    n_spec = specimen_count(rows)
    if n_spec < min_specimens:
        raise SelfshapeError(f"{rows['_file']}: {n_rows(rows)} rows from {n_spec} specimen(s); validation splits by "
                             f"specimen and needs at least {min_specimens}")
    fit_modulus_ratio(rows)
    return rows


def _plot_fit(rows, ratio, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5.5, 4.0))
    h = rows["plastic_thickness_mm"]
    hs = np.linspace(h.min() * 0.9, h.max() * 1.1, 100)
    keys = sorted({(rows["side"][i], rows["stretch"][i]) for i in range(n_rows(rows))})
    for j, (side, s) in enumerate(keys):
        m = (rows["side"] == side) & (rows["stretch"] == s)
        color = f"C{j % 10}"
        ax.plot(h[m], rows[MEASURED][m], "o", ms=3, color=color, alpha=0.6, label=f"{side}, s = {s:g}")
        hf = float(np.median(rows["fabric_thickness_mm"][m]))
        ax.plot(hs, strip_model(hs, hf, s, ratio), "-", color=color, lw=1.2)
    ax.set_xlabel("plastic thickness (mm)")
    ax.set_ylabel("curvature (1/mm)")
    ax.set_title(f"{rows['_file']}: base model, E_p/E_f = {ratio:.4g}", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
