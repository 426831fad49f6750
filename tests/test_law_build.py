"""`selfshape law build` (validation.law_build): a law_measurements.csv -> the designer's law table.

Bad measurements (empty, non-numeric, out of range), grids too sparse to invert, missing cells
and non-monotone columns are ONE line on stderr (exit 2) naming the file and, per problem, the
patch id and column or the cell; nothing is written. Replicates are averaged; the output is
checked before the work and loads in inverse.thickness_law.
"""
import csv
import os

import numpy as np
import pytest

from inverse.thickness_law import STRETCH_KEY, load_thickness_law
from selfshape.cli import main
from validation.calibration_prints import LAW_COLUMNS, csv_text

KAPPA = {0.2: 0.40, 0.3: 0.20, 0.4: 0.10}          # decreasing in thickness (as the shipped laws)


def template(path, cells=None, comments=(), **edit):
    """Write a law_measurements.csv: by default a full 3 x 2 grid per side at stretch 1.6 with
    kappa from KAPPA (x 1.1 at the larger spacing). ``edit``: {patch id: {column: text}}."""
    rows = []
    k = 0
    for side in ("front", "back"):
        for t in (0.2, 0.3, 0.4):
            for mu in (3.9, 6.5):
                k += 1
                rows.append(dict(patch=f"LP-{k:03d}", frame=1, side=side, stretch=1.6, thickness_mm=t, spacing_mm=mu,
                                 ribbon_length_mm=15, ribbon_width_mm=1.5, ribbon_gap_mm=7.5, rows=6, motifs=3,
                                 patch_length_mm=67.5, patch_width_mm=6 * mu, x_mm=0, y_mm=0,
                                 kappa_per_mm=KAPPA[t] * (1.1 if mu > 4 else 1.0)))
    if cells is not None:
        rows = [r for r in rows if cells(r)]
    for r in rows:
        r.update(edit.get(r["patch"], {}))
    path.write_text(csv_text(LAW_COLUMNS, rows, comments))
    return path


def build(capsys, src, out, *extra):
    rc = main(["law", "build", str(src), "-o", str(out), *extra])
    so, err = capsys.readouterr()
    return rc, so, err


def one_line_error(rc, err, *needles):
    assert rc == 2 and err.count("\n") == 1 and err.startswith("selfshape law: error: "), err
    for n in needles:
        assert n in err, (n, err)


def test_a_full_grid_builds_a_loadable_law(tmp_path, capsys):
    src = template(tmp_path / "law_measurements.csv", comments=["plastic_young_modulus_mpa = 900"])
    rc, so, err = build(capsys, src, tmp_path / "law.csv")
    assert rc == 0, err
    assert "law at stretch 1.6: 12 rows from 12 patches" in so
    law = load_thickness_law(tmp_path / "law.csv")
    assert law.stretch == 1.6 and law.plastic_young_modulus_mpa == 900.0
    assert any(ln == f"{STRETCH_KEY} = 1.6" for ln in law.provenance)
    assert any("SOURCE: law_measurements.csv (sha256" in ln for ln in law.provenance)
    for side in ("front", "back"):
        t = law.table(side)
        np.testing.assert_allclose(t.kappa[:, 0], [0.40, 0.20, 0.10])
        np.testing.assert_allclose(t.kappa[:, 1], [0.44, 0.22, 0.11])
        assert not t.increasing
    # --plastic-modulus overrides the template's
    rc, _, err = build(capsys, src, tmp_path / "law2.csv", "--plastic-modulus", "1200")
    assert rc == 0 and load_thickness_law(tmp_path / "law2.csv").plastic_young_modulus_mpa == 1200.0


def test_the_plastic_comes_from_the_labs_strip_calibration(tmp_path, capsys):
    """`law build --calibration parameters.json` states the plastic its strips measured (modulus
    ratio x fabric E): with the shipped strips_S1 calibration it is the shipped law's plastic,
    which `design --law` then writes into pattern.toml. Without any source the one output line
    says the law states none; --calibration and --plastic-modulus together, or a file that is no
    calibration, are one-line errors with nothing written."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    cal = os.path.join(root, "inverse", "data", "strips_S1_calibration.json")
    src = template(tmp_path / "m.csv")
    rc, so, err = build(capsys, src, tmp_path / "law.csv", "--calibration", cal)
    assert rc == 0, err
    law = load_thickness_law(tmp_path / "law.csv")
    assert law.plastic_young_modulus_mpa == load_thickness_law().plastic_young_modulus_mpa
    assert f"plastic E {law.plastic_young_modulus_mpa:.6g} MPa" in so
    assert any("plastic: plastic E" in ln and "from strips_S1_calibration.json" in ln for ln in law.provenance)
    rc, so, err = build(capsys, src, tmp_path / "bare.csv")
    assert rc == 0 and "no plastic modulus stated" in so and so.count("\n") == 1
    assert load_thickness_law(tmp_path / "bare.csv").plastic_young_modulus_mpa is None
    one_line_error(*build(capsys, src, tmp_path / "x.csv", "--calibration", cal, "--plastic-modulus", "900")[::2],
                   "--plastic-modulus and --calibration both state the plastic")
    (tmp_path / "p.json").write_text('{"modulus_ratio": "abc"}')
    one_line_error(*build(capsys, src, tmp_path / "x.csv", "--calibration", str(tmp_path / "p.json"))[::2],
                   "p.json: not a `selfshape calibrate strips` parameters.json")
    assert not (tmp_path / "x.csv").exists()


def test_replicates_are_averaged_and_named(tmp_path, capsys):
    src = template(tmp_path / "m.csv")
    text = src.read_text().splitlines()
    extra = next(ln for ln in text if ln.startswith("LP-003,")).replace("LP-003", "LP-099").replace(",0.2,", ",0.3,")
    src.write_text("\n".join(text + [extra]) + "\n")      # LP-003: t 0.3 mu2 3.9 front, kappa 0.2 -> a replicate
    rows = list(csv.DictReader(line for line in src.read_text().splitlines() if not line.startswith("#")))
    assert rows[-1]["kappa_per_mm"] == "0.3"
    rc, _, err = build(capsys, src, tmp_path / "law.csv")
    assert rc == 0, err
    law = load_thickness_law(tmp_path / "law.csv")
    assert law.table("front").kappa[1, 0] == pytest.approx(0.25)
    assert law.table("back").kappa[1, 0] == pytest.approx(0.20)
    assert any("mean of 2 patches (LP-003, LP-099)" in ln for ln in law.provenance)


@pytest.mark.parametrize("edit, needles", [
    ({"LP-004": {"kappa_per_mm": ""}}, ["m.csv: 1 unusable entry: patch LP-004, column kappa_per_mm: empty"]),
    ({"LP-004": {"kappa_per_mm": "0.2x"}}, ["patch LP-004, column kappa_per_mm: must be a number, got '0.2x'"]),
    ({"LP-002": {"kappa_per_mm": "nan"}}, ["patch LP-002, column kappa_per_mm: must be finite"]),
    ({"LP-002": {"kappa_per_mm": "-0.1"}}, ["patch LP-002, column kappa_per_mm: must be >= 0"]),
    ({"LP-002": {"contraction_along": "abc"}}, ["patch LP-002, column contraction_along: must be a number"]),
    ({"LP-002": {"side": "top"}}, ["patch LP-002, column side: must be front or back, got 'top'"]),
    ({"LP-002": {"stretch": "1.3"}}, ["patch LP-002, column stretch: 1.3, but patch LP-001 has 1.6"]),
    ({"LP-002": {"kappa_per_mm": "", "note": "torn"}, "LP-007": {"thickness_mm": "thick"}},
     ["2 unusable entries", "patch LP-002, column kappa_per_mm: empty (torn)",
      "patch LP-007, column thickness_mm: must be a number, got 'thick'", "(units and ranges: docs/"]),
    # the across curvature is a magnitude too (as --simulate writes it): a signed value is refused
    ({"LP-002": {"kappa_across_per_mm": "-0.02"}}, ["patch LP-002, column kappa_across_per_mm: must be >= 0"]),
    # a patch id on two rows is not a replicate: LP-004 (front 0.3 / 6.5) relabelled LP-003
    ({"LP-004": {"patch": "LP-003"}}, ["patch LP-003 (row 4), column patch: the id of row 3 too"]),
])
def test_bad_measurements_name_file_patch_and_column(tmp_path, capsys, edit, needles):
    src = template(tmp_path / "m.csv", **edit)
    rc, _, err = build(capsys, src, tmp_path / "law.csv")
    one_line_error(rc, err, *needles)
    assert not (tmp_path / "law.csv").exists()


def test_grids_that_cannot_be_inverted_are_reported_per_cell(tmp_path, capsys):
    out = tmp_path / "law.csv"
    # one thickness per spacing: nothing to invert
    rc, _, err = build(capsys, template(tmp_path / "m.csv", cells=lambda r: r["thickness_mm"] == 0.3), out)
    one_line_error(rc, err, "side front: 1 thickness(es) x 2 spacing(s), too sparse to invert (column thickness_mm "
                            "has 0.3", "over patches LP-003, LP-004", "side back: 1 thickness(es) x 2 spacing(s)")
    # one spacing only: too sparse
    rc, _, err = build(capsys, template(tmp_path / "m.csv", cells=lambda r: r["spacing_mm"] == 3.9), out)
    one_line_error(rc, err, "m.csv: cannot build a law", "side front: 3 thickness(es) x 1 spacing(s), too sparse",
                   "side back: 3 thickness(es) x 1 spacing(s)", "spacing_mm 3.9 over patches LP-001, LP-003, LP-005")
    # a missing cell
    rc, _, err = build(capsys, template(tmp_path / "m.csv", cells=lambda r: r["patch"] != "LP-010"), out)
    one_line_error(rc, err, "side back, thickness 0.3 mm, spacing 6.5 mm: no patch (missing cell)")
    # no back at all: said, with the way out
    rc, _, err = build(capsys, template(tmp_path / "m.csv", cells=lambda r: r["side"] == "front"), out)
    one_line_error(rc, err, "side back: no patch", "--mirror-back")
    # non-monotone: the cell and the patches are named, nothing is dropped or smoothed
    src = template(tmp_path / "m.csv", **{"LP-006": {"kappa_per_mm": "0.3"}})
    rc, _, err = build(capsys, src, out)
    one_line_error(rc, err, "side front, spacing 6.5 mm: not decreasing in thickness between 0.3 and 0.4 mm "
                            "(kappa 0.22 -> 0.3 1/mm, rises; patches LP-004, LP-006)")
    assert "back" not in err.split("cannot build a law:")[1]
    assert not out.exists()


def test_sub_grid_and_mirror_back_are_the_labs_choice(tmp_path, capsys):
    out = tmp_path / "law.csv"
    src = template(tmp_path / "m.csv", **{"LP-005": {"kappa_per_mm": "0.5"}})       # t 0.4 mu2 3.9 front
    one_line_error(*build(capsys, src, out)[::2], "between 0.3 and 0.4 mm")
    rc, _, err = build(capsys, src, out, "--thickness", "0.2", "0.3")
    assert rc == 0, err
    law = load_thickness_law(out)
    assert list(law.table("front").thickness) == [0.2, 0.3]
    assert any("sub-grid chosen with --thickness" in ln for ln in law.provenance)
    one_line_error(*build(capsys, src, out, "--spacing", "5")[::2], "--spacing 5 mm: no patch has spacing_mm 5")
    front = template(tmp_path / "f.csv", cells=lambda r: r["side"] == "front")
    rc, _, err = build(capsys, front, out, "--mirror-back")
    assert rc == 0, err
    law = load_thickness_law(out)
    np.testing.assert_array_equal(law.table("back").kappa, law.table("front").kappa)
    one_line_error(*build(capsys, src, out, "--mirror-back")[::2], "back patches are given")


def test_output_is_checked_before_the_work(tmp_path, capsys):
    src = template(tmp_path / "m.csv")
    one_line_error(*build(capsys, src, src)[::2], "refusing to overwrite input data")
    one_line_error(*build(capsys, src, tmp_path / "law.txt")[::2], "must be a .csv file")
    (tmp_path / "dir.csv").mkdir()
    one_line_error(*build(capsys, src, tmp_path / "dir.csv")[::2], "is a folder")
    one_line_error(*build(capsys, tmp_path / "absent.csv", tmp_path / "law.csv")[::2], "absent.csv")
    (tmp_path / "bin.csv").write_bytes(b"\x00\x01\xff")
    one_line_error(*build(capsys, tmp_path / "bin.csv", tmp_path / "law.csv")[::2], "bin.csv")
    (tmp_path / "empty.csv").write_text("")
    one_line_error(*build(capsys, tmp_path / "empty.csv", tmp_path / "law.csv")[::2], "empty.csv: no header line")
    (tmp_path / "h.csv").write_text("# only comments\npatch,side\n")
    one_line_error(*build(capsys, tmp_path / "h.csv", tmp_path / "law.csv")[::2], "h.csv: missing column(s) stretch")
    assert not (tmp_path / "law.csv").exists()


def test_a_decimal_comma_row_names_the_patch(tmp_path, capsys):
    src = template(tmp_path / "m.csv")
    text = src.read_text().replace("LP-003,1,front,1.6,0.3,3.9", "LP-003,1,front,1.6,0,3,3.9")
    src.write_text(text)
    rc, _, err = build(capsys, src, tmp_path / "law.csv")
    one_line_error(rc, err, "patch LP-003 (row 3): 21 fields, the header has 20 (a decimal comma?")


def test_replicated_noisy_measurements_build_the_law_they_measure(tmp_path, capsys):
    """The measured analogue of the strips round trip: a law print with 3 replicates per cell,
    kappa filled from the shipped s = 1.3 law with 2 % seeded noise: the built law is the shipped
    one within 3 noise standard errors (2 % / sqrt(3)) at every cell."""
    from inverse.thickness_law import curvature, load_thickness_law, law_for_stretch
    out = tmp_path / "print"
    assert main(["calibration-print", "law", "-o", str(out), "--stretch", "1.3", "--thickness", "0.2", "0.3", "0.4",
                 "--spacing", "3.9", "6.5", "--repetitions", "3"]) == 0
    capsys.readouterr()
    path = out / "law_measurements.csv"
    lines = path.read_text().splitlines()
    shipped = law_for_stretch(1.3)
    rng = np.random.default_rng(5)
    head = [i for i, ln in enumerate(lines) if ln.startswith("patch,")][0]
    cols = lines[head].split(",")
    j = {c: cols.index(c) for c in ("side", "thickness_mm", "spacing_mm", "kappa_per_mm")}
    for i in range(head + 1, len(lines)):
        f = lines[i].split(",")
        k = float(curvature(shipped, float(f[j["thickness_mm"]]), float(f[j["spacing_mm"]]), f[j["side"]]))
        f[j["kappa_per_mm"]] = f"{k * (1 + 0.02 * rng.standard_normal()):.6g}"
        lines[i] = ",".join(f)
    path.write_text("\n".join(lines) + "\n")
    rc, so, err = build(capsys, path, tmp_path / "law.csv")
    assert rc == 0, err
    assert "12 rows from 36 patches" in so
    law = load_thickness_law(tmp_path / "law.csv")
    for side in ("front", "back"):
        a, b = law.table(side), shipped.table(side)
        rel = a.kappa / b.kappa - 1
        assert np.all(np.abs(rel) < 3 * 0.02 / np.sqrt(3)) and np.any(rel != 0)
    assert sum("mean of 3 patches" in ln for ln in law.provenance) == 12
