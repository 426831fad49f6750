"""The output side of the CLI contract (issue 19), over every verb.

Bad output paths (a file where a folder is asked, a folder where a file is asked, /dev/null,
an empty path, a path under a file, an unwritable folder, a symbolic link at an output, an
input as the output) exit 2 with exactly one stderr line naming the path, before any work,
and leave every file as it was. A rerun removes the verb's own stale outputs (never other
files), writes its summary last and leaves nothing behind when interrupted. No written
number is NaN or infinite. Usage errors are one line. The writer itself
(shellfem.outfiles) is checked property-based with hypothesis.
"""
import json
import math
import os
import shutil
import stat
import subprocess
import sys
import tempfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from selfshape.cli import main
from shellfem import outfiles
from shellfem.errors import SelfshapeError
from shellfem.outfiles import NonFiniteOutput, OutputDir, check_finite_arrays, write_json

ROOT = os.path.join(os.path.dirname(__file__), "..")
EXAMPLE = os.path.join(ROOT, "examples", "strip_narrow.toml")
STRIPS = os.path.join(ROOT, "validation", "data", "strips_S1.csv")
FABRIC = os.path.join(ROOT, "validation", "data", "fabric")
FAST = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ----------------------------------------------------------------------------- inputs
def _write_obj(path, V, F):
    with open(path, "w") as f:
        f.writelines(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in V)
        f.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F)
    return str(path)


def _strips_head(path, n_rows=12):
    with open(STRIPS) as f:
        lines = f.readlines()[: n_rows + 1]
    with open(path, "w") as f:
        f.writelines(lines)
    return str(path)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """Small inputs of every verb, and a model.json from one (short) validate run."""
    from geometry.target import cylinder_patch
    d = tmp_path_factory.mktemp("inputs")
    pattern = d / "strip.toml"
    shutil.copy(EXAMPLE, pattern)
    V, F = cylinder_patch(n_arc=16, n_len=12)
    csv = _strips_head(d / "strips.csv")
    v = d / "validated"
    assert main(["validate", csv, "-o", str(v)]) == 0
    return dict(pattern=str(pattern), target=_write_obj(d / "cyl.obj", V, F), csv=csv,
                model=str(v / "model.json"), validated=str(v))


#: verb -> (argv with OUT for the output, "dir" or "file", its summary, every output name)
VERBS = {
    "mesh": (["mesh", "{pattern}", "-o", "OUT", "--size", "4"], "file", None, None),
    "export": (["export", "{pattern}", "-o", "OUT"], "file", None, None),
    "simulate": (["simulate", "{pattern}", "-o", "OUT", "--size", "3", "--no-png"], "dir", "summary.json",
                 ("deployed.vtu", "deployed.obj", "deployed.stl", "deployed.ply", "pattern.dxf", "pattern.svg",
                  "deployed.png", "index.html", "summary.json")),
    "design": (["design", "{target}", "-o", "OUT"], "dir", "report.json",
               ("report.json", "pattern.toml", "flat.vtu", "front.gcode", "back.gcode", "pattern.png",
                "pattern.dxf", "pattern.svg", "deployed.vtu", "deployed.obj", "deployed.stl", "deployed.ply",
                "verify.png", "index.html")),
    "calibrate strips": (["calibrate", "strips", "{csv}", "-o", "OUT"], "dir", "parameters.json",
                         ("strips_fit.png", "parameters.json")),
    "calibrate fabric": (["calibrate", "fabric", FABRIC, "-o", "OUT"], "dir", "parameters.json",
                         ("parameters.json", "shear.png", "master_curve.png", "tensile_0deg.png",
                          "tensile_45deg.png")),
    "validate": (["validate", "{csv}", "-o", "OUT"], "dir", "report.json",
                 ("residuals_before.png", "residuals_after.png", "model.json", "report.json")),
    "predict": (["predict", "{model}", "{csv}", "-o", "OUT"], "file", None, None),
}


# where each verb's work starts (patched to raise): the folder's stale outputs must be gone
# by then, and nothing of the run left after it
WORK = {"simulate": ("forward.simulate", "simulate"), "design": ("inverse.design", "design"),
        "calibrate strips": ("validation.strips", "fit_modulus_ratio"),
        "calibrate fabric": ("validation.fabric", "_load_tensile"), "validate": ("validation.loop", "validate")}


def argv_of(verb, inputs, out):
    return [out if a == "OUT" else a.format(**inputs) for a in VERBS[verb][0]]


def run(argv, capsys):
    """(exit status, stdout, stderr lines) of an in-process `selfshape` call."""
    rc = main(argv)
    cap = capsys.readouterr()
    return rc, cap.out, cap.err.splitlines()


def snapshot(root):
    """Every entry under root: relative path -> link target, "<dir>", or file bytes."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for n in dirnames + filenames:
            p = os.path.join(dirpath, n)
            rel = os.path.relpath(p, root)
            if os.path.islink(p):
                out[rel] = "-> " + os.readlink(p)
            elif os.path.isdir(p):
                out[rel] = "<dir>"
            else:
                with open(p, "rb") as f:
                    out[rel] = f.read()
    return out


def assert_refused(rc, err, names):
    """Exit 2 with exactly one stderr line, of this verb's form, naming ``names``."""
    assert rc == 2, err
    assert len(err) == 1, err
    assert err[0].startswith("selfshape ") and ": error: " in err[0]
    assert "internal error" not in err[0] and "Traceback" not in err[0]
    assert names in err[0], (names, err[0])


# ----------------------------------------------------------------------------- bad output paths
def _bad_cases(verb, base, inputs):
    """(the -o value, the text the error line must name) for every bad output kind of ``verb``;
    files planted under base as each case needs. A folder verb also gets a symbolic link, a
    folder and an input file at one of its output names inside an existing folder."""
    kind, names = VERBS[verb][1], VERBS[verb][3]
    sfx = {"mesh": ".msh", "predict": ".csv", "export": ".dxf"}.get(verb, "")
    victim = base / "victim.txt"
    victim.write_text("precious")
    (base / "afile").write_text("a file")
    cases = [("/dev/null", "/dev/null"), ("", "empty"), (str(base / "afile" / ("out" + sfx)), "afile"),
             ("/proc/selfshape-contract/out" + sfx, "/proc")]
    link = base / ("link" + sfx)
    link.symlink_to(victim)
    cases.append((str(link), str(link)))
    dangling = base / ("gone" + sfx)
    dangling.symlink_to(base / "nowhere")
    cases.append((str(dangling), str(dangling)))
    long = str(base / ("x" * 300 + sfx))                # longer than a file name may be
    cases.append((long, long))
    cases.append((str(base / "new" / ("y" * 300) / ("out" + sfx)), "y" * 300))
    if kind == "dir":
        cases.append((str(base / "afile"), str(base / "afile")))
        summary = VERBS[verb][2] if verb != "calibrate fabric" else "tensile_45deg.png"   # a pattern-named plot
        planted = base / "with_link"
        planted.mkdir()
        (planted / summary).symlink_to(victim)
        cases.append((str(planted), str(planted / summary)))
        sub = base / "with_dir"
        (sub / names[0]).mkdir(parents=True)
        cases.append((str(sub), str(sub / names[0])))
    else:
        (base / ("adir" + sfx)).mkdir()
        cases.append((str(base / ("adir" + sfx)), str(base / ("adir" + sfx))))
    return cases


def _same_as_input(verb, base, inputs):
    """(inputs with one of them moved to an output path, the -o value, the path named), or None
    where no input can sit at an output path (calibrate fabric reads a folder of *.csv and
    meta.json, names it never writes)."""
    import meshio
    from geometry.target import cylinder_patch
    out = base / "same"
    out.mkdir()
    moved = dict(inputs)
    if verb in ("mesh", "export"):
        p = base / ("pattern.msh" if verb == "mesh" else "pattern.dxf")     # a TOML pattern whatever its suffix
        shutil.copy(inputs["pattern"], p)
        moved["pattern"] = str(p)
        return moved, str(p), str(p)
    if verb == "predict":
        return moved, inputs["csv"], inputs["csv"]
    if verb == "calibrate fabric":
        return None
    target = {"simulate": "summary.json", "design": "flat.vtu", "calibrate strips": "parameters.json",
              "validate": "report.json"}[verb]
    p = out / target
    if verb == "simulate":
        shutil.copy(inputs["pattern"], p)
        moved["pattern"] = str(p)
    elif verb == "design":
        V, F = cylinder_patch(n_arc=16, n_len=12)
        meshio.write(p, meshio.Mesh(V, [("triangle", F)]), file_format="vtu")
        moved["target"] = str(p)
    else:
        shutil.copy(inputs["csv"], p)
        moved["csv"] = str(p)
    return moved, str(out), str(p)


@pytest.mark.parametrize("verb", sorted(VERBS))
def test_bad_output_paths_are_refused_before_the_work(verb, inputs, tmp_path, capsys, monkeypatch):
    """Every bad output kind: exit 2, one line naming it, and every file as it was (the
    victim behind a planted link intact, no folder created, nothing written); the verb's work
    never starts (it is replaced by a failure: exit 3 if it ran)."""
    import importlib
    mod, fn = {**WORK, "mesh": ("geometry.meshing", "_mesh_model"), "export": ("geometry.cad", "pattern_drawing"),
               "predict": ("validation.loop", "predict_rows")}[verb]

    def work(*a, **k):
        raise AssertionError("the work started before the output was checked")
    monkeypatch.setattr(importlib.import_module(mod), fn, work)
    cases = _bad_cases(verb, tmp_path, inputs)
    before = snapshot(tmp_path)
    for out, named in cases:
        rc, _, err = run(argv_of(verb, inputs, out), capsys)
        assert_refused(rc, err, named)
        assert snapshot(tmp_path) == before, out
    same = _same_as_input(verb, tmp_path, inputs)
    if same is not None:
        moved, out, named = same
        before = snapshot(tmp_path)
        rc, _, err = run(argv_of(verb, moved, out), capsys)
        assert_refused(rc, err, named)
        assert "input" in err[0]
        assert snapshot(tmp_path) == before


def test_read_only_folder_is_refused(inputs, tmp_path, capsys):
    """A folder without write permission (root ignores permissions: then skipped; the /proc
    case above covers an unwritable folder for root too)."""
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(stat.S_IRUSR | stat.S_IXUSR)
    try:
        try:
            (ro / "probe").write_text("x")
        except OSError:
            pass
        else:
            pytest.skip("this user writes into a read-only folder (root)")
        for verb in sorted(VERBS):
            out = str(ro / {"mesh": "o.msh", "predict": "o.csv", "export": "o.dxf"}.get(verb, "o"))
            rc, _, err = run(argv_of(verb, inputs, out), capsys)
            assert_refused(rc, err, out)
            assert os.listdir(ro) == []
    finally:
        ro.chmod(stat.S_IRWXU)


# ----------------------------------------------------------------------------- reruns, order, interrupts
def _replace_order(monkeypatch):
    """Record the final names of atomic writes in order (os.replace is the commit of each)."""
    order = []
    real = os.replace

    def replace(src, dst, *a, **k):
        real(src, dst, *a, **k)
        if "__pycache__" not in os.fspath(dst):      # numba's kernel cache, written on a first run
            order.append(os.path.basename(os.fspath(dst)))
    monkeypatch.setattr(outfiles.os, "replace", replace)
    return order


def _no_temp_files(folder):
    return [n for n in os.listdir(folder) if n.startswith(".") or "partial" in n or n.endswith(".tmp")]


def test_simulate_rerun_clears_its_stale_outputs_and_writes_the_summary_last(inputs, tmp_path, capsys,
                                                                            monkeypatch):
    """A rerun with --no-png must not keep the old picture; other files are the user's."""
    out = tmp_path / "sim"
    out.mkdir()
    (out / "deployed.png").write_text("old picture")
    (out / "summary.json").write_text('{"converged": true}')
    for keep in ("notes.txt", "summary.json.bak", "deployed.vtu.old", "Summary.json"):
        (out / keep).write_text("user")
    order = _replace_order(monkeypatch)
    rc, so, err = run(argv_of("simulate", inputs, str(out)), capsys)
    assert rc == 0 and err == [] and len(so.splitlines()) == 1
    written = ["deployed.vtu", "deployed.obj", "deployed.stl", "deployed.ply", "pattern.dxf", "pattern.svg",
               "index.html", "summary.json"]
    assert sorted(os.listdir(out)) == sorted(written + ["notes.txt", "summary.json.bak", "deployed.vtu.old",
                                                        "Summary.json"])
    assert order == written
    s = json.loads((out / "summary.json").read_text(), parse_constant=lambda c: pytest.fail(c))
    assert s["converged"] is True and s["n_vertices"] > 0


@pytest.mark.parametrize("verb", ["design", "calibrate strips", "calibrate fabric", "validate"])
def test_summary_is_written_last_and_the_folder_is_complete(verb, inputs, tmp_path, monkeypatch):
    """design (Python API, the CLI's design_file with a coarse refinement for speed), calibrate
    and validate: each output exactly once, the summary last; stale outputs of the verb gone."""
    out = tmp_path / "o"
    out.mkdir()
    names = VERBS[verb][3]
    stale = {"design": "verify.png", "calibrate strips": "strips_fit.png", "calibrate fabric": "tensile_37.5deg.png",
             "validate": "residuals_after.png"}[verb]
    (out / stale).write_text("stale")
    (out / "mine.txt").write_text("user")
    order = _replace_order(monkeypatch)
    if verb == "design":
        from inverse.design import design_file
        rep = design_file(inputs["target"], out, edge_mm=2.0)
        assert rep["files"] == sorted(set(os.listdir(out)) - {"mine.txt"})
    else:
        assert main(argv_of(verb, inputs, str(out))) == 0
    summary = VERBS[verb][2]
    assert order[-1] == summary and order.count(summary) == 1
    written = set(os.listdir(out)) - {"mine.txt"}
    assert (out / "mine.txt").read_text() == "user"
    if stale in written:                   # rewritten by this run, not kept
        assert (out / stale).read_bytes() != b"stale"
    assert written <= set(names) | {n for n in written if n.startswith("tensile_") and n.endswith("deg.png")}
    assert _no_temp_files(out) == []
    with open(out / summary) as f:
        json.load(f, parse_constant=lambda c: pytest.fail(f"{summary} holds {c}"))


@pytest.mark.parametrize("verb", sorted(WORK))
@pytest.mark.parametrize("exc", [KeyboardInterrupt, RuntimeError])
def test_an_interrupted_rerun_leaves_no_stale_summary(verb, exc, inputs, tmp_path, capsys, monkeypatch):
    """Ctrl-C (130) or an internal failure (3) during the work of a rerun: the earlier run's
    files (its summary saying converged) are gone, the user's files stay, nothing else is left;
    a folder the run created is removed again."""
    import importlib
    mod, fn = WORK[verb]

    def boom(*a, **k):
        raise exc("stop")
    monkeypatch.setattr(importlib.import_module(mod), fn, boom)
    out = tmp_path / "o"
    out.mkdir()
    for n in VERBS[verb][3]:
        (out / n).write_text('{"converged": true}')
    (out / "mine.txt").write_text("user")
    rc, _, err = run(argv_of(verb, inputs, str(out)), capsys)
    assert rc == (130 if exc is KeyboardInterrupt else 3) and len(err) == 1
    assert os.listdir(out) == ["mine.txt"]
    fresh = tmp_path / "new" / "deeper"
    rc, _, err = run(argv_of(verb, inputs, str(fresh)), capsys)
    assert rc == (130 if exc is KeyboardInterrupt else 3)
    assert not (tmp_path / "new").exists()


def test_interrupt_while_writing_leaves_nothing(inputs, tmp_path, capsys, monkeypatch):
    """Ctrl-C in the middle of writing deployed.vtu: no partial file, no temporary file, no
    summary, and the folder this run created is gone."""
    import forward.simulate as fs

    def partial(sim, path):
        with open(path, "w") as f:
            f.write("<VTKFile half")
        raise KeyboardInterrupt
    monkeypatch.setattr(fs, "write_vtu", partial)
    out = tmp_path / "made"
    rc, _, err = run(argv_of("simulate", inputs, str(out)), capsys)
    assert rc == 130 and err == ["selfshape simulate: interrupted"]
    assert os.listdir(tmp_path) == []


# ----------------------------------------------------------------------------- finite numbers
def test_non_finite_simulation_writes_nothing(inputs, tmp_path, capsys):
    """A Young's modulus of 1e300 overflows the energy: exit 2 naming the pattern file (either
    the range check of the pattern or the finite check of the results), no summary.json with
    Infinity."""
    p = tmp_path / "huge.toml"
    p.write_text(open(EXAMPLE).read().replace("young_modulus_mpa = 72.3", "young_modulus_mpa = 1e300"))
    out = tmp_path / "o"
    rc, _, err = run(["simulate", str(p), "-o", str(out), "--size", "3", "--no-png"], capsys)
    assert_refused(rc, err, "huge.toml")
    assert not out.exists()


def test_non_finite_prediction_writes_nothing(inputs, tmp_path, capsys):
    """A model.json with NaN parameters: exit 2, one line naming it, no CSV (refused when the
    model is read, or when the predictions are written)."""
    with open(inputs["model"]) as f:
        m = json.load(f)
    m["theta"] = [float("nan") for _ in m["theta"]]
    bad = tmp_path / "model.json"
    bad.write_text(json.dumps(m))
    out = tmp_path / "p.csv"
    rc, _, err = run(["predict", str(bad), inputs["csv"], "-o", str(out)], capsys)
    assert_refused(rc, err, "model.json")
    assert os.listdir(tmp_path) == ["model.json"]


NOISY = """
import os, sys, warnings
import forward.simulate as fs
from shellfem.errors import SelfshapeError
def noisy(*a, **k):
    warnings.warn("overflow encountered in multiply", RuntimeWarning)
    print("Warning: a note printed by a Python library", file=sys.stderr)
    os.write(2, b"Warning : a line printed by a C library\\n")
    raise SelfshapeError("huge.toml: the simulation gave non-finite numbers")
fs.simulate = noisy
from selfshape.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.parametrize("verbose", [False, True])
def test_library_noise_is_kept_from_the_error_line(verbose, tmp_path):
    """A fresh process (pytest records warnings itself) whose simulation warns through Python's
    warnings, prints to sys.stderr and writes to file descriptor 2 (as numpy, meshio and Gmsh
    or VTK do) before failing: one stderr line; with -v the noise is shown."""
    env = dict(os.environ, PYTHONPATH=os.path.abspath(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               MPLBACKEND="Agg")
    argv = ["simulate", EXAMPLE, "-o", str(tmp_path / "o"), "--size", "3", "--no-png"] + (["-v"] if verbose else [])
    r = subprocess.run([sys.executable, "-c", NOISY, *argv], capture_output=True, text=True, env=env, timeout=300)
    lines = r.stderr.splitlines()
    assert r.returncode == 2 and r.stdout == ""
    assert lines[-1] == "selfshape simulate: error: huge.toml: the simulation gave non-finite numbers"
    if verbose:
        assert any("Python library" in x for x in lines) and any("C library" in x for x in lines)
        assert any("RuntimeWarning" in x for x in lines)
    else:
        assert len(lines) == 1, r.stderr
    assert os.listdir(tmp_path) == []


def test_verbose_progress_is_kept(inputs, tmp_path, capsys):
    """-v still prints the solver's progress (stdout) before the one result line."""
    rc, so, err = run(argv_of("simulate", inputs, str(tmp_path / "o")) + ["-v"], capsys)
    assert rc == 0 and err == []
    assert len(so.splitlines()) > 3 and so.splitlines()[-1].startswith("converged in ")


def test_gcode_with_a_non_finite_word_is_not_written(tmp_path):
    """G-code drives a printer: a feed or extrusion of inf/nan (e.g. from a 1e-300 mm filament)
    is refused with the file and line, and no file is written; comments do not count."""
    from geometry.gcode import GcodeWriter
    w = GcodeWriter.__new__(GcodeWriter)          # only its lines matter to write()
    w.lines = ["G90", "; Einf in a comment is text", "G1 X1.000 Y2.000 E0.12"]
    w.write(tmp_path / "ok.gcode")
    assert (tmp_path / "ok.gcode").read_text().splitlines() == w.lines
    for bad in ("G1 X1.000 Y2.000 Einf", "G1 F-inf", "G1 Xnan Y1"):
        w.lines = ["G90", bad]
        with pytest.raises(NonFiniteOutput, match=r"^front\.gcode: line 2: "):
            w.write(tmp_path / "front.gcode")
    assert sorted(os.listdir(tmp_path)) == ["ok.gcode"]


def _containers(kids):
    return st.lists(kids, max_size=4) | st.dictionaries(st.text("abcxyz_", min_size=1, max_size=4), kids, max_size=4)


JSONISH = st.recursive(st.none() | st.booleans() | st.integers(-10**6, 10**6)
                       | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=5),
                       _containers, max_leaves=12)


def _non_finite(o):
    if isinstance(o, float):
        return not math.isfinite(o)
    if isinstance(o, dict):
        return any(_non_finite(v) for v in o.values())
    if isinstance(o, list):
        return any(_non_finite(v) for v in o)
    return False


@settings(max_examples=100, **FAST)
@given(obj=JSONISH)
def test_write_json_is_strict_json_or_writes_nothing(obj):
    """Strict JSON that reads back equal, or NonFiniteOutput (a SelfshapeError: exit 2) naming
    the file, and no file nor temporary file left."""
    with tempfile.TemporaryDirectory() as d:
        p = os.path.join(d, "summary.json")
        if _non_finite(obj):
            with pytest.raises(NonFiniteOutput, match=r"^summary\.json.* is (nan|inf|-inf), not a finite number"):
                write_json(p, {"top": obj})
            assert os.listdir(d) == []
        else:
            write_json(p, {"top": obj})
            with open(p) as f:
                back = json.load(f, parse_constant=lambda c: pytest.fail(c))
            assert back == {"top": obj}
            assert os.listdir(d) == ["summary.json"]


@settings(max_examples=60, **FAST)
@given(a=hnp.arrays(np.float64, hnp.array_shapes(max_dims=2, max_side=6),
                    elements=st.floats(allow_nan=True, allow_infinity=True, width=64)))
def test_non_finite_arrays_are_named(a):
    """check_finite_arrays: silent for finite arrays; otherwise names the file, the array and
    the first bad index."""
    bad = ~np.isfinite(a)
    if not bad.any():
        check_finite_arrays("deployed.vtu", {"k1_per_mm": a})
        return
    first = np.unravel_index(int(np.flatnonzero(bad.ravel())[0]), a.shape)
    with pytest.raises(NonFiniteOutput) as e:
        check_finite_arrays("deployed.vtu", {"region": np.arange(3), "k1_per_mm": a})
    msg = str(e.value)
    assert msg.startswith("deployed.vtu: k1_per_mm[" + ", ".join(map(str, first)) + "]") and "\n" not in msg


# ----------------------------------------------------------------------------- the OutputDir itself
NAME = st.text("abcdeps_.0123456789", min_size=1, max_size=14).filter(lambda n: n not in (".", ".."))
KNOWN = ("summary.json", "deployed.vtu", "deployed.png")


@settings(max_examples=80, **FAST)
@given(user=st.sets(NAME | st.sampled_from(["summary.json.bak", "Summary.json", "deployed.png.old",
                                                "tensile_xdeg.png", "tensile_15deg.png.1"]), max_size=6),
       stale=st.sets(st.sampled_from(KNOWN + ("tensile_15deg.png", "tensile_0deg.png", "tensile_37.5deg.png"))))
def test_only_the_verbs_own_outputs_are_cleared(user, stale):
    """begin() removes exactly the known names and pattern matches; every other file stays."""
    pattern = r"tensile_\d+(?:\.\d+)?deg\.png"
    import re
    user = {u for u in user if u not in KNOWN and not re.fullmatch(pattern, u)}
    with tempfile.TemporaryDirectory() as d:
        for n in user | stale:
            with open(os.path.join(d, n), "w") as f:
                f.write(n)
        OutputDir(d, KNOWN, patterns=(pattern,)).begin()
        assert set(os.listdir(d)) == user
        for n in user:
            with open(os.path.join(d, n)) as f:
                assert f.read() == n


def test_output_dir_removes_what_it_wrote_on_failure(tmp_path):
    """A failure after some writes: those files go, and the folders the run created."""
    target = tmp_path / "a" / "b"
    with pytest.raises(RuntimeError):
        with OutputDir(target, ("x.json", "y.txt")) as out:
            out.write_json("x.json", {"v": 1.0})
            assert (target / "x.json").exists()
            raise RuntimeError("later stage")
    assert os.listdir(tmp_path) == []
    with pytest.raises(ValueError, match="not one of"):
        OutputDir(tmp_path, ("x.json",)).file("other.json")


def test_a_link_planted_after_the_check_is_not_written_through(tmp_path):
    """Time passes between the check and the writes: begin() checks again, and so does each
    write; the victim is never written and the planted link is left alone."""
    victim = tmp_path / "victim"
    victim.write_text("precious")
    o = tmp_path / "o"
    out = OutputDir(o, ("summary.json",))
    o.mkdir()
    (o / "summary.json").symlink_to(victim)
    with pytest.raises(SelfshapeError, match="summary.json: is a symbolic link"):
        with out:
            pass
    (o / "summary.json").unlink()
    out = OutputDir(o, ("summary.json",))
    with pytest.raises(SelfshapeError, match="summary.json: is a symbolic link"):
        with out:
            (o / "summary.json").symlink_to(victim)
            out.write_json("summary.json", {})
    assert victim.read_text() == "precious" and os.path.islink(o / "summary.json")
    assert sorted(os.listdir(o)) == ["summary.json"]


# ----------------------------------------------------------------------------- usage errors
_GARBAGE = st.sampled_from(["nan", "inf", "-inf", "", "1e999", "abc", "0x10", "--", "1,5"]) | \
    st.text("0123456789.eE+-", min_size=1, max_size=6).filter(lambda t: not _is_float(t))
_NEGATIVE = st.floats(max_value=-1e-9, allow_nan=False, allow_infinity=False).map(repr)
#: numeric options and values each must refuse
NUMERIC = {("simulate", "--size"): _GARBAGE | _NEGATIVE | st.just("0"),
           ("simulate", "--seed"): _GARBAGE | _NEGATIVE | st.just("1.5"),
           ("simulate", "--max-iterations"): _GARBAGE | _NEGATIVE | st.sampled_from(["0", "2.5"]),
           ("mesh", "--size"): _GARBAGE | _NEGATIVE,
           ("design", "--mesh-size"): _GARBAGE | _NEGATIVE,
           ("design", "--diagonal"): _GARBAGE | _NEGATIVE | st.just("0") | st.floats(0, 9.999).map(repr)
           | st.floats(5000.001, 1e308).map(repr),          # the schema's 10-5000 mm (issue 19: 1e300 ran)
           ("design", "--stretch"): _GARBAGE | st.floats(-1e6, 1.0).map(repr),
           ("design", "--lam"): _GARBAGE | st.floats(1e-9, 1e6).map(repr),
           ("design", "--verify-iterations"): _GARBAGE | st.just("0"),
           ("validate", "--seed"): _GARBAGE | _NEGATIVE}


def _is_float(t):
    try:
        float(t)
        return True
    except ValueError:
        return False


@settings(max_examples=50, **FAST)
@given(data=st.data())
def test_bad_option_values_are_one_line(data):
    """Any non-finite, out-of-range or malformed value of a numeric option: exit 2, one line
    naming the option, no usage text, nothing run (stdout empty, no output)."""
    import contextlib
    import io
    verb, name = data.draw(st.sampled_from(sorted(NUMERIC)))
    value = data.draw(NUMERIC[(verb, name)])
    with tempfile.TemporaryDirectory() as d:
        out = os.path.join(d, "o.msh" if verb == "mesh" else "o")
        src = {"mesh": EXAMPLE, "validate": STRIPS, "design": os.path.join(ROOT, "meshes", "targets", "saddle.obj")}
        argv = [verb, src.get(verb, EXAMPLE), "-o", out, f"{name}={value}"]
        err, so = io.StringIO(), io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(so):
            rc = main(argv)
        lines = err.getvalue().splitlines()
        assert rc == 2 and len(lines) == 1 and name in lines[0] and "usage:" not in err.getvalue(), err.getvalue()
        assert so.getvalue() == "" and os.listdir(d) == []


@pytest.mark.parametrize("argv,word", [
    ([], "required"), (["frob"], "invalid choice"), (["simulate"], "required"),
    (["simulate", EXAMPLE, "-o", "x", "--bogus"], "unrecognized"), (["calibrate", "cloth", "d", "-o", "x"], "choice"),
    (["predict", "m.json", "-o", "x"], "required"),
])
def test_usage_errors_are_one_line(argv, word, capsys):
    rc, so, err = run(argv, capsys)
    assert rc == 2 and len(err) == 1 and word in err[0] and so == ""
    assert "usage:" not in err[0]


def test_failed_prediction_removes_the_folders_it_created(inputs, tmp_path, capsys, monkeypatch):
    """predict -o a/b/p.csv creates a/ and a/b/; if the write then fails they are removed
    again (only those this run created, and only while empty), so nothing is left."""
    import validation.loop as loop_module
    from shellfem.errors import SelfshapeError

    def failing(path, writer):
        raise SelfshapeError(f"{path}: cannot write (disk full)")
    monkeypatch.setattr(loop_module, "write_atomic", failing)
    (tmp_path / "kept").mkdir()
    out = tmp_path / "kept" / "a" / "b" / "p.csv"
    rc, _, err = run(["predict", inputs["model"], inputs["csv"], "-o", str(out)], capsys)
    assert_refused(rc, err, "p.csv")
    assert os.listdir(tmp_path) == ["kept"] and os.listdir(tmp_path / "kept") == []
    monkeypatch.undo()
    rc, _, _ = run(["predict", inputs["model"], inputs["csv"], "-o", str(out)], capsys)
    assert rc == 0 and out.is_file()


@pytest.mark.parametrize("name", ["\x1b]0;pwned\x07p.toml", "\x1b[2J\x1b[31mp.toml", "p\x9b31m.toml"])
def test_error_lines_never_carry_control_characters(tmp_path, capsys, name):
    """A file name (or key) from the input is echoed in the error line: its terminal escape
    sequences (ESC, BEL, CSI) are shown as \\x escapes, never sent to the terminal (issue 19)."""
    rc, so, err = run(["mesh", str(tmp_path / name), "-o", str(tmp_path / "o.msh")], capsys)
    assert rc == 2 and len(err) == 1 and so == "", err
    assert not any(c in err[0] for c in "\x1b\x07\x9b") and "\\x" in err[0], err


def test_a_library_calling_exit_inside_a_verb_is_one_line_status_3(monkeypatch, capsys):
    """meshio's readers call exit() on some malformed files; such a SystemExit escaped the
    verb as status 1 (the non-converged status) with a stray line. Whatever still raises it is
    an internal error: status 3, one line."""
    import geometry.meshing

    def exits(*a, **k):
        raise SystemExit("Expected ply")
    monkeypatch.setattr(geometry.meshing, "mesh_pattern_file", exits)
    rc, so, err = run(["mesh", EXAMPLE, "-o", "x.msh"], capsys)
    assert rc == 3 and so == "" and len(err) == 1 and "internal error (SystemExit): Expected ply" in err[0], err
