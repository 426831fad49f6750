"""The contract of calibrate / validate / predict under bad or undetermined input (issue 19),
through the CLI entry point: exit status 2, a single stderr line naming the file and the
key / line / row, no output written, never a traceback, an "internal error" or a silent
wrong answer; honest standard errors (none without residual degrees of freedom, none from a
fit on a search bound); every number written finite. Generated and property-based."""
import json
import math
import os
import subprocess
import sys

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fabric_folders as G
from selfshape.cli import main

REPO = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
S1 = os.path.join(REPO, "validation", "data", "strips_S1.csv")
HEADER = ("specimen,side,stretch,orientation_deg,plastic_thickness_mm,fabric_thickness_mm,width_mm,length_mm,"
          "curvature_per_mm,rest_curvature_per_mm")
ROW = "A{i},front,1.35,0,{h},0.80,10,40,{k},"
SETTINGS = settings(max_examples=12, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def run(argv, capsys):
    """(exit status, stderr) of selfshape main(argv)."""
    rc = main([str(a) for a in argv])
    return rc, capsys.readouterr().err


def assert_bad_input(rc, err, *names):
    """exit 2, exactly one stderr line, no internal error, naming every one of names."""
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "internal error" not in err and "Traceback" not in err
    for n in names:
        assert str(n) in lines[0], (n, lines[0])


def strips_file(path, rows):
    path.write_text("\n".join([HEADER] + list(rows)) + "\n")
    return path


def strict_json(path):
    """Parse a JSON file refusing NaN / Infinity (not JSON)."""
    def bad(c):
        raise AssertionError(f"{path}: non-finite {c}")
    return json.loads(open(path).read(), parse_constant=bad)


# ----------------------------------------------------------------------------- honest errors

def test_one_strips_row_has_no_standard_error(tmp_path, capsys):
    p = strips_file(tmp_path / "one.csv", [ROW.format(i=1, h=0.3, k=0.05)])
    rc, err = run(["calibrate", "strips", p, "-o", tmp_path / "o"], capsys)
    assert_bad_input(rc, err, "one.csv", "not identifiable", "modulus_ratio")
    assert not (tmp_path / "o").exists()


@SETTINGS
@given(n=st.integers(2, 12), h=st.sampled_from([0.25, 0.3, 0.45]), k=st.floats(0.01, 0.08))
def test_identical_rows_of_one_specimen_are_not_replicates(tmp_path, capsys, n, h, k):
    """n identical rows (one specimen measured n times, the same value each time): one strip,
    no residual degrees of freedom; calibrate and validate both refuse with the file named."""
    row = f"S,front,1.35,0,{h},0.80,10,40,{k:.5f},"
    p = strips_file(tmp_path / "same.csv", [row] * n)
    rc, err = run(["calibrate", "strips", p, "-o", tmp_path / "o"], capsys)
    assert_bad_input(rc, err, "same.csv", "not identifiable")
    rc, err = run(["validate", p, "-o", tmp_path / "v"], capsys)
    assert_bad_input(rc, err, "same.csv", "specimen")
    assert not (tmp_path / "o").exists() and not (tmp_path / "v").exists()


@SETTINGS
@given(ks=st.lists(st.floats(-0.1, 0.0), min_size=3, max_size=12))
def test_curvatures_at_or_below_zero_do_not_return_the_search_bound(tmp_path, capsys, ks):
    """Curvatures <= 0 (all-zero included): the bilayer reaches them only as the modulus ratio
    runs to a bound of its search range; that is not an estimate."""
    p = strips_file(tmp_path / "flat.csv", [ROW.format(i=i, h=0.3 + 0.01 * i, k=f"{k:.6f}") for i, k in enumerate(ks)])
    rc, err = run(["calibrate", "strips", p, "-o", tmp_path / "o"], capsys)
    assert_bad_input(rc, err, "flat.csv", "not identifiable", "bound")
    assert not (tmp_path / "o").exists()


def test_no_misfit_is_not_identifiable(tmp_path, capsys):
    p = strips_file(tmp_path / "s1.csv", [f"A{i},front,1,0,0.3,0.8,10,40,0.05," for i in range(3)])
    rc, err = run(["calibrate", "strips", p, "-o", tmp_path / "o"], capsys)
    assert_bad_input(rc, err, "s1.csv", "not identifiable")


def test_three_distinct_rows_give_an_honest_interval(tmp_path, capsys):
    """Three strips from the shipped file: a ratio with a positive SE and an interval that
    contains it, every number finite, the interval as wide as its two residual degrees of
    freedom make it."""
    lines = open(S1).read().splitlines()
    p = tmp_path / "three.csv"
    p.write_text("\n".join(lines[:1] + lines[1:4]) + "\n")
    assert main(["calibrate", "strips", str(p), "-o", str(tmp_path / "o3")]) == 0
    assert main(["calibrate", "strips", S1, "-o", str(tmp_path / "all")]) == 0
    three, every = strict_json(tmp_path / "o3" / "parameters.json"), strict_json(tmp_path / "all" / "parameters.json")
    v, se = three["modulus_ratio"]
    lo, hi = three["confidence_intervals_95"]["modulus_ratio"]
    assert se > 0 and lo < v < hi
    # the interval uses the 2 residual degrees of freedom: half-width ~ t(0.975, 2) = 4.30 SE
    # (in log ratio), against t(0.975, 79) = 1.99 SE with all 80 strips
    from scipy import stats
    for res, dof in ((three, 2), (every, 79)):
        (v, se), (lo, hi) = res["modulus_ratio"], res["confidence_intervals_95"]["modulus_ratio"]
        half = 0.5 * (math.log(hi) - math.log(lo)) / (se / v)
        assert half == pytest.approx(stats.t.ppf(0.975, dof), rel=0.1), dof
    assert three["fit"]["n_specimens"] == 3


# ----------------------------------------------------------------------------- readers

@pytest.mark.parametrize("col, value", [
    ("stretch", "1e300"), ("stretch", "0.5"), ("plastic_thickness_mm", "1e-300"), ("plastic_thickness_mm", "1e300"),
    ("fabric_thickness_mm", "0"), ("width_mm", "-3"), ("length_mm", "inf"), ("curvature_per_mm", "1e300"),
    ("curvature_per_mm", "nan"), ("rest_curvature_per_mm", "-1e9"), ("orientation_deg", "1e6"),
])
def test_strips_values_outside_physical_ranges(tmp_path, capsys, col, value):
    cols = HEADER.split(",")
    good = "A2,front,1.35,0,0.30,0.80,10,40,0.05,0.01".split(",")
    bad = list(good)
    bad[cols.index(col)] = value
    p = strips_file(tmp_path / "r.csv", [",".join(good).replace("A2", "A1"), ",".join(bad)])
    for argv in (["calibrate", "strips", p, "-o", tmp_path / "o"], ["validate", p, "-o", tmp_path / "v"]):
        rc, err = run(argv, capsys)
        assert_bad_input(rc, err, "r.csv", "row 2", col)


def test_duplicate_columns_and_too_many_rows(tmp_path, capsys):
    """A header naming a column twice is ambiguous (which curvature?): the error names it. More
    rows than a lab's strip set (validation.strips.MAX_ROWS) are refused before any fit:
    100,000 rows ran out of memory in the calibration (issue 19)."""
    from validation.strips import MAX_ROWS
    p = tmp_path / "dup.csv"
    p.write_text(HEADER + ",curvature_per_mm\n" + ROW.format(i=1, h=0.3, k=0.05) + ",0.06\n")
    rc, err = run(["calibrate", "strips", p, "-o", tmp_path / "o"], capsys)
    assert_bad_input(rc, err, "dup.csv", "duplicate", "'curvature_per_mm'")
    many = strips_file(tmp_path / "many.csv", (ROW.format(i=i, h=0.3, k=0.05) for i in range(MAX_ROWS + 1)))
    for argv in (["calibrate", "strips", many, "-o", tmp_path / "o"], ["validate", many, "-o", tmp_path / "v"],
                 ["predict", os.path.join(REPO, "tests", "data", "model_S1.json"), many, "-o", tmp_path / "p.csv"]):
        rc, err = run(argv, capsys)
        assert_bad_input(rc, err, "many.csv", f"{MAX_ROWS + 1} data rows")
    assert not {"o", "v", "p.csv"} & set(os.listdir(tmp_path))


def test_a_fabric_test_file_with_too_many_rows(tmp_path, capsys):
    """A tensile file of more rows than a test logs (fabric_files.MAX_TABLE_ROWS) is refused
    before the fits, which took minutes on 1.9 million rows (issue 19)."""
    from validation.fabric_files import MAX_TABLE_ROWS
    folder = G.write_folder(G.random_spec(14), tmp_path / "fab")
    t = os.path.join(folder, "tensile_00deg_80pct.csv")
    rows = open(t).read().splitlines()
    with open(t, "w") as f:
        f.write("\n".join(rows + rows[1:] * (MAX_TABLE_ROWS // (len(rows) - 1) + 1)) + "\n")
    rc, err = run(["calibrate", "fabric", folder, "-o", tmp_path / "o"], capsys)
    assert_bad_input(rc, err, "tensile_00deg_80pct.csv", "data rows, more than the 200,000")
    assert not os.path.exists(tmp_path / "o")


def test_csv_field_over_the_csv_limit(tmp_path, capsys):
    import csv
    big = "x" * (csv.field_size_limit() + 10)
    p = strips_file(tmp_path / "huge.csv", [ROW.format(i=1, h=0.3, k=0.05), f'"{big}",front,1.35,0,0.3,0.8,10,40,0.05,'])
    rc, err = run(["calibrate", "strips", p, "-o", tmp_path / "o"], capsys)
    assert_bad_input(rc, err, "huge.csv", "line 3", "limit")
    assert len(err) < 400
    folder = G.write_folder(G.random_spec(14), tmp_path / "fab")
    t = os.path.join(folder, "tensile_00deg_80pct.csv")
    with open(t, "a") as f:
        f.write(f'1,2,load,"{big}",3\n')
    rc, err = run(["calibrate", "fabric", folder, "-o", tmp_path / "of"], capsys)
    assert_bad_input(rc, err, "tensile_00deg_80pct.csv", "line", "limit")


@pytest.mark.parametrize("junk", [b"\xff\xfe\x00\x01binary", b"fabric_thickness_mm\x89PNG\r\n\x1a\n\x00\x00",
                                  b'{"fabric_thickness_mm": 0.8,\n "x": "\xe9"}'])
def test_binary_meta_json(tmp_path, capsys, junk):
    folder = G.write_folder(G.random_spec(14), tmp_path / "fab")
    with open(os.path.join(folder, "meta.json"), "wb") as f:
        f.write(junk)
    rc, err = run(["calibrate", "fabric", folder, "-o", tmp_path / "o"], capsys)
    assert_bad_input(rc, err, "meta.json", "line")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("meta, key", [
    ({"fabric_thickness_mm": 1e300}, "fabric_thickness_mm"), ({"tensile_width_mm": "20"}, "tensile_width_mm"),
    ({"shear_sample_side_mm": True}, "shear_sample_side_mm"), ({"poisson": 1.5}, "poisson"),
])
def test_malformed_meta_json_fields(tmp_path, capsys, meta, key):
    folder = G.write_folder(G.random_spec(14), tmp_path / "fab")
    m = json.load(open(os.path.join(folder, "meta.json")))
    m.update(meta)
    json.dump(m, open(os.path.join(folder, "meta.json"), "w"))
    rc, err = run(["calibrate", "fabric", folder, "-o", tmp_path / "o"], capsys)
    assert_bad_input(rc, err, "meta.json", key)


@pytest.mark.parametrize("fname, col, value", [
    ("tensile_00deg_80pct.csv", "extension_mm", "1e300"), ("tensile_90deg_80pct.csv", "load_N", "-1e300"),
    ("shear_00deg.csv", "lateral_displacement_mm", "1e9"), ("cantilever.csv", "free_length_mm", "1e300"),
    ("cantilever.csv", "areal_weight_N_per_mm2", "5"), ("cantilever.csv", "height_over_width", "1e300"),
])
def test_fabric_values_outside_physical_ranges(tmp_path, capsys, fname, col, value):
    folder = G.write_folder(G.random_spec(14), tmp_path / "fab")
    path = os.path.join(folder, fname)
    lines = open(path).read().splitlines()
    cells = lines[3].split(",")
    cells[lines[0].split(",").index(col)] = value
    lines[3] = ",".join(cells)
    open(path, "w").write("\n".join(lines) + "\n")
    rc, err = run(["calibrate", "fabric", folder, "-o", tmp_path / "o"], capsys)
    assert_bad_input(rc, err, fname, "row 3", col)
    assert not (tmp_path / "o").exists()


def test_binary_strips_file(tmp_path, capsys):
    p = tmp_path / "bin.csv"
    p.write_bytes((HEADER + "\n").encode() + b"A,front,1.35,0,0.3,0.8,10,40,0.05,\n\xff\xd8\xff\xe0JFIF\x00\n")
    rc, err = run(["calibrate", "strips", p, "-o", tmp_path / "o"], capsys)
    assert_bad_input(rc, err, "bin.csv", "line 3")


# ----------------------------------------------------------------------------- model.json and predict

@pytest.fixture(scope="module")
def fitted_model(tmp_path_factory):
    """model.json of the loop on the shipped strips (validate once for the module)."""
    d = tmp_path_factory.mktemp("loop")
    assert main(["validate", S1, "-o", str(d / "loop")]) == 0
    m = strict_json(d / "loop" / "model.json")
    return m, d


def _edits(m):
    """(name, edited model dict, key the error must name) for malformed model.json fields."""
    out = []
    for k in ("format", "effects", "theta"):
        e = dict(m)
        del e[k]
        out.append((f"missing {k}", e, k))
    n = len(m["theta"])
    for name, theta in (("nan", [float("nan")] * n), ("inf", [float("inf")] + m["theta"][1:]),
                        ("string", ["1200"] + m["theta"][1:]), ("bool", [True] + m["theta"][1:]),
                        ("short", m["theta"][:-1]), ("negative ratio", [-5.0] + m["theta"][1:]),
                        ("huge ratio", [1e300] + m["theta"][1:])):
        out.append((name, dict(m, theta=theta), "theta"))
    out.append(("effects not a list", dict(m, effects="side_deposition"), "effects"))
    out.append(("unknown effect", dict(m, effects=[{"name": "magic"}] + m["effects"][1:]), "effects[0]"))
    out.append(("effect without name", dict(m, effects=[{}] + m["effects"][1:]), "effects[0]"))
    out.append(("aux not an object", dict(m, aux=[1, 2]), "aux"))
    out.append(("aux emptied", dict(m, aux={k: {} for k in m["aux"]}), "aux"))
    aux = json.loads(json.dumps(m["aux"]))
    for v in aux.values():          # the first number list in the auxiliary data gets a NaN
        lists = [x for x in v.values() if isinstance(x, list) and x and isinstance(x[0], float)]
        if lists:
            lists[0][0] = float("nan")
            break
    out.append(("aux nan", dict(m, aux=aux), "aux"))
    out.append(("measured_column", dict(m, measured_column=["x"]), "measured_column"))
    out.append(("not an object", [1, 2, 3], "JSON object"))
    # keys predict used to ignore, so a model fitted for something else or edited predicted
    # as if it said the defaults (issue 19)
    out.append(("other mode", dict(m, mode="plate"), "'mode'"))
    out.append(("other base model", dict(m, model="os.system"), "'model'"))
    out.append(("other column", dict(m, measured_column="specimen"), "'measured_column'"))
    out.append(("other reference stretch", dict(m, reference_stretch=1.6), "'reference_stretch'"))
    out.append(("names disagree", dict(m, parameter_names=list(reversed(m["parameter_names"]))), "parameter_names"))
    out.append(("standard errors short", dict(m, standard_errors=m["standard_errors"][:-1]), "standard_errors"))
    out.append(("standard error negative", dict(m, standard_errors=[-1.0] * len(m["theta"])), "standard_errors[0]"))
    out.append(("unknown key", dict(m, thetta=m["theta"]), "unknown key 'thetta'"))
    named = [i for i, e in enumerate(m["effects"]) if e.get("parameters")]
    if named:
        eff = json.loads(json.dumps(m["effects"]))
        q = next(iter(eff[named[0]]["parameters"]))
        eff[named[0]]["parameters"][q] *= 2.0
        out.append(("effect parameter disagrees with theta", dict(m, effects=eff), f"effects[{named[0]}].parameters"))
    return out


def test_malformed_model_json_never_predicts(fitted_model, tmp_path, capsys):
    m, _ = fitted_model
    assert any(v for v in m["aux"].values()), "the shipped loop should leave auxiliary data to corrupt"
    for name, edited, key in _edits(m):
        p = tmp_path / "model.json"
        p.write_text(json.dumps(edited))
        out = tmp_path / f"pred_{name.replace(' ', '_')}.csv"
        rc, err = run(["predict", p, S1, "-o", out], capsys)
        assert_bad_input(rc, err, "model.json", key)
        assert not out.exists(), name


@SETTINGS
@given(data=st.data())
def test_model_json_with_any_non_finite_or_wrong_typed_parameter(fitted_model, tmp_path, capsys, data):
    m, _ = fitted_model
    i = data.draw(st.integers(0, len(m["theta"]) - 1))
    v = data.draw(st.one_of(st.sampled_from([float("nan"), float("inf"), -float("inf")]), st.text(max_size=5),
                            st.none(), st.booleans(), st.lists(st.floats(), max_size=2)))
    theta = list(m["theta"])
    theta[i] = v
    p = tmp_path / "model.json"
    p.write_text(json.dumps(dict(m, theta=theta)))
    rc, err = run(["predict", p, S1, "-o", tmp_path / "p.csv"], capsys)
    assert_bad_input(rc, err, "model.json", f"theta[{i}]")


def test_a_number_too_long_to_read(tmp_path, capsys):
    """A 5,000-digit integer parses as JSON but int() refuses it: a raw ValueError, exit 3 (issue 19)."""
    p = tmp_path / "model.json"
    p.write_text('{"format": "selfshape-strip-model/1", "theta": [1' + "0" * 5000 + "]}")
    rc, err = run(["predict", p, S1, "-o", tmp_path / "p.csv"], capsys)
    assert_bad_input(rc, err, "model.json", "too long")


def test_binary_model_json(tmp_path, capsys):
    p = tmp_path / "model.json"
    p.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR")
    rc, err = run(["predict", p, S1, "-o", tmp_path / "p.csv"], capsys)
    assert_bad_input(rc, err, "model.json", "line 1", "UTF-8")


def test_output_equal_to_an_input_is_refused(fitted_model, tmp_path, capsys):
    m, d = fitted_model
    model = d / "loop" / "model.json"
    data = tmp_path / "data.csv"
    data.write_text(open(S1).read())
    before = (data.read_bytes(), model.read_bytes())
    for argv, name in ((["predict", model, data, "-o", data], "data.csv"),
                       (["predict", model, data, "-o", model], "model.json"),
                       (["calibrate", "strips", data, "-o", data], "data.csv"),
                       (["validate", data, "-o", data], "data.csv")):
        rc, err = run(argv, capsys)
        assert_bad_input(rc, err, name, "-o")
    assert (data.read_bytes(), model.read_bytes()) == before
    folder = G.write_folder(G.random_spec(14), tmp_path / "fab")
    rc, err = run(["calibrate", "fabric", folder, "-o", folder], capsys)
    assert_bad_input(rc, err, "fab", "-o")
    assert not os.path.exists(os.path.join(folder, "parameters.json"))


def test_predictions_and_parameters_written_are_finite(fitted_model, tmp_path, capsys):
    m, d = fitted_model
    out = tmp_path / "pred.csv"
    assert main(["predict", str(d / "loop" / "model.json"), S1, "-o", str(out)]) == 0
    col = open(out).read().splitlines()
    idx = col[0].split(",").index("curvature_per_mm_predicted")
    assert all(math.isfinite(float(r.split(",")[idx])) for r in col[1:])
    strict_json(d / "loop" / "report.json")


# ----------------------------------------------------------------------------- one line, really

def test_one_line_on_stderr_from_a_fresh_process(tmp_path):
    """The CLI as a user runs it: warnings would print before the error line."""
    p = strips_file(tmp_path / "zero.csv", [ROW.format(i=i, h=0.3 + 0.02 * i, k=0) for i in range(5)])
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""), MPLBACKEND="Agg")
    r = subprocess.run([sys.executable, "-m", "selfshape.cli", "calibrate", "strips", str(p), "-o", str(tmp_path / "o")],
                       capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 2, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "zero.csv" in r.stderr, r.stderr
