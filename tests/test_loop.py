"""The closed validation loop on data these tests generate: the project's strip model
(shellfem.strip) + one effect the data do not declare + seeded noise. The effects are
written here independently of validation.effects."""
import csv
import json
import os

import numpy as np
import pytest

from shellfem.errors import SelfshapeError
from shellfem.strip import strip_curvature
from validation import loop
from validation.strips import MEASURED, REST, read_strips

R_TRUE = 2500.0
NOISE = 0.015  # relative measurement noise of the synthetic curvatures


def design(seed, n_points=16, reps=3, sides=("front", "back"), stretch=(1.35,), orientation=(0.0,),
           fabric=(0.6, 0.8, 1.0), width=(10.0,), length=(40.0,), plastic=(0.25, 0.35, 0.45, 0.6)):
    """Random design points (each level set drawn so that every level appears),
    each repeated ``reps`` times: a rows dict like read_strips returns."""
    rng = np.random.default_rng(seed)
    cols = {"side": sides, "stretch": stretch, "orientation_deg": orientation, "fabric_thickness_mm": fabric,
            "width_mm": width, "length_mm": length, "plastic_thickness_mm": plastic}
    pts = {}
    for c, levels in cols.items():
        idx = np.concatenate([rng.permutation(len(levels)) for _ in range(-(-n_points // len(levels)))])
        pts[c] = np.asarray(levels, dtype=object if c == "side" else float)[rng.permutation(idx[:n_points])]
    rows = {c: np.repeat(v, reps) for c, v in pts.items()}
    n = n_points * reps
    rows["specimen"] = np.array([f"T-{i:03d}" for i in range(n)], dtype=object)
    rows[REST] = np.full(n, np.nan)
    rows["_file"] = "synthetic.csv"
    return rows


def rigidity(hp, hf, R):
    """Bilayer flexural rigidity per width / E_fabric (composite beam, mm^3)."""
    zc = (hf * 0.0 + R * hp * (hf / 2 + hp / 2)) / (hf + R * hp)
    return hf ** 3 / 12 + hf * zc ** 2 + R * (hp ** 3 / 12 + hp * (hf / 2 + hp / 2 - zc) ** 2)


def curvature(rows, effect=None, seed=1):
    """Noisy 'measured' curvatures: the strip model with one effect applied."""
    hp, hf, s = (rows[c].astype(float).copy() for c in ("plastic_thickness_mm", "fabric_thickness_mm", "stretch"))
    R = np.full(hp.size, R_TRUE)
    rest = np.zeros(hp.size)
    back = rows["side"] == "back"
    th = np.radians(rows["orientation_deg"])
    post = None
    if effect == "plastic_set_measured":
        rng = np.random.default_rng(seed + 100)
        rest = 0.016 - 0.02 * hp + rng.normal(0, 0.0015, hp.size)  # specimen-to-specimen set
        rows[REST] = rest + rng.normal(0, 0.0001, hp.size)          # measured after peeling
    elif effect == "plastic_set_constant":
        rest[:] = 0.006
    elif effect == "plastic_set_thickness":
        rest = 0.008 - 0.04 * (hp - 0.4)
    elif effect == "side_deposition":
        hp = np.where(back, hp + 0.06, hp)
    elif effect == "side_deposition_factor":
        hp = np.where(back, hp * 1.3, hp)
    elif effect == "side_fabric_stiffness":
        R = np.where(back, R / 1.8, R)
    elif effect == "thickness_bias":
        hp = hp + 0.06
    elif effect == "stretch_modulus":
        R = R * (s / 1.35) ** -4.0
    elif effect == "plastic_prestrain":
        s = s * (1 - 0.05)
    elif effect == "orthotropy":
        R = R / (1 + 0.35 * np.cos(2 * th))
    elif effect == "fabric_compression":
        hf = hf * 0.6
    elif effect == "plastic_seeping":
        hp, hf = hp + 0.15, hf - 0.15
    elif effect in ("gravity", "width_transition"):
        post = effect
    elif effect is not None:
        raise KeyError(effect)
    k = strip_curvature(hp, hf, s, R, rest_curvature=rest)
    if post == "gravity":
        k = k - 2e-3 * rows["length_mm"] ** 2 / (24 * rigidity(hp, hf, R))
    elif post == "width_transition":
        kp = strip_curvature(hp, hf, s, R, mode="plate")
        b = rows["width_mm"] ** 2 * k / (hp + hf)
        k = k + b ** 2 / (b ** 2 + 6.0 ** 2) * (kp - k)
    rng = np.random.default_rng(seed)
    rows[MEASURED] = k * (1 + NOISE * rng.standard_normal(k.size))
    return rows


# designs that make each effect identifiable (its covariate varies)
DESIGNS = {
    "stretch_modulus": {"stretch": (1.2, 1.35, 1.6)},
    "plastic_prestrain": {"stretch": (1.2, 1.35, 1.6)},
    "orthotropy": {"orientation": (0.0, 45.0, 90.0)},
    "gravity": {"length": (30.0, 60.0, 120.0)},
    "width_transition": {"width": (3.0, 10.0, 30.0)},
}
EFFECTS = ["plastic_set_measured", "plastic_set_constant", "plastic_set_thickness", "side_deposition",
           "side_deposition_factor", "side_fabric_stiffness", "thickness_bias", "stretch_modulus",
           "plastic_prestrain", "orthotropy", "gravity", "width_transition", "fabric_compression",
           "plastic_seeping"]


def synthetic(effect, seed=0, **kw):
    d = dict(DESIGNS.get(effect, {}))
    d.update(kw)
    return curvature(design(seed, **d), effect, seed=seed + 1)


def found(sel, effect):
    """The effect was added, or reported indistinguishable from an added one."""
    if effect in sel["added"]:
        return True
    return any(effect in d["effects"] and set(d["effects"]) & set(sel["added"]) for d in sel["indistinguishable"])


def _rel(x, y):
    return float(x / np.sqrt(np.mean(y ** 2)))


@pytest.mark.parametrize("effect", EFFECTS)
def test_loop_finds_each_catalogue_effect(effect):
    rows = synthetic(effect)
    y = rows[MEASURED]
    sel = loop.select_effects(rows, seed=0, folds=4)
    assert found(sel, effect), (sel["added"], sel["indistinguishable"])
    before = _rel(sel["cv_rms_before"], y)
    after = _rel(sel["cv_rms_after"], y)
    assert before > 1.5 * NOISE      # the effect matters ...
    assert after < 1.3 * NOISE       # ... and the loop brings the CV error to the noise level


def write_csv(rows, path, measured=True):
    cols = ["specimen", "side", "stretch", "orientation_deg", "plastic_thickness_mm", "fabric_thickness_mm",
            "width_mm", "length_mm"] + ([MEASURED] if measured else []) + [REST]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for i in range(len(rows["specimen"])):
            w.writerow(["" if isinstance(rows[c][i], float) and np.isnan(rows[c][i]) else
                        (f"{rows[c][i]:.10g}" if isinstance(rows[c][i], float) else rows[c][i]) for c in cols])


def test_clean_data_add_nothing_and_errors_are_held_out():
    rows = curvature(design(3, n_points=16, stretch=(1.2, 1.35, 1.6), orientation=(0.0, 45.0, 90.0),
                            width=(5.0, 10.0, 20.0), length=(30.0, 60.0, 90.0)), None, seed=4)
    rows[REST] = np.random.default_rng(5).normal(0.004, 0.001, rows[MEASURED].size)  # unrelated column
    events = []
    rep = loop.validate(rows, seed=0, outer_folds=4, inner_folds=4, progress=events.append)
    # progress (issue 21): the 4 outer folds and the final selection, counted for the status line
    assert [(e["stage"], e["done"], e["total"], e["unit"]) for e in events] == [("tasks", k, 5, "fits") for k in range(6)]
    assert events[1]["last"] == "outer fold 1/4" and events[-1]["last"] == "selection on all rows"
    assert rep["effects_added"] == []
    assert all(not f for f in rep["effects_added_per_outer_fold"])
    names = {r["name"] for r in rep["effects_rejected"]}
    assert names == {e.name for e in loop.fx.CATALOGUE}
    assert abs(rep["error_after"] - rep["error_before"]) < 1e-12
    assert 0.5 * NOISE < rep["error_before"] < 1.3 * NOISE
    assert abs(rep["parameters"]["modulus_ratio"][0] - R_TRUE) < 4 * rep["parameters"]["modulus_ratio"][1]
    # one fitted parameter on 3/4 of the rows: the held-out floor lies just above the residual floor
    n_train = 0.75 * rep["n_rows"]
    assert rep["noise_relative_held_out"] == pytest.approx(rep["noise_relative"] * np.sqrt(1 + 1 / n_train), rel=1e-12)


def test_held_out_floor_is_the_held_out_error_of_a_correct_linear_model():
    """Least squares with p parameters on n_train rows, K-fold held-out over many noise draws:
    the mean held-out squared error is sigma^2 (1 + p / n_train) up to the rows' leverage
    (between p / n_train and p / (n_train - p - 1)); the plain sigma is below it."""
    rng = np.random.default_rng(11)
    n, p, sigma, k = 60, 6, 0.3, 5
    X = np.column_stack([np.ones(n), rng.normal(size=(n, p - 1))])
    beta = rng.normal(size=p)
    folds = np.array_split(rng.permutation(n), k)
    mse = []
    for _ in range(800):
        y = X @ beta + rng.normal(0, sigma, n)
        err = np.empty(n)
        for te in folds:
            tr = np.setdiff1d(np.arange(n), te)
            b = np.linalg.lstsq(X[tr], y[tr], rcond=None)[0]
            err[te] = y[te] - X[te] @ b
        mse.append(np.mean(err ** 2))
    held = np.sqrt(np.mean(mse))
    n_train = n - n // k
    lo = loop.held_out_floor(sigma, p, n_train)
    hi = sigma * np.sqrt(1 + p / (n_train - p - 1))
    assert lo == pytest.approx(sigma * np.sqrt(1 + p / n_train))
    assert 0.99 * lo < held < 1.01 * hi
    assert held > 1.03 * sigma
    with pytest.raises(ValueError):
        loop.held_out_floor(sigma, p, 0)


def test_confounded_effects_are_reported():
    # only back-face strips: extra back-face deposition is a thickness bias here
    rows = curvature(design(6, sides=("back",)), "thickness_bias", seed=7)
    sel = loop.select_effects(rows, seed=0, folds=4)
    assert len(sel["added"]) == 1
    pairs = [set(d["effects"]) for d in sel["indistinguishable"]]
    assert {"thickness_bias", "side_deposition"} in pairs
    other = ({"thickness_bias", "side_deposition"} - set(sel["added"])).pop()
    assert "indistinguishable" in sel["rejected"][other]


def test_validate_file_predict_round_trip(tmp_path):
    rows = synthetic("side_deposition", seed=11)
    data = tmp_path / "strips_T.csv"
    write_csv(rows, data)
    out = tmp_path / "out"
    rep = loop.validate_file(data, out, seed=0)
    on_disk = json.loads((out / "report.json").read_text())
    for key in ("error_before", "error_after", "effects_added", "effects_rejected", "parameters",
                "indistinguishable", "residual_tests_before", "residual_tests_after"):
        assert key in on_disk
    assert on_disk["effects_added"] == rep["effects_added"]
    assert "side_deposition" in rep["effects_added"]
    assert rep["error_after"] < 0.2 * rep["error_before"]
    assert rep["error_after"] < 1.5 * rep["noise_relative"]  # held out, 48 rows, multiplicative noise
    p = rep["parameters"]["side_deposition.back_extra_thickness_mm"]
    assert abs(p[0] - 0.06) < 4 * p[1]
    assert all(isinstance(r["reason"], str) and r["reason"] for r in rep["effects_rejected"])
    for png in ("residuals_before.png", "residuals_after.png"):
        assert (out / png).stat().st_size > 1000
    # predict reproduces the fitted model, also on a file without the measured column
    model = json.loads((out / "model.json").read_text())
    expect = loop.predict_rows(model, read_strips(data))
    pred_csv = tmp_path / "pred.csv"
    assert loop.predict_file(out / "model.json", data, pred_csv) == len(rows["specimen"])
    with open(pred_csv) as fh:
        table = list(csv.DictReader(fh))
    got = np.array([float(r[MEASURED + "_predicted"]) for r in table])
    assert np.allclose(got, expect, rtol=1e-7)
    assert table[0]["specimen"] == "T-000" and MEASURED in table[0]
    bare = tmp_path / "bare.csv"
    write_csv(rows, bare, measured=False)
    assert loop.predict_file(out / "model.json", bare, tmp_path / "pred2.csv") == len(rows["specimen"])
    with open(tmp_path / "pred2.csv") as fh:
        got2 = np.array([float(r[MEASURED + "_predicted"]) for r in csv.DictReader(fh)])
    assert np.allclose(got2, expect, rtol=1e-7)


def test_bad_input_one_line_errors(tmp_path):
    rows = synthetic(None, seed=2)
    data = tmp_path / "d.csv"
    write_csv(rows, data)
    bad = tmp_path / "bad_model.json"
    bad.write_text(json.dumps({"format": loop.FORMAT, "effects": [{"name": "telekinesis"}], "theta": [1.0]}))
    with pytest.raises(SelfshapeError, match="bad_model.json.*telekinesis"):
        loop.predict_file(bad, data, tmp_path / "p.csv")
    (tmp_path / "junk.json").write_text("{not json")
    with pytest.raises(SelfshapeError, match="junk.json"):
        loop.predict_file(tmp_path / "junk.json", data, tmp_path / "p.csv")
    assert not (tmp_path / "p.csv").exists()
    text = data.read_text().splitlines()
    text[3] = text[3].replace("front", "sideways").replace("back", "sideways")
    (tmp_path / "e.csv").write_text("\n".join(text) + "\n")
    with pytest.raises(SelfshapeError, match=r"e.csv: row 3 .*column side"):
        loop.validate_file(tmp_path / "e.csv", tmp_path / "o")
    with pytest.raises(SelfshapeError, match="at least"):
        loop.validate({k: (v[:5] if isinstance(v, np.ndarray) else v) for k, v in rows.items()})


def test_cli_validate_and_predict(tmp_path):
    from selfshape.cli import main
    rows = synthetic("plastic_set_constant", seed=21, n_points=8, reps=2)
    data = tmp_path / "c.csv"
    write_csv(rows, data)
    assert main(["validate", str(data), "-o", str(tmp_path / "v")]) == 0
    assert main(["predict", str(tmp_path / "v" / "model.json"), str(data), "-o", str(tmp_path / "p.csv")]) == 0
    assert main(["predict", str(tmp_path / "nope.json"), str(data), "-o", str(tmp_path / "q.csv")]) == 2


@pytest.mark.slow
def test_strips_s1_loop(tmp_path):
    """The lab-style file shipped with the project (validation/data/strips_S1.csv): the base
    model misses structure (held-out error several times the noise floor; measured 4.9 x), the
    loop adds the back-face deposition and brings the held-out error near the noise floor
    (measured 1.12 x)."""
    path = os.path.join(os.path.dirname(__file__), "..", "validation", "data", "strips_S1.csv")
    rep = loop.validate_file(path, tmp_path, seed=0)
    assert rep["error_after"] < rep["error_before"]
    assert rep["effects_added"]
    assert rep["error_before"] > 3 * rep["noise_relative"]
    assert rep["error_after"] < 1.5 * rep["noise_relative"]
    assert "side_deposition" in rep["effects_added"]


def test_three_undeclared_effects_at_once():
    """Back-face deposition, fabric orthotropy and a specimen-to-specimen plastic set
    that only the measured rest-curvature column reveals."""
    rows = design(0, n_points=24, orientation=(0.0, 45.0, 90.0), stretch=(1.25, 1.35, 1.5), width=(5.0, 10.0, 20.0),
                  length=(30.0, 60.0))
    hp, back = rows["plastic_thickness_mm"], rows["side"] == "back"
    rng = np.random.default_rng(50)
    rest = 0.016 - 0.02 * hp + rng.normal(0, 0.001, hp.size)
    rows[REST] = rest + rng.normal(0, 2e-4, hp.size)
    R = R_TRUE / (1 + 0.25 * np.cos(2 * np.radians(rows["orientation_deg"])))
    k = strip_curvature(np.where(back, hp + 0.05, hp), rows["fabric_thickness_mm"], rows["stretch"], R,
                        rest_curvature=rest)
    rows[MEASURED] = k * (1 + NOISE * rng.standard_normal(k.size))
    sel = loop.select_effects(rows, seed=0)
    assert sorted(sel["added"]) == ["orthotropy", "plastic_set_measured", "side_deposition"]
    p = loop._parameters(sel["fit"])
    for name, true in (("orthotropy.cos2theta_amplitude", 0.25), ("side_deposition.back_extra_thickness_mm", 0.05)):
        assert abs(p[name][0] - true) < 4 * p[name][1], name
    assert _rel(sel["cv_rms_after"], rows[MEASURED]) < 1.3 * NOISE
