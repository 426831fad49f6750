"""`selfshape sweep` (validation.sweep, shellfem.cluster): the same table serially, on a local
Dask cluster and on a scheduler with separately started workers, one of them killed mid-run;
resuming runs nothing; a bad sweep file is one line, exit 2, nothing written.

The sweep is examples/sweep_strip.toml: the 30 x 3 mm strip at 3 stretches x 2 thicknesses on
a 2 mm mesh (97 vertices, about a second each).
"""
import csv
import os
import signal
import subprocess
import sys
import time

import pytest

from selfshape.cli import main
from validation import sweep as sweep_module

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXAMPLE = os.path.join(ROOT, "examples", "sweep_strip.toml")
STRIP = os.path.join(ROOT, "examples", "strip_narrow.toml")


def read_rows(folder):
    with open(os.path.join(folder, "results.csv"), newline="") as f:
        return list(csv.DictReader(f))


def figures(row):
    """The case's inputs and summary figures that do not depend on the machine's speed."""
    return {k: v for k, v in row.items()
            if (k.startswith("summary.") and not k.startswith("summary.timings_s.") and k != "summary.wall_time_s")
            or k in ("index", "case", "status", "reason", "fabric.stretch", "region.0.thickness_mm",
                     "mesh.size_mm")}


def check_table(folder, reference=None):
    rows = read_rows(folder)
    assert [r["index"] for r in rows] == [str(i) for i in range(6)]
    assert all(r["status"] == "ok" for r in rows)
    assert {(r["fabric.stretch"], r["region.0.thickness_mm"]) for r in rows} == \
        {(s, t) for s in ("1.2", "1.35", "1.5") for t in ("0.2", "0.3")}
    for r in rows:
        for name in ("summary.json", "deployed.png", "pattern.toml"):
            assert os.path.isfile(os.path.join(folder, r[f"path.{name}"]))
        assert os.path.isfile(os.path.join(folder, r["case"], "case.json"))
    import pyarrow.parquet as pq
    table = pq.read_table(os.path.join(folder, "results.parquet"))
    assert table.num_rows == 6 and table.column("summary.energy").type == "double"
    assert os.path.getsize(os.path.join(folder, "contact_sheet.png")) > 10_000
    if reference is not None:
        assert [figures(r) for r in rows] == [figures(r) for r in reference]
    return rows


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("sweep") / "serial")
    r = sweep_module.run_sweep(EXAMPLE, out, workers=0)
    assert (r["cases"], r["ran"], r["reused"], r["failed"]) == (6, 6, 0, 0)
    return out, check_table(out)


def test_local_cluster_gives_the_serial_table(serial, tmp_path):
    out = str(tmp_path / "local")
    r = sweep_module.run_sweep(EXAMPLE, out, workers=2)
    assert (r["cases"], r["ran"], r["failed"]) == (6, 6, 0)
    rows = check_table(out, serial[1])
    assert len({row["worker"] for row in rows}) == 2          # both workers took cases


def test_resuming_a_finished_sweep_runs_nothing(serial, tmp_path, monkeypatch):
    import shutil
    out = str(tmp_path / "copy")
    shutil.copytree(serial[0], out)
    import forward.simulate

    def refuse(*a, **k):
        raise AssertionError("a finished case was simulated again")
    monkeypatch.setattr(forward.simulate, "simulate_pattern_file", refuse)
    r = sweep_module.run_sweep(EXAMPLE, out, workers=0)
    assert (r["ran"], r["reused"], r["failed"]) == (0, 6, 0)
    check_table(out, serial[1])
    # a case without its marker (its worker died before the end) runs again, the others not
    monkeypatch.undo()
    victim = serial[1][4]["case"]
    os.remove(os.path.join(out, victim, "case.json"))
    monkeypatch.setattr(sweep_module, "PARTIAL_TABLE_S", -1.0)          # the table so far after each case
    r = sweep_module.run_sweep(EXAMPLE, out, workers=0)
    assert (r["ran"], r["reused"]) == (1, 5)
    rows = check_table(out, serial[1])
    assert [row["ran"] for row in rows] == ["False"] * 4 + ["True", "False"]


# ----------------------------------------------------------------------------- a scheduler
def _start(args, env, log):
    return subprocess.Popen(args, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def _stop(proc):
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    proc.wait(timeout=30)


@pytest.fixture
def scheduler(tmp_path):
    """A `dask scheduler` on 127.0.0.1 (port from its scheduler file) and two `dask worker`s
    (no nanny: the worker is the process, so SIGKILL kills it), each its own process group,
    all killed at the end whatever happens."""
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""), MPLBACKEND="Agg")
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    sfile = str(tmp_path / "scheduler.json")
    log = open(tmp_path / "dask.log", "w")
    procs = []
    try:
        procs.append(_start(dask + ["--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file", sfile],
                            env, log))
        t0 = time.time()
        while not os.path.isfile(sfile) and time.time() - t0 < 60:
            assert procs[0].poll() is None, open(tmp_path / "dask.log").read()[-2000:]
            time.sleep(0.2)
        import json
        time.sleep(0.2)
        with open(sfile) as f:
            address = json.load(f)["address"]
        workers = [_start([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1",
                           "--no-nanny", "--no-dashboard", "--name", f"w{i}"], env, log) for i in range(2)]
        procs += workers
        from distributed import Client
        with Client(address, timeout=30) as c:
            c.wait_for_workers(2, timeout=60)
        yield address, workers
    finally:
        for p in reversed(procs):
            _stop(p)
        log.close()


def test_scheduler_with_a_worker_killed_mid_run(serial, scheduler, tmp_path):
    from distributed import Client
    address, workers = scheduler
    killed = {}

    def kill_busy(row, done, total):
        # after the first case: SIGKILL a worker while the scheduler has a case on it
        if killed or row is None:               # None: the call before any case runs
            return
        with Client(address, timeout=30) as c:
            t0 = time.time()
            while time.time() - t0 < 30:
                busy = {w: keys for w, keys in c.processing().items() if keys}
                if busy:
                    break
                time.sleep(0.02)
            pids = {w: c.run(os.getpid, workers=[w])[w] for w in busy}
            # the worker that finished the first case has just started its next one
            addr = next((w for w in busy if row["worker"].endswith(f":{pids[w]}")), next(iter(busy)))
            keys, pid = busy[addr], pids[addr]
        victim = next(p for p in workers if p.pid == pid)
        os.kill(pid, signal.SIGKILL)
        killed.update(proc=victim, keys=list(keys))
    out = str(tmp_path / "cluster")
    r = sweep_module.run_sweep(EXAMPLE, out, scheduler=address, progress=kill_busy)
    assert killed["proc"].wait(timeout=30) == -signal.SIGKILL
    assert (r["cases"], r["failed"]) == (6, 0)
    rows = check_table(out, serial[1])
    survivor = next(p for p in workers if p is not killed["proc"])
    lost = [int(k.rsplit("-", 1)[1]) for k in killed["keys"]]          # the case the killed worker had
    assert lost and all(rows[i]["worker"].endswith(f":{survivor.pid}") for i in lost)


# ----------------------------------------------------------------------------- bad input
BAD = {
    "unknown key": ('pattern = "{strip}"', '"fabric.strech" = [1.2]', "[grid] fabric.strech: unknown key 'strech' "
                                                                      "(did you mean 'stretch'?)"),
    "empty grid": ('pattern = "{strip}"', '"fabric.stretch" = []', "[grid] fabric.stretch: the list of values is empty"),
    "non-numeric": ('pattern = "{strip}"', '"fabric.stretch" = [1.2, "abc"]',
                    "[grid] fabric.stretch value #2 must be a number or [sx, sy], got the string 'abc'"),
    "missing pattern": ('pattern = "nothere.toml"', '"fabric.stretch" = [1.2]',
                        "[sweep] pattern nothere.toml: file not found"),
    "bad base pattern": ('pattern = "{typo}"', '"fabric.stretch" = [1.2]', "[sweep] pattern: "),
    "index out of range": ('pattern = "{strip}"', '"region.1.thickness_mm" = [0.2]',
                           "the base pattern has 1 [[region]] entry (indices from 0)"),
    "unknown table": ('pattern = "{strip}"', '"fabrik.stretch" = [1.2]', "unknown key 'fabrik'"),
    "not a list": ('pattern = "{strip}"', '"fabric.stretch" = 1.2', "[grid] fabric.stretch must be a list of values"),
    "design option": ('targets = ["{strip}"]', '"strech" = [1.3]', "unknown key 'strech' (did you mean 'stretch'?)"),
    # values of the right type that the pattern reader refuses: before, each ran as a case and
    # wrote NaN or 135 into results.csv and the case's pattern.toml (exit 1)
    "NaN pattern value": ('pattern = "{strip}"', '"fabric.stretch" = [1.2, nan]',
                          "[grid] fabric.stretch = nan (case #1): [fabric]: stretch must be a finite number in [1, 3]"),
    "out-of-range pattern value": ('pattern = "{strip}"',
                                   '"fabric.stretch" = [1.2]\n"region.0.thickness_mm" = [0.2, 135]',
                                   "[grid] region.0.thickness_mm = 135 (case #1): [[region]] #1: thickness_mm must be "
                                   "in [0.01, 10] mm, got 135"),
    "wrong-type pattern value": ('pattern = "{strip}"', '"solver.seed" = [1.5]',
                                 "[grid] solver.seed = 1.5 (case #0): [solver]: seed must be an integer"),
    "out-of-range option": ('pattern = "{strip}"', '"fabric.stretch" = [1.2]\n[options]\n"mesh.size_mm" = inf',
                            "[options] mesh.size_mm = inf: [mesh]: size_mm must be a finite number in [0.01, 1000] mm"),
    "out-of-range [[case]]": ('pattern = "{strip}"', '"fabric.stretch" = [1.2]\n[[case]]\n"mesh.size_mm" = 0',
                              "[[case]] #1 mesh.size_mm = 0 (case #0): [mesh]: size_mm must be in [0.01, 1000] mm"),
    "NaN random range": ('pattern = "{strip}"\nsamples = 2', '"mesh.size_mm" = [2.0]\n[random]\n"fabric.stretch" = '
                         '[1.2, nan]', "[random] fabric.stretch must be a range [lo, hi] of two finite numbers"),
    "out-of-range random draw": ('pattern = "{strip}"\nsamples = 2', '"mesh.size_mm" = [2.0]\n[random]\n'
                                '"fabric.stretch" = [4, 5.0]', "[random] fabric.stretch = 4"),
    "NaN design option": ('targets = ["{strip}"]', 'diagonal = [40.0, nan]',
                          "[grid] diagonal value #2 must be a finite number in [10, 5000] mm, got nan"),
    "out-of-range design option": ('targets = ["{strip}"]', 'stretch = [1.6, 5]',
                                   "[grid] stretch value #2 must be in (1, 3], got 5"),
    "wrong-type design option": ('targets = ["{strip}"]', 'mesh_size = ["2"]',
                                 "[grid] mesh_size value #1 must be a number in [0.01, 1000] mm, got the string '2'"),
    "out-of-range design draw": ('targets = ["{strip}"]\nsamples = 2',
                                 'diagonal = [40.0]\n[random]\ngap_mm = [0.5, 1e9]',
                                 "[random] gap_mm hi must be in [0, 10000] mm, got 1e+09"),
    "missing design law": ('targets = ["{strip}"]', 'law = ["nothere.csv"]', "[grid] law value #1: nothere.csv: file "
                                                                             "not found"),
    # more than MAX_CASES cases: before, 10^9 samples hung and a 10,000 x 10,000 grid ran out of memory
    "grid over the case cap": ('pattern = "{strip}"', '"fabric.stretch" = [' + ", ".join(["1.2"] * 101) + ']\n'
                               '"mesh.size_mm" = [' + ", ".join(["2.0"] * 100) + "]",
                               "10,100 cases ([grid] fabric.stretch (101 values) x [grid] mesh.size_mm (100 values)), "
                               "more than the 10,000 a sweep may have"),
    "grid list over the case cap": ('pattern = "{strip}"', '"mesh.size_mm" = [' + ", ".join(["2.0"] * 10_001) + "]",
                                    "[grid] mesh.size_mm has 10,001 values, more than the 10,000 cases"),
    "samples over the case cap": ('pattern = "{strip}"\nsamples = 10001', '"mesh.size_mm" = [2.0]\n[random]\n'
                                  '"fabric.stretch" = [1.2, 1.6]', "10,001 cases ([sweep] samples = 10,001), more than "
                                                                   "the 10,000 a sweep may have"),
    "design samples over the case cap": ('targets = ["{strip}", "{strip}"]\nsamples = 5001', 'diagonal = [40.0]\n'
                                         '[random]\nstretch = [1.2, 1.6]',
                                         "10,002 cases ([sweep] samples = 5,001 x 2 [sweep] targets)"),
}


@pytest.mark.parametrize("name", sorted(BAD))
def test_bad_sweep_file_is_one_line_and_writes_nothing(name, tmp_path, capsys, monkeypatch):
    """exit 2, one line naming the sweep file and the key (and the value and case where one
    is at fault), no output folder; no case runs (the old code ran the bad values as cases)."""
    import shellfem.cluster

    def refuse(*a, **k):
        raise AssertionError("a case of a bad sweep file ran")
    monkeypatch.setattr(shellfem.cluster, "map_tasks", refuse)
    head, grid, message = BAD[name]
    path = tmp_path / "bad.toml"
    typo = os.path.join(ROOT, "tests", "data", "patterns", "typo.toml")
    path.write_text(f"[sweep]\n{head.format(strip=STRIP, typo=typo)}\n\n[grid]\n{grid}\n")
    out = tmp_path / "out"
    rc = main(["sweep", str(path), "-o", str(out), "--workers", "0"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and err.startswith(f"selfshape sweep: error: {path}")
    assert message in err
    assert not out.exists()


def test_a_case_that_fails_while_it_runs_is_a_row(tmp_path, capsys):
    """A value the pattern reader accepts but the simulation refuses (a mesh above the
    triangle cap) is the case's error row, not the sweep's."""
    path = tmp_path / "s.toml"
    path.write_text(f'[sweep]\npattern = "{STRIP}"\n\n[[case]]\n"mesh.size_mm" = 0.01\n')
    out = tmp_path / "out"
    rc = main(["sweep", str(path), "-o", str(out), "--workers", "0"])
    assert rc == 1
    (row,) = read_rows(str(out))
    assert row["status"] == "error" and "more than the 2,000,000 selfshape meshes" in row["reason"]
    assert "1 cases: 1 run, 0 reused, 1 not ok (error 1)" in capsys.readouterr().out


def test_a_combination_the_reader_refuses_names_the_case(tmp_path):
    """Values each valid alone but refused together: the line names the case and its values
    (with the reader's reason), since no single key is at fault."""
    path = tmp_path / "s.toml"
    path.write_text(f'[sweep]\npattern = "{STRIP}"\n\n[[case]]\n"fabric.rectangle" = [10, 3]\n'
                    f'"region.0.polygon" = [[20, 0], [25, 0], [25, 3], [20, 3]]\n')
    with pytest.raises(sweep_module.SelfshapeError) as e:
        sweep_module.load_sweep(path)
    assert str(e.value).startswith(f"{path}: case #0 (fabric.rectangle = [10, 3], region.0.polygon = [[20, 0], ")
    assert "polygon is outside the fabric" in str(e.value)


def test_the_table_holds_no_non_finite_number(tmp_path):
    """A failed case's row, or a figure that is NaN or infinite, is written as empty cells:
    results.csv and results.parquet never hold NaN/Infinity (before: the CSV wrote 'nan')."""
    import math

    import pyarrow.parquet as pq
    from shellfem.outfiles import OutputDir
    figures = sweep_module.flatten_figures({"energy": float("nan"), "bbox_mm": [1.0, float("inf")]}, "summary")
    assert figures == {"summary.energy": None, "summary.bbox_mm.0": 1.0, "summary.bbox_mm.1": None}
    rows = [{"index": 0, "case": "case-a", "status": "ok", "reason": "", "time_s": 1.0, "ran": True, "worker": "w",
             "x": 1.5, "summary.energy": 2.0},
            {"index": 1, "case": "case-b", "status": "failed", "reason": "boom", "time_s": None, "ran": True,
             "worker": None, "x": float("nan"), "summary.energy": float("-inf")}]
    out = OutputDir(str(tmp_path / "t"), sweep_module.OUTPUTS)
    with out:
        sweep_module.write_table(out, rows)
    text = (tmp_path / "t" / "results.csv").read_text()
    assert "nan" not in text.lower() and "inf" not in text.lower()
    assert read_rows(str(tmp_path / "t"))[1]["x"] == "" and read_rows(str(tmp_path / "t"))[1]["reason"] == "boom"
    table = pq.read_table(str(tmp_path / "t" / "results.parquet")).to_pydict()
    assert table["x"] == [1.5, None] and table["summary.energy"] == [2.0, None]
    assert all(not (isinstance(v, float) and not math.isfinite(v)) for col in table.values() for v in col)


def test_random_draws_are_seeded(tmp_path):
    path = tmp_path / "r.toml"
    path.write_text(f'[sweep]\npattern = "{STRIP}"\nsamples = 4\nseed = 3\n\n[random]\n"fabric.stretch" = [1.2, 1.6]\n'
                    f'"solver.seed" = [0, 9]\n\n[grid]\n"mesh.size_mm" = [2.0, 3.0]\n')
    a, b = sweep_module.load_sweep(path), sweep_module.load_sweep(path)
    assert a.cases == b.cases and len(a.cases) == 8
    assert all(1.2 <= c["fabric.stretch"] <= 1.6 and isinstance(c["solver.seed"], int) for c in a.cases)
    base = repr(a.base)
    specs = sweep_module.case_specs(a, str(tmp_path / "o"))
    assert len({s["hash"] for s in specs}) == 8
    assert 'stretch = 1.' in specs[0]["pattern_text"]
    assert repr(a.base) == base                       # the cases copy the base pattern's paths, never change it


# ----------------------------------------------------------------------------- the law's patches
@pytest.mark.slow
def test_law_patches_on_a_local_cluster_give_the_serial_table(tmp_path, capsys):
    """studies/thickness_law_sim.py --workers 2: the same table (and rows) as the serial default."""
    from validation.law_tables import main as law_main
    args = ["--model", "sim", "--thickness", "0.3", "--spacing", "3.9", "6.5", "--rows", "3", "--motifs", "2",
            "--mesh-size", "3", "--across", "1", "--sides", "front", "--calibration",
            os.path.join(ROOT, "inverse", "data", "strips_S1_calibration.json")]
    import json
    runs = []
    for extra, name in (([], "serial.csv"), (["--workers", "2"], "cluster.csv")):
        rc = law_main(args + extra + ["--out", str(tmp_path / name)])    # 1: one thickness is no table
        rows = json.loads(capsys.readouterr().out)["rows"]
        runs.append((rc, [{k: v for k, v in r.items() if k != "time_s"} for r in rows]))
    assert runs[0] == runs[1] and len(runs[0][1]) == 2 and all(r["converged"] for r in runs[0][1])


def test_example_sweep_files_load():
    import glob
    files = glob.glob(os.path.join(ROOT, "examples", "**", "sweep_*.toml"), recursive=True)
    assert files
    for f in files:
        assert sweep_module.load_sweep(f).cases


def test_output_that_is_a_file_is_refused(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("precious")
    assert main(["sweep", EXAMPLE, "-o", str(afile), "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the output must be a folder" in err
    assert afile.read_text() == "precious"
    assert main(["sweep", EXAMPLE, "-o", str(tmp_path / "o"), "--workers", "-1"]) == 2
    assert "--workers" in capsys.readouterr().err


def test_design_sweep(tmp_path):
    """targets x design options: each case a design folder, report.json figures in the table,
    a stretch without a shipped law an error row."""
    from geometry.target import sphere_cap
    V, F = sphere_cap(radius=40.0, half_angle_deg=30.0, n_radial=8)
    with open(tmp_path / "cap.obj", "w") as f:
        f.writelines(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in V)
        f.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F)
    (tmp_path / "s.toml").write_text('[sweep]\ntargets = ["cap.obj"]\n\n[options]\ndiagonal = 40.0\n\n'
                                     '[grid]\nstretch = [1.6, 1.8]\n')
    r = sweep_module.run_sweep(str(tmp_path / "s.toml"), str(tmp_path / "out"), workers=0)
    assert r["statuses"] == {"ok": 1, "error": 1}
    ok, bad = read_rows(str(tmp_path / "out"))
    assert ok["target"] == "cap.obj" and ok["stretch"] == "1.6" and int(ok["report.n_ribbons"]) > 0
    assert os.path.isfile(os.path.join(str(tmp_path / "out"), ok["path.pattern.png"]))
    assert bad["status"] == "error" and "no shipped thickness law for fabric stretch 1.8" in bad["reason"]
