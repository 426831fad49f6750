"""Fabric calibration (validation.fabric and its readers, curves and law modules): readers, the orthotropic model, and recovery of known parameters
from synthetic tensile / shear / cantilever tests. The shipped data are checked for
sanity only (finite, positive, SE > 0), never for their particular numbers."""
import json
import os

import numpy as np
import pytest

from shellfem.errors import SelfshapeError
from validation import elastica
from shellfem.materials import orthotropic as ortho
from validation import fabric as F
from validation import fabric_curves as FC
from validation import fabric_files as FF
from validation import fabric_law as FL

DATA = os.path.join(os.path.dirname(__file__), "..", "validation", "data", "fabric")
META = {"fabric_thickness_mm": 0.8, "tensile_width_mm": 20.0, "tensile_gauge_length_mm": 60.0,
        "shear_sample_side_mm": 40.0}
TRUE = {"a1": 0.03, "a2": 0.08, "a3": 0.05, "b1": 0.025, "b2": 0.02, "g1": 1.0, "g2": 1.05}
NU = 0.3


def _write_csv(path, header, rows):
    with open(path, "w") as f:
        f.write(",".join(header) + "\n")
        for r in rows:
            f.write(",".join(str(v) for v in r) + "\n")


def _tensile_rows(stress_of_e, max_pct, rng, n=100, cycles=3, noise_n=0.003, first_cycle_scale=1.0):
    """Load/unload cycles: unloading follows stress_of_e exactly (+ load-cell noise), loading
    is stiffer (hysteresis loop); cycle 1 unloading optionally scaled (not stabilised)."""
    L, w, h = META["tensile_gauge_length_mm"], META["tensile_width_mm"], META["fabric_thickness_mm"]
    d_up = np.linspace(0, L * max_pct / 100, n)
    rows, t = [], 0.0
    for c in range(1, cycles + 1):
        for branch, d in (("load", d_up), ("unload", d_up[::-1])):
            e = FC.green_strain(d, L)
            S = stress_of_e(e)
            if branch == "load":
                S = S + 0.3 * S.max() * np.sin(np.pi * d / d.max()) ** 0.7
            elif c == 1:
                S = S * first_cycle_scale
            f = S * w * h * (d + L) / L + noise_n * rng.standard_normal(n)
            for di, fi in zip(d, f):
                rows.append((f"{t:.2f}", c, branch, f"{di:.5f}", f"{fi:.6f}"))
                t += 0.5
    return rows


def _synthetic_folder(tmp_path, rng, k_b=None):
    folder = tmp_path / "fabric"
    folder.mkdir()
    (folder / "meta.json").write_text(json.dumps(META))
    for pct in (45, 70):
        for deg in (0, 30, 45, 60, 90):
            rows = _tensile_rows(lambda e: FL.uniaxial_response(e, deg, TRUE, NU)[0], pct, rng, first_cycle_scale=0.9)
            _write_csv(folder / f"tensile_{deg:02d}deg_{pct}pct.csv", list(FF.TENSILE_COLUMNS), rows)
    side, h = META["shear_sample_side_mm"], META["fabric_thickness_mm"]
    for deg, cubic in ((0, 0.06), (90, 0.02)):  # orientation-dependent stiffening at large shear
        u = np.linspace(0, 14, 60)
        g = u / side
        load = (TRUE["a3"] * g + cubic * g ** 3) * side * h + 0.003 * rng.standard_normal(u.size)
        _write_csv(folder / f"shear_{deg:02d}deg.csv", list(FF.SHEAR_COLUMNS), zip(u, load))
    k_b = k_b or {"0/front": 0.015, "0/back": 0.016, "90/front": 0.011, "90/back": 0.03}
    rows = []
    for key, k in k_b.items():
        o, face = key.split("/")
        for L in (20, 30, 40, 50, 60, 80, 100):
            hw = elastica.master_curve(1.9e-6 * L ** 3 / k) * (1 + 0.02 * rng.standard_normal())
            rows.append((o, face, L, "1.9e-06", f"{hw:.6f}"))
    _write_csv(folder / "cantilever.csv", list(FF.CANTILEVER_COLUMNS), rows)
    return str(folder), k_b


# ----------------------------------------------------------------------------- model

def test_stiffness_from_uniaxial_inverts_eq46():
    a1, a2, nu = 0.024161, 0.09089, 0.3
    A1 = (a1 - np.sqrt(a1 * a2) * nu ** 2) / (1 - nu ** 2)
    A2 = (a2 - np.sqrt(a1 * a2) * nu ** 2) / (1 - nu ** 2)
    assert FC.stiffness_from_uniaxial(A1, A2, nu) == pytest.approx((a1, a2), rel=1e-12)
    with pytest.raises(SelfshapeError):
        FC.stiffness_from_uniaxial(-0.01, 0.05, 0.3)


def test_stress_is_the_gradient_of_the_energy_and_tangent_its_hessian():
    p = dict(TRUE)

    def psi(eps):
        a1, a2, a3 = p["a1"], p["a2"], p["a3"]
        C = np.array([[a1, np.sqrt(a1 * a2) * NU, 0], [np.sqrt(a1 * a2) * NU, a2, 0], [0, 0, a3 * (1 - NU ** 2)]])
        out = 0.5 * eps @ C @ eps / (1 - NU ** 2)
        for i, (b, g) in enumerate(((p["b1"], p["g1"]), (p["b2"], p["g2"]))):
            e = eps[i]  # Eq. 4.3, both branches as written in the seed
            if e > 0:
                out -= b * ((e - g) * np.log((g - e) / g) - e)
            elif e < 0:
                out -= -b * ((e + g) * np.log((g + e) / g) - e)
        return out

    eps = np.array([0.6, -0.2, 0.3])
    sig, K = ortho.orthotropic_stress(eps[None], p, NU)
    h = 1e-6
    num = [(psi(eps + h * np.eye(3)[k]) - psi(eps - h * np.eye(3)[k])) / (2 * h) for k in range(3)]
    assert sig[0] == pytest.approx(num, rel=1e-6, abs=1e-10)
    numK = [(ortho.orthotropic_stress((eps + h * np.eye(3)[k])[None], p, NU)[0][0]
             - ortho.orthotropic_stress((eps - h * np.eye(3)[k])[None], p, NU)[0][0]) / (2 * h) for k in range(3)]
    assert K[0] == pytest.approx(np.array(numK).T, rel=1e-6, abs=1e-9)


def test_uniaxial_response_isotropic_is_angle_independent_and_exact():
    E_, nu = 0.1, 0.3
    iso = {"a1": E_, "a2": E_, "a3": E_ / (2 * (1 + nu)), "b1": 1e-12, "b2": 1e-12, "g1": 5.0, "g2": 5.0}
    e = np.linspace(0.0, 0.5, 11)
    ref, free0 = FL.uniaxial_response(e, 0.0, iso, nu)
    assert ref == pytest.approx(E_ * e, rel=1e-8, abs=1e-14)  # plane-stress uniaxial: sigma = E e
    assert free0[:, 0] == pytest.approx(-nu * e, rel=1e-8, abs=1e-14)
    for deg in (15.0, 45.0, 72.0):
        s, free = FL.uniaxial_response(e, deg, iso, nu)
        assert s == pytest.approx(ref, rel=1e-8, abs=1e-14)
        assert free[:, 1] == pytest.approx(0.0, abs=1e-10)


def test_uniaxial_small_strain_slope_at_0_deg():
    p = dict(TRUE)
    k11 = p["a1"] / (1 - NU ** 2) + p["b1"] / p["g1"]
    k22 = p["a2"] / (1 - NU ** 2) + p["b2"] / p["g2"]
    k12 = np.sqrt(p["a1"] * p["a2"]) * NU / (1 - NU ** 2)
    s, _ = FL.uniaxial_response([1e-7], 0.0, p, NU)
    assert s[0] / 1e-7 == pytest.approx(k11 - k12 ** 2 / k22, rel=1e-5)


def test_interpolation_by_stretch_is_linear_and_clamped():
    by = {"45": {"a": 1.0}, "70": {"a": 2.0}}
    assert F.interpolate_by_stretch(by, 57.5)["a"] == pytest.approx(1.5)
    assert F.interpolate_by_stretch(by, 30)["a"] == 1.0 and F.interpolate_by_stretch(by, 90)["a"] == 2.0


# ----------------------------------------------------------------------------- fits

def test_barrier_curve_fit_recovers_parameters_with_honest_errors():
    rng = np.random.default_rng(3)
    e = np.linspace(0, 0.945, 240)
    A, b, g = 0.024, 0.03, 0.9626
    S = FC.barrier_curve(e, A, b, g) + 2e-4 * rng.standard_normal(e.size)
    fit = FC.fit_barrier_curve(e, S)
    assert fit["A"] == pytest.approx(A, rel=0.02)
    assert fit["b"] == pytest.approx(b, rel=0.02)
    assert fit["g"] == pytest.approx(g, rel=1e-3)
    for v, true, se in zip((fit["A"], fit["b"], fit["g"]), (A, b, g), fit["se"]):
        assert 0 < se and abs(v - true) < 4 * se
    tan, se = FC.release_tangent(fit)
    assert tan == pytest.approx(A + b / (g - 0.945), rel=0.03) and se > 0


def test_shear_fit_recovers_initial_slope_under_cubic_stiffening():
    rng = np.random.default_rng(5)
    g = np.linspace(0, 0.35, 60)
    tau = 0.0634 * g + 0.06 * g ** 3 + 1e-4 * rng.standard_normal(g.size)
    fit = FC.fit_shear_modulus(g, tau)
    assert fit["odd_cubic"]["slope"] == pytest.approx(0.0634, rel=0.02)
    assert abs(fit["odd_cubic"]["slope"] - 0.0634) < 4 * fit["odd_cubic"]["se"]
    assert fit["linear"]["slope"] > 0.0634 * 1.04  # the straight line over the range is biased up


def test_stabilised_cycles_drop_preconditioning_and_drifting_cycles():
    rng = np.random.default_rng(11)
    stress = lambda e: FC.barrier_curve(e, 0.03, 0.02, 1.0)  # noqa: E731
    rows = _tensile_rows(stress, 70, rng, cycles=4)
    # make cycle 2 unloading 5 % stiffer than the (stable) cycles 3 and 4
    fixed = []
    for r in rows:
        if r[1] == 2 and r[2] == "unload":
            r = r[:4] + (f"{float(r[4]) * 1.05:.6f}",)
        fixed.append(r)
    t = {"cycle": np.array([r[1] for r in fixed]), "branch": np.array([r[2] for r in fixed]),
         "extension_mm": np.array([float(r[3]) for r in fixed]), "load_N": np.array([float(r[4]) for r in fixed])}
    cycles, why = FC.stabilised_cycles(t, META)
    assert cycles == [3, 4] and "preconditioning" in why
    t1 = {k: v[t["cycle"] == 1] for k, v in t.items()}
    assert FC.stabilised_cycles(t1, META)[0] == [1]


def test_calibration_recovers_known_parameters(tmp_path):
    rng = np.random.default_rng(2024)
    folder, k_b = _synthetic_folder(tmp_path, rng)
    out = tmp_path / "out"
    res = F.calibrate_fabric(folder, str(out))
    on_disk = json.loads((out / "parameters.json").read_text())
    assert on_disk["orthotropic"] == res["orthotropic"]
    o = res["orthotropic"]
    tol = {"a1": 0.03, "a2": 0.02, "a3": 0.02, "b1": 0.03, "b2": 0.03, "g1": 0.003, "g2": 0.003}
    for k, rel in tol.items():
        assert o[k][0] == pytest.approx(TRUE[k], rel=rel), k
        assert o[k][1] > 0
    # model-consistent fit reproduces every orientation to noise level (load noise 0.003 N)
    for deg, v in res["fit_quality"]["validation"]["70"].items():
        assert v["rel_rms"] < 0.01, deg
    for key, k in k_b.items():
        assert res["bending_stiffness_nmm"][key][0] == pytest.approx(k, rel=0.03)
    assert res["bending_stiffness_mean_nmm"][0] == pytest.approx(np.mean(list(k_b.values())), rel=0.02)
    # release modulus: orientation mean of the true model's slope at release
    L = META["tensile_gauge_length_mm"]
    for pct in ("45", "70"):
        e_rel = FC.green_strain(L * float(pct) / 100, L)
        h = 1e-6
        slopes = [(FL.uniaxial_response([e_rel], d, TRUE, NU)[0][0] - FL.uniaxial_response([e_rel - h], d, TRUE, NU)[0][0]) / h
                  for d in (0.0, 30.0, 45.0, 60.0, 90.0)]
        assert res["release_modulus_mpa"][pct][0] == pytest.approx(np.mean(slopes), rel=0.05), pct
    assert all(c["cycles"] == [2, 3] for c in res["cycles_used"].values())
    assert {"shear.png", "master_curve.png", "tensile_45deg.png"} <= set(os.listdir(out))


def test_shipped_data_calibrates_to_sane_values(tmp_path):
    """validation/data/fabric: every value and standard error finite and positive; the fitted
    orthotropic parameters within 1 % of the seed's Table 4.1 (a fabric of the same kind;
    measured: within 0.6 %) and the held-out 15-75 deg curves reproduced to 1 % RMS
    (measured 0.29-0.41 %), as on docs/validation.md."""
    from shellfem.materials.orthotropic import TABLE_4_1_ORTHOTROPIC
    res = F.calibrate_fabric(DATA, str(tmp_path))
    pairs = list(res["orthotropic"].values()) + list(res["release_modulus_mpa"].values()) \
        + list(res["bending_stiffness_nmm"].values()) + [res["bending_stiffness_mean_nmm"]]
    assert set(res["bending_stiffness_nmm"]) == {"0/front", "0/back", "90/front", "90/back"}
    assert set(res["release_modulus_mpa"]) == {"45", "70"}
    for v, se in pairs:
        assert np.isfinite(v) and v > 0 and np.isfinite(se) and se > 0
    assert json.loads((tmp_path / "parameters.json").read_text())["poisson"][0] == pytest.approx(0.3)
    for k, ref in TABLE_4_1_ORTHOTROPIC.items():
        assert res["orthotropic"][k][0] == pytest.approx(ref, rel=0.01), k
    held_out = {d: v for d, v in res["fit_quality"]["validation"]["70"].items() if d not in ("0", "90")}
    assert sorted(held_out, key=float) == ["15", "30", "45", "60", "75"]
    for deg, v in held_out.items():
        assert v["rel_rms"] < 0.01, deg


# ----------------------------------------------------------------------------- bad input

@pytest.fixture
def good_folder(tmp_path):
    folder, _ = _synthetic_folder(tmp_path, np.random.default_rng(0))
    return folder


@pytest.mark.parametrize("edit, expect", [
    (lambda s: s.replace("load_N", "force_N"), ["tensile_00deg_70pct.csv", "load_N"]),
    (lambda s: s.replace("load_N\n", "load_N,extra\n", 1), ["tensile_00deg_70pct.csv", "extra"]),
    (lambda s: s.replace(",unload,", ",unlaod,", 1), ["tensile_00deg_70pct.csv", "row", "branch", "unlaod"]),
    (lambda s: "\n".join([ln if i != 3 else ln.rsplit(",", 1)[0] + ",abc" for i, ln in enumerate(s.split("\n"))]),
     ["tensile_00deg_70pct.csv", "row 3", "load_N", "abc"]),
    (lambda s: "", ["tensile_00deg_70pct.csv", "empty"]),
])
def test_bad_tensile_file_names_file_row_column(good_folder, tmp_path, edit, expect):
    p = os.path.join(good_folder, "tensile_00deg_70pct.csv")
    with open(p) as f:
        text = f.read()
    with open(p, "w") as f:
        f.write(edit(text))
    with pytest.raises(SelfshapeError) as err:
        F.calibrate_fabric(good_folder, str(tmp_path / "out"))
    msg = str(err.value)
    assert "\n" not in msg and all(x in msg for x in expect), msg
    assert not os.path.exists(tmp_path / "out" / "parameters.json")


def test_bad_meta_and_missing_files(good_folder, tmp_path):
    meta = dict(META)
    del meta["tensile_width_mm"]
    with open(os.path.join(good_folder, "meta.json"), "w") as f:
        json.dump(meta, f)
    with pytest.raises(SelfshapeError, match="tensile_width_mm"):
        F.calibrate_fabric(good_folder, str(tmp_path / "o"))
    with open(os.path.join(good_folder, "meta.json"), "w") as f:
        json.dump(META, f)
    os.remove(os.path.join(good_folder, "tensile_90deg_45pct.csv"))
    with pytest.raises(SelfshapeError, match="tensile_90deg_45pct.csv"):
        F.calibrate_fabric(good_folder, str(tmp_path / "o"))


def test_bad_cantilever_face_and_value(good_folder, tmp_path):
    p = os.path.join(good_folder, "cantilever.csv")
    with open(p) as f:
        text = f.read()
    with open(p, "w") as f:
        f.write(text.replace(",front,", ",top,", 1))
    with pytest.raises(SelfshapeError, match=r"cantilever.csv: row 1, column face_up"):
        F.calibrate_fabric(good_folder, str(tmp_path / "o"))
