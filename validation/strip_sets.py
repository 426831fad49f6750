"""Synthetic strip sets with known undeclared effects, for measuring the validation loop.

A *strip set* is a rows dict of the strips schema (validation/data/README.md; the same
dict :func:`validation.strips.read_strips` returns) whose measured curvatures come from
the project's strip model (:func:`shellfem.strip.strip_curvature`) with one or more
physical effects applied and seeded measurement noise added. The effects are written
here from their physical description, independently of :mod:`validation.effects`, so
that recovering them tests the loop and the catalogue together rather than one code
path against itself.

Why: the loop (validation.loop) must find every effect such data hold when the data can
tell it apart, add nothing to clean data, and reach the noise floor on held-out rows
(issue 19). :data:`CASES` lists the two- and three-effect combinations the study
(studies/loop_recovery.py) and the tests sweep, some of them partly confounded.

Units: mm, 1/mm; the noise is relative (a fraction of each curvature).
"""
from __future__ import annotations

import csv

import numpy as np

from validation.strips import MEASURED, REST

R_TRUE = 2500.0          # E_plastic / E_fabric of the generator
NOISE = 0.015            # relative measurement noise (standard deviation / curvature)
REFERENCE_STRETCH = 1.35  # the stretch at which the stretch-dependent modulus is unchanged
REFERENCE_THICKNESS = 0.4  # mm, thickness at which the thickness-law plastic set is k0

# levels of each design covariate; every level appears in every set
RICH = {"side": ("front", "back"), "stretch": (1.2, 1.35, 1.6), "orientation_deg": (0.0, 45.0, 90.0),
        "plastic_thickness_mm": (0.25, 0.35, 0.45, 0.6), "fabric_thickness_mm": (0.6, 0.8, 1.0),
        "width_mm": (3.0, 10.0, 30.0), "length_mm": (30.0, 60.0, 120.0)}
COLUMNS = ("specimen", "side", "stretch", "orientation_deg", "plastic_thickness_mm", "fabric_thickness_mm",
           "width_mm", "length_mm", MEASURED, REST)


def design(seed, n_points=24, reps=3, levels=None):
    """Rows dict of ``n_points`` random design points, each printed ``reps`` times
    (replicates share every design covariate; specimens are numbered per row). Each
    covariate's levels are dealt out evenly and shuffled independently (a random
    balanced design). ``levels``: {column: tuple} overriding :data:`RICH`."""
    rng = np.random.default_rng(seed)
    lv = dict(RICH)
    lv.update(levels or {})
    pts = {}
    for c, values in lv.items():
        idx = np.concatenate([rng.permutation(len(values)) for _ in range(-(-n_points // len(values)))])
        pts[c] = np.asarray(values, dtype=object if c == "side" else float)[rng.permutation(idx[:n_points])]
    rows = {c: np.repeat(v, reps) for c, v in pts.items()}
    n = n_points * reps
    rows["specimen"] = np.array([f"G-{i:03d}" for i in range(n)], dtype=object)
    rows[REST] = np.full(n, np.nan)
    rows[MEASURED] = np.full(n, np.nan)
    rows["_file"] = "synthetic.csv"
    return rows


def _rigidity(hp, hf, R):
    """Bilayer flexural rigidity per width in units of E_fabric (mm^3): composite beam,
    plastic on top of the fabric, bending about the neutral axis."""
    z_plastic = hf / 2 + hp / 2
    zn = R * hp * z_plastic / (hf + R * hp)
    return hf ** 3 / 12 + hf * zn ** 2 + R * (hp ** 3 / 12 + hp * (z_plastic - zn) ** 2)


# True parameter values used by default (the magnitudes the seed's strips suggest:
# a few hundredths of a mm of thickness change, a few thousandths of 1/mm of set, tens of
# per cent of modulus change).
DEFAULTS = {
    "plastic_set_measured": {"k0": 0.016, "k1": -0.02, "scatter": 0.0015, "measurement": 1e-4},
    "plastic_set_constant": {"k": 0.006},
    "plastic_set_thickness": {"k0": 0.008, "k1": -0.04},
    "thickness_bias": {"delta": 0.05},
    "side_deposition": {"delta": 0.06},
    "side_deposition_factor": {"f": 1.3},
    "side_fabric_stiffness": {"g": 1.8},
    "stretch_modulus": {"p": 4.0},
    "plastic_prestrain": {"e": 0.04},
    "orthotropy": {"c": 0.3},
    "gravity": {"q": 1.5e-4},
    "width_transition": {"b0": 6.0},
    "fabric_compression": {"c": 0.7},
    "plastic_seeping": {"d": 0.1},
}


def measure(rows, effects=(), seed=0, noise=NOISE, params=None, rest="empty"):
    """Fill ``rows[MEASURED]`` (and ``rows[REST]``) with synthetic measurements.

    effects: names (catalogue names, written independently here) applied together:
    thickness, stretch, modulus and rest-curvature changes first, then the width
    transition, then gravity. params: {effect: {name: value}} overriding
    :data:`DEFAULTS`. rest: what the rest-curvature column holds when
    ``plastic_set_measured`` is absent: "empty", or "unrelated" (a measured-looking
    column with no bearing on the curvature). noise: relative standard deviation of the
    multiplicative Gaussian measurement noise. Returns rows (modified in place) and sets
    ``rows["_truth"]`` = {effects, params, noise, modulus_ratio, noise_free}."""
    p = {e: dict(DEFAULTS[e], **(params or {}).get(e, {})) for e in effects}
    unknown = set(effects) - set(DEFAULTS)
    if unknown:
        raise KeyError(f"unknown effect(s) {sorted(unknown)}")
    rng = np.random.default_rng(seed)
    hp = rows["plastic_thickness_mm"].astype(float).copy()
    hf = rows["fabric_thickness_mm"].astype(float).copy()
    s = rows["stretch"].astype(float).copy()
    n = hp.size
    R = np.full(n, R_TRUE)
    kbar = np.zeros(n)
    back = rows["side"] == "back"
    c2 = np.cos(2 * np.radians(rows["orientation_deg"].astype(float)))
    h0 = hp.copy()  # nominal thickness (the laws of plastic set are in the nominal thickness)
    if "thickness_bias" in p:
        hp = hp + p["thickness_bias"]["delta"]
    if "side_deposition" in p:
        hp = np.where(back, hp + p["side_deposition"]["delta"], hp)
    if "side_deposition_factor" in p:
        hp = np.where(back, hp * p["side_deposition_factor"]["f"], hp)
    if "plastic_seeping" in p:
        d = p["plastic_seeping"]["d"]
        hp, hf = hp + d, hf - d
    if "fabric_compression" in p:
        hf = hf * p["fabric_compression"]["c"]
    if "side_fabric_stiffness" in p:
        R = np.where(back, R / p["side_fabric_stiffness"]["g"], R)
    if "stretch_modulus" in p:
        R = R * (s / REFERENCE_STRETCH) ** (-p["stretch_modulus"]["p"])
    if "orthotropy" in p:
        R = R / (1 + p["orthotropy"]["c"] * c2)
    if "plastic_prestrain" in p:
        s = s * (1 - p["plastic_prestrain"]["e"])
    if "plastic_set_constant" in p:
        kbar = kbar + p["plastic_set_constant"]["k"]
    if "plastic_set_thickness" in p:
        q = p["plastic_set_thickness"]
        kbar = kbar + q["k0"] + q["k1"] * (h0 - REFERENCE_THICKNESS)
    set_rng = np.random.default_rng(seed + 7_000_003)
    if "plastic_set_measured" in p:
        q = p["plastic_set_measured"]
        own = q["k0"] + q["k1"] * h0 + set_rng.normal(0.0, q["scatter"], n)  # specimen-to-specimen set
        kbar = kbar + own
        rows[REST] = own + set_rng.normal(0.0, q["measurement"], n)       # measured after peeling
    elif rest == "unrelated":
        rows[REST] = set_rng.normal(0.004, 0.001, n)
    elif rest == "empty":
        rows[REST] = np.full(n, np.nan)
    else:
        raise ValueError(f"rest must be 'empty' or 'unrelated', got {rest!r}")
    from shellfem.strip import strip_curvature
    k = strip_curvature(hp, hf, s, R, rest_curvature=kbar)
    if "width_transition" in p:
        kp = strip_curvature(hp, hf, s, R, rest_curvature=kbar, mode="plate")
        b = rows["width_mm"] ** 2 * np.abs(k) / (hp + hf)
        k = k + b ** 2 / (b ** 2 + p["width_transition"]["b0"] ** 2) * (kp - k)
    if "gravity" in p:
        k = k - p["gravity"]["q"] * rows["length_mm"] ** 2 / (24 * _rigidity(hp, hf, R))
    rows[MEASURED] = k * (1 + noise * rng.standard_normal(n))
    rows["_truth"] = {"effects": list(effects), "params": p, "noise": noise, "modulus_ratio": R_TRUE,
                      "noise_free": k}
    return rows


# The combinations the study sweeps: name -> effects. "partly confounded" pairs act on
# the curvature through the same covariate or the same model input, so the data separate
# them only through how the effect scales with the other covariates.
CASES = {
    "clean": (),
    # two effects
    "side_deposition+orthotropy": ("side_deposition", "orthotropy"),             # separate covariates
    "thickness_bias+plastic_set_constant": ("thickness_bias", "plastic_set_constant"),  # partly confounded
    "stretch_modulus+plastic_prestrain": ("stretch_modulus", "plastic_prestrain"),      # both through stretch
    "gravity+width_transition": ("gravity", "width_transition"),                 # length vs width
    "side_fabric_stiffness+plastic_set_thickness": ("side_fabric_stiffness", "plastic_set_thickness"),
    # three effects
    "side_deposition+orthotropy+plastic_set_measured": ("side_deposition", "orthotropy", "plastic_set_measured"),
    "thickness_bias+stretch_modulus+gravity": ("thickness_bias", "stretch_modulus", "gravity"),
    "side_fabric_stiffness+plastic_prestrain+width_transition": ("side_fabric_stiffness", "plastic_prestrain",
                                                                 "width_transition"),
    "side_deposition_factor+plastic_set_constant+orthotropy": ("side_deposition_factor", "plastic_set_constant",
                                                               "orthotropy"),
}


def strip_set(case, seed, n_points=24, reps=3, noise=NOISE, levels=None, params=None):
    """The synthetic set of ``case`` (a :data:`CASES` key, or a tuple of effect names)
    for ``seed``: design seed ``seed``, noise seed ``seed + 1``. Clean sets carry an
    unrelated rest-curvature column (a decoy), the others an empty one unless the
    measured plastic set is among the effects."""
    effects = CASES[case] if isinstance(case, str) else tuple(case)
    rows = design(seed, n_points=n_points, reps=reps, levels=levels)
    return measure(rows, effects, seed=seed + 1, noise=noise, params=params,
                   rest="unrelated" if not effects else "empty")


def write_csv(rows, path, measured=True):
    """Write rows as a strips CSV of the schema (empty rest-curvature cells where NaN)."""
    cols = [c for c in COLUMNS if measured or c != MEASURED]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for i in range(len(rows["specimen"])):
            out = []
            for c in cols:
                v = rows[c][i]
                if isinstance(v, (float, np.floating)):
                    out.append("" if np.isnan(v) else f"{v:.10g}")
                else:
                    out.append(v)
            w.writerow(out)
