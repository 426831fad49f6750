"""Strips CSV reader and the modulus-ratio calibration."""
import json
import os

import numpy as np
import pytest

from shellfem.errors import SelfshapeError
from shellfem.strip import strip_curvature, timoshenko_curvature
from validation import strips
from validation.strips import MEASURED, REST

HEADER = ("specimen,side,stretch,orientation_deg,plastic_thickness_mm,fabric_thickness_mm,width_mm,length_mm,"
          "curvature_per_mm,rest_curvature_per_mm")
S1 = os.path.join(os.path.dirname(__file__), "..", "validation", "data", "strips_S1.csv")


def write(tmp_path, lines, name="s.csv"):
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n")
    return p


def good_lines():
    return [HEADER, "A1,front,1.35,0,0.30,0.80,10,40,0.05,0.01", "A2,Back,1.35,90,0.40,0.80,10,40,0.03,"]


def test_reader_parses_and_allows_empty_rest(tmp_path):
    rows = strips.read_strips(write(tmp_path, good_lines()))
    assert list(rows["side"]) == ["front", "back"]
    assert rows["plastic_thickness_mm"][1] == 0.4 and rows[MEASURED][0] == 0.05
    assert rows[REST][0] == 0.01 and np.isnan(rows[REST][1])
    assert strips.n_rows(rows) == 2


@pytest.mark.parametrize("edit,match", [
    (lambda L: [L[0].replace(",side", ",face")] + L[1:], r"s.csv: missing column\(s\) side"),
    (lambda L: [L[0], L[1].replace("front", "top")], r"s.csv: row 1 \(specimen A1\), column side"),
    (lambda L: [L[0], L[1].replace("0.30", "abc")],
     r"row 1 \(specimen A1\), column plastic_thickness_mm: must be a number"),
    (lambda L: [L[0], L[1].replace("0.30", "-0.3")], r"column plastic_thickness_mm: must be >= 0.001"),
    (lambda L: [L[0], L[1].replace("1.35", "0.9")], r"column stretch: must be >= 1"),
    (lambda L: [L[0], L[1].replace("0.05,", "nan,")], r"column curvature_per_mm: must be finite"),
    (lambda L: [L[0], L[1].replace("0.05,", ",")], r"column curvature_per_mm: empty"),
    (lambda L: [L[0], L[1] + ",7"], r"row 1: 11 fields, header has 10"),
    (lambda L: [L[0]], r"no data rows"),
    (lambda L: [L[0], L[2], L[1].replace("A1", "")], r"row 2, column specimen: empty"),
])
def test_reader_errors_name_file_row_column(tmp_path, edit, match):
    with pytest.raises(SelfshapeError, match=match) as e:
        strips.read_strips(write(tmp_path, edit(good_lines())))
    assert "\n" not in str(e.value)


def test_reader_missing_and_empty_files(tmp_path):
    with pytest.raises(SelfshapeError, match="nope.csv: file not found"):
        strips.read_strips(tmp_path / "nope.csv")
    with pytest.raises(SelfshapeError, match="empty file"):
        strips.read_strips(write(tmp_path, [""]))
    # predict-style files need no measured column
    lines = [",".join(c for c in HEADER.split(",") if c != MEASURED), "B,front,1.35,0,0.3,0.8,10,40,"]
    rows = strips.read_strips(write(tmp_path, lines), require_measured=False)
    assert np.isnan(rows[MEASURED][0])
    with pytest.raises(SelfshapeError, match="missing column"):
        strips.read_strips(write(tmp_path, lines))


def test_timoshenko_closed_forms_agree():
    h1, h2 = np.array([0.2, 0.3, 0.45]), np.array([0.8, 0.6, 1.0])
    for n in (1.0, 50.0, 3200.0):
        assert np.allclose(strips._timoshenko_curvature(h1, h2, 0.01, n), timoshenko_curvature(h1, h2, n, 0.01),
                           rtol=1e-12)


def test_seed_linear_fit_is_exact_on_eq_3_17_data():
    h1 = np.array([0.3, 0.35, 0.4, 0.45])
    s = np.array([1.35, 1.35, 1.5, 1.2])
    kbar = np.array([0.01, 0.008, 0.0, 0.004])
    rows = {"plastic_thickness_mm": h1, "fabric_thickness_mm": np.full(4, 0.8), "stretch": s, REST: kbar,
            MEASURED: 6 * 0.8 * (h1 + 0.8) / (3200.0 * h1 ** 3) * (1 - 1 / s ** 2) + kbar}
    ratio, se = strips.seed_linear_fit(rows)
    assert ratio == pytest.approx(3200.0, rel=1e-12) and se == pytest.approx(0.0, abs=1e-6)


def test_calibration_recovers_the_ratio_with_interval(tmp_path):
    rng = np.random.default_rng(0)
    h = np.repeat([0.25, 0.3, 0.4, 0.5, 0.6], 6)
    s = np.tile([1.25, 1.35, 1.5], 10)
    k = strip_curvature(h, 0.8, s, 1800.0) * (1 + 0.02 * rng.standard_normal(h.size))
    lines = [HEADER] + [f"C{i},front,{s[i]},0,{h[i]},0.8,10,40,{k[i]:.8g}," for i in range(h.size)]
    out = strips.calibrate_strips(write(tmp_path, lines), tmp_path / "cal")
    v, se = out["modulus_ratio"]
    lo, hi = out["confidence_intervals_95"]["modulus_ratio"]
    assert lo < 1800.0 < hi and lo < v < hi
    assert abs(v - 1800.0) < 4 * se
    assert (hi - lo) / (2 * 1.96 * se) == pytest.approx(1.0, rel=0.1)  # near-linear: profile ~ Wald
    on_disk = json.loads((tmp_path / "cal" / "parameters.json").read_text())
    assert on_disk["modulus_ratio"] == [v, se]
    assert len(on_disk["residuals"]["residual_per_mm"]) == h.size
    assert "modulus_ratio_rest_measured" not in on_disk  # rest curvature column empty
    assert (tmp_path / "cal" / "strips_fit.png").stat().st_size > 1000


def test_calibration_on_the_shipped_strips_file(tmp_path):
    """strips_S1.csv calibrates to the modulus ratio the shipped curvature law was simulated
    with (inverse/data/strips_S1_calibration.json): a change in the calibration shows here
    before the law silently goes stale."""
    out = strips.calibrate_strips(S1, tmp_path)
    v, se = out["modulus_ratio"]
    lo, hi = out["confidence_intervals_95"]["modulus_ratio"]
    assert 0 < se < v and lo < v < hi
    shipped = os.path.join(os.path.dirname(__file__), "..", "inverse", "data", "strips_S1_calibration.json")
    with open(shipped) as fh:
        law_calibration = json.load(fh)
    assert [v, se] == pytest.approx(law_calibration["modulus_ratio"], rel=1e-6)   # scipy versions differ at 4e-7
    assert [lo, hi] == pytest.approx(law_calibration["confidence_intervals_95"]["modulus_ratio"], rel=1e-6)
    # the plastic set adds curvature, so fitting it explicitly needs a stiffer plastic
    assert out["modulus_ratio_rest_measured"][0] > v
    res = np.array(out["residuals"]["residual_per_mm"])
    assert np.sqrt(np.mean(res ** 2)) == pytest.approx(out["fit"]["rms_residual_per_mm"])
