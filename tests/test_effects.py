"""The effect catalogue: each effect changes the model the way its docstring says,
checked against the strip model evaluated by hand with the changed inputs."""
import numpy as np
import pytest

from shellfem.strip import strip_curvature
from validation import effects as fx
from validation.strips import MEASURED, REST


def rows_fixture():
    n = 6
    return {"specimen": np.array([f"s{i}" for i in range(n)], dtype=object),
            "side": np.array(["front", "back"] * 3, dtype=object),
            "stretch": np.array([1.2, 1.35, 1.5, 1.35, 1.2, 1.6]),
            "orientation_deg": np.array([0.0, 45.0, 90.0, 30.0, 0.0, 90.0]),
            "plastic_thickness_mm": np.array([0.3, 0.35, 0.4, 0.45, 0.5, 0.3]),
            "fabric_thickness_mm": np.array([0.8, 0.8, 0.6, 1.0, 0.8, 0.7]),
            "width_mm": np.array([5.0, 10.0, 20.0, 10.0, 5.0, 30.0]),
            "length_mm": np.array([30.0, 40.0, 60.0, 40.0, 90.0, 40.0]),
            MEASURED: np.zeros(n),
            REST: np.array([0.01, np.nan, 0.008, 0.006, np.nan, 0.012])}


R = 2000.0


def model(rows, hp=None, hf=None, s=None, ratio=R, rest=0.0, mode="narrow"):
    return strip_curvature(rows["plastic_thickness_mm"] if hp is None else hp,
                           rows["fabric_thickness_mm"] if hf is None else hf,
                           rows["stretch"] if s is None else s, ratio, rest_curvature=rest, mode=mode)


def pred(rows, name, *params):
    e = fx.BY_NAME[name]
    return fx.predict(rows, [e], [R, *params], {name: e.prepare(rows)})


def test_base_model_is_the_engine():
    rows = rows_fixture()
    assert np.allclose(fx.predict(rows, [], [R]), model(rows), rtol=1e-12)
    batch = fx.predict(rows, [], np.array([[R], [2 * R]]))
    assert batch.shape == (2, 6) and np.allclose(batch[1], model(rows, ratio=2 * R))


@pytest.mark.parametrize("name,params,expect", [
    ("plastic_set_constant", (0.004,), lambda r: model(r, rest=0.004)),
    ("plastic_set_thickness", (0.01, -0.05), lambda r: model(r, rest=0.01 - 0.05 * (r["plastic_thickness_mm"] - 0.4))),
    ("thickness_bias", (0.03,), lambda r: model(r, hp=r["plastic_thickness_mm"] + 0.03)),
    ("side_deposition", (0.05,), lambda r: model(r, hp=r["plastic_thickness_mm"] + 0.05 * (r["side"] == "back"))),
    ("side_deposition_factor", (1.2,),
     lambda r: model(r, hp=r["plastic_thickness_mm"] * np.where(r["side"] == "back", 1.2, 1.0))),
    ("side_fabric_stiffness", (1.5,), lambda r: model(r, ratio=np.where(r["side"] == "back", R / 1.5, R))),
    ("stretch_modulus", (3.0,), lambda r: model(r, ratio=R * (r["stretch"] / 1.35) ** -3.0)),
    ("plastic_prestrain", (0.02,), lambda r: model(r, s=r["stretch"] * 0.98)),
    ("orthotropy", (0.3,), lambda r: model(r, ratio=R / (1 + 0.3 * np.cos(np.radians(2 * r["orientation_deg"]))))),
    ("fabric_compression", (0.7,), lambda r: model(r, hf=0.7 * r["fabric_thickness_mm"])),
    ("plastic_seeping", (0.1,), lambda r: model(r, hp=r["plastic_thickness_mm"] + 0.1,
                                                hf=r["fabric_thickness_mm"] - 0.1)),
])
def test_input_effects_change_the_inputs_as_documented(name, params, expect):
    rows = rows_fixture()
    assert np.allclose(pred(rows, name, *params), expect(rows), rtol=1e-12)


def test_neutral_parameters_give_the_base_model():
    rows = rows_fixture()
    base = model(rows)
    neutral = {"plastic_set_constant": (0.0,), "thickness_bias": (0.0,), "side_deposition": (0.0,),
               "side_deposition_factor": (1.0,), "side_fabric_stiffness": (1.0,), "stretch_modulus": (0.0,),
               "plastic_prestrain": (0.0,), "orthotropy": (0.0,), "gravity": (0.0,), "fabric_compression": (1.0,),
               "plastic_seeping": (0.0,), "plastic_set_thickness": (0.0, 0.0)}
    for name, p in neutral.items():
        assert np.allclose(pred(rows, name, *p), base, rtol=1e-12), name
    assert np.allclose(pred(rows, "width_transition", 1e9), base, rtol=1e-9)  # huge Searle scale: narrow


def test_measured_plastic_set_and_its_fallback_law():
    rows = rows_fixture()
    e = fx.BY_NAME["plastic_set_measured"]
    aux = e.prepare(rows)
    m = np.isfinite(rows[REST])
    c1, c0 = np.polyfit(rows["plastic_thickness_mm"][m], rows[REST][m], 1)
    assert aux["fallback_c0"] == pytest.approx(c0) and aux["fallback_c1"] == pytest.approx(c1)
    rest = np.where(m, rows[REST], c0 + c1 * rows["plastic_thickness_mm"])
    assert np.allclose(fx.predict(rows, [e], [R], {e.name: aux}), model(rows, rest=rest), rtol=1e-10)
    no = dict(rows, **{REST: np.full(6, np.nan)})
    ok, why = e.applicable(no)
    assert not ok and "never measured" in why


def test_smoothed_plastic_set_recovers_an_exact_law():
    rows = rows_fixture()
    law = 0.02 - 0.03 * rows["plastic_thickness_mm"] + 0.004 * rows["stretch"]
    rows[REST] = law
    e = fx.BY_NAME["plastic_set_smoothed"]
    aux = e.prepare(rows)
    assert np.allclose(fx.predict(rows, [e], [R], {e.name: aux}), model(rows, rest=law), rtol=1e-8)
    assert aux["parameters"]["rest_curvature_intercept_per_mm"][0] == pytest.approx(0.02, abs=1e-10)


def test_flexural_rigidity_of_a_homogeneous_beam():
    h1, h2 = 0.3, 0.8
    assert fx.flexural_rigidity(h1, h2, 1.0) == pytest.approx((h1 + h2) ** 3 / 12)
    # stiff plastic: rigidity -> R (h1^3/12 + h1 h2^2 ...) dominated by the plastic about its own axis
    assert fx.flexural_rigidity(h1, h2, 1e9) / 1e9 == pytest.approx(h1 ** 3 / 12, rel=1e-6)


def test_gravity_lowers_curvature_by_the_cantilever_sag():
    rows = rows_fixture()
    g = 1e-3
    D = fx.flexural_rigidity(rows["plastic_thickness_mm"], rows["fabric_thickness_mm"], R)
    expect = model(rows) - g * rows["length_mm"] ** 2 / (24 * D)
    assert np.allclose(pred(rows, "gravity", g), expect, rtol=1e-12)


def test_width_transition_limits_and_midpoint():
    rows = rows_fixture()
    kn, kp = model(rows), model(rows, mode="plate")
    assert np.allclose(pred(rows, "width_transition", 1e-6), kp, rtol=1e-9)  # tiny scale: plate
    b = rows["width_mm"] ** 2 * kn / (rows["plastic_thickness_mm"] + rows["fabric_thickness_mm"])
    mid = pred(rows, "width_transition", b[2])
    assert mid[2] == pytest.approx(0.5 * (kn[2] + kp[2]))


def test_applicability_needs_the_covariate_to_vary():
    rows = rows_fixture()
    assert all(e.applicable(rows)[0] for e in fx.CATALOGUE)
    flat = dict(rows, stretch=np.full(6, 1.35), orientation_deg=np.full(6, 90.0), width_mm=np.full(6, 10.0),
                side=np.array(["front"] * 6, dtype=object))
    off = {e.name: e.applicable(flat) for e in fx.CATALOGUE}
    for name in ("stretch_modulus", "plastic_prestrain", "orthotropy", "width_transition", "side_deposition",
                 "side_fabric_stiffness"):
        assert not off[name][0] and off[name][1].startswith("not identifiable"), name
    back = dict(rows, side=np.array(["back"] * 6, dtype=object))
    assert fx.BY_NAME["side_deposition"].applicable(back)[0]  # competes with thickness_bias


def test_parameter_transforms_round_trip():
    eff = [fx.BY_NAME["side_deposition_factor"], fx.BY_NAME["plastic_set_thickness"]]
    nat = np.array([2500.0, 1.3, 0.01, -0.05])
    internal, flags = fx.to_internal(eff, nat)
    assert list(flags) == [True, True, False, False]
    assert np.allclose(fx.natural(eff, internal), nat)
    lo, hi = fx.bounds_internal(eff)
    assert np.all(lo < internal) and np.all(internal < hi)
    assert fx.parameter_names(eff) == ["modulus_ratio", "side_deposition_factor.back_thickness_factor",
                                       "plastic_set_thickness.rest_curvature_per_mm",
                                       "plastic_set_thickness.slope_per_mm2"]


def test_catalogue_is_documented():
    names = [e.name for e in fx.CATALOGUE]
    assert len(names) == len(set(names)) >= 12
    for e in fx.CATALOGUE:
        assert "seed" in (type(e).__doc__ or ""), e.name
        assert len(e.params) == len(e.init) == len(e.bounds)
        for v, (lo, hi) in zip(e.init, e.bounds):
            assert lo <= v <= hi
