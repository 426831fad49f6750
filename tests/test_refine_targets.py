"""studies/refine_targets.py runs its targets through the Dask machinery (issue 21): each target
one task of shellfem.cluster.map_tasks; serially (the default) and on a 2-worker LocalCluster the
rows are the same, in the targets' order; one JSON line per target and the summary; bad
--workers / --scheduler are refused before any work. A cheap stand-in replaces the refinement
itself (minutes per target)."""
import json
import os
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "studies"))
import refine_targets  # noqa: E402

TARGETS = ["beetle", "hat", "hemisphere", "saddle"]


def fake_target(job: dict) -> dict:
    """A cheap stand-in for ``run_target``, loaded by the workers by name: the target mesh's face
    count and bounding-box diagonal (mm) as read on the worker, a file written into the target's
    folder, the options it was given, and the process that ran it."""
    from geometry.target import read_mesh
    V, F = read_mesh(job["path"])
    os.makedirs(job["out_dir"], exist_ok=True)
    with open(os.path.join(job["out_dir"], "done.txt"), "w") as f:
        f.write(job["path"])
    return {"target": os.path.splitext(os.path.basename(job["path"]))[0], "faces": int(len(F)),
            "diagonal_mm": float(np.linalg.norm(V.max(0) - V.min(0))), "mesh_size": job["args"].mesh_size,
            "pid": os.getpid()}


def _jobs(tmp_path, args):
    paths = [os.path.join(ROOT, "meshes", "targets", f"{n}.obj") for n in TARGETS]
    return [{"path": p, "out_dir": str(tmp_path / os.path.basename(p)[:-4]), "args": args} for p in paths]


def test_serial_and_local_cluster_give_the_same_rows(tmp_path):
    import argparse
    args = argparse.Namespace(mesh_size=3.0)
    calls = {}
    rows = {}
    for workers in (0, 2):
        seen = calls[workers] = []
        rows[workers] = refine_targets.run_targets(_jobs(tmp_path / str(workers), args), workers=workers,
                                                   task=fake_target, on_row=lambda r, d, t: seen.append((r, d, t)))
    assert [r["target"] for r in rows[0]] == TARGETS                       # the targets' order
    assert {r["pid"] for r in rows[0]} == {os.getpid()}                    # serial: in this process
    assert os.getpid() not in {r["pid"] for r in rows[2]}                  # the cluster's worker processes
    strip = [[{k: v for k, v in r.items() if k != "pid"} for r in rows[w]] for w in (0, 2)]
    assert strip[0] == strip[1] and all(r["faces"] > 100 and r["mesh_size"] == 3.0 for r in strip[0])
    for w in (0, 2):
        assert calls[w][0] == (None, 0, 4) and [c[1:] for c in calls[w][1:]] == [(k, 4) for k in (1, 2, 3, 4)]
        assert sorted(c[0]["target"] for c in calls[w][1:]) == TARGETS
        assert all(os.path.isfile(tmp_path / str(w) / n / "done.txt") for n in TARGETS)


def test_main_prints_a_json_line_per_target_and_the_summary(tmp_path, monkeypatch, capsys):
    """--workers 0 (the default): run_target in this process, as before, for each target asked."""
    got = []

    def fake_run_target(path, out_dir, args):
        got.append((os.path.basename(path), out_dir, args.max_outer))
        name = os.path.splitext(os.path.basename(path))[0]
        return {"target": name, "open_loop": {"deployed_to_target_pct": 2.0}, "refined": {"deployed_to_target_pct": 1.0}}
    monkeypatch.setattr(refine_targets, "run_target", fake_run_target)
    monkeypatch.chdir(ROOT)
    assert refine_targets.main(["hemisphere", "saddle", "--out", str(tmp_path), "--max-outer", "3", "-q"]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [x["target"] for x in lines[:2]] == ["hemisphere", "saddle"] and len(lines) == 3
    assert lines[2] == {"summary": {n: {"open": {"deployed_to_target_pct": 2.0}, "refined": {"deployed_to_target_pct": 1.0}}
                                    for n in ("hemisphere", "saddle")}}
    assert got == [("hemisphere.obj", str(tmp_path / "hemisphere"), 3), ("saddle.obj", str(tmp_path / "saddle"), 3)]


@pytest.mark.parametrize("extra", [["--workers", "-1"], ["--workers", "2", "--scheduler", "tcp://127.0.0.1:1"],
                                   ["--scheduler", "not an address"], ["--stability", "nan"], ["--stability", "1"],
                                   ["--stability", "-0.5"], ["--start-iterations", "0"]])
def test_bad_workers_or_scheduler_are_refused_before_any_work(extra, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(refine_targets, "run_target", lambda *a: pytest.fail("ran a target"))
    with pytest.raises(SystemExit) as e:
        refine_targets.main(["saddle", "--out", str(tmp_path)] + extra)
    err = capsys.readouterr().err.splitlines()[-1]
    assert e.value.code == 2 and any(f"error: --{o}" in err for o in ("workers", "scheduler", "stability", "start-iterations")), err


def test_the_readme_table_is_built_from_the_json_lines(tmp_path, capsys):
    """--table reads runs' output (JSON lines among other lines), keeps the last row per target
    and prints one markdown row each with both deviations, mean / max to two decimals."""
    row = {"target": "saddle", "stretch": 1.2, "out_of_bounds_pct": [7.25, 11.2],
           "open_loop": {"deployed_to_target_pct": [2.047, 7.54], "target_to_deployed_pct": [2.105, 7.225]},
           "refined": {"deployed_to_target_pct": [0.957, 4.034], "target_to_deployed_pct": [1.086, 4.711]},
           "outer_iterations": 6, "kept": "refined, on a jig", "release_reaches_refined_state": False,
           "refine_s": 1720.3, "total_s": 1789.8}
    log = tmp_path / "run.log"
    log.write_text("refine 0: J 5.5\n" + json.dumps({**row, "outer_iterations": 9}) + "\n" + json.dumps(row)
                   + "\n" + json.dumps({"summary": {}}) + "\n")
    assert refine_targets.main(["--table", str(log)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 3 and out[0].startswith("| target |")
    assert out[2] == ("| saddle | 1.2 | 7.25 / 11.20 | 2.05 / 7.54 (2.10 / 7.22) | 0.96 / 4.03 (1.09 / 4.71) | 6 | "
                      "refined, on a jig (release from flat misses the refined state) | 1720 / 1790 |")


def test_analytic_targets_are_disks_with_the_curvature_they_state():
    """Each analytic target (study_cli.ANALYTIC_TARGETS) is a disk the designer accepts; the
    hypar z = x y / 250 mm has K = -1/250^2 at its centre, the ellipsoid cap K > 0 at its top
    (angle defect per area within 8 mm of the centre), the vault, the wave and the cone K = 0,
    the bump K > 0 on top and K < 0 around it."""
    import igl
    from geometry.target import check_disk
    from study_cli import ANALYTIC_TARGETS
    K0 = {}
    for name, make in ANALYTIC_TARGETS.items():
        V, F = make()
        check_disk(V, F, name)
        near = np.linalg.norm(V[:, :2] - V[:, :2].mean(0), axis=1) < 8.0        # mm around the centre
        area = igl.massmatrix(V, F, igl.MASSMATRIX_TYPE_BARYCENTRIC).diagonal()
        K0[name] = igl.gaussian_curvature(V, F)[near].sum() / area[near].sum()
    assert K0["hypar"] == pytest.approx(-1 / 250.0 ** 2, rel=0.1)
    assert K0["ellipsoid"] == pytest.approx(15.0 ** 2 / (90.0 ** 2 * 60.0 ** 2), rel=0.1)   # c^2 / (a^2 b^2)
    assert abs(K0["vault"]) < 1e-3 * abs(K0["hypar"]) and abs(K0["wave"]) < 1e-3 * abs(K0["hypar"])
    assert abs(K0["cone"]) < 1e-3 * abs(K0["hypar"])
    # the bump: K = 4 h^2 / w^4 at the top, falling within the 8 mm disk; a ring of saddles below
    assert 0.75 * 4 * 14.0 ** 2 / 30.0 ** 4 < K0["bump"] < 4 * 14.0 ** 2 / 30.0 ** 4
    V, F = ANALYTIC_TARGETS["bump"]()
    inner = np.setdiff1d(np.arange(len(V)), igl.boundary_loop(F))
    K = igl.gaussian_curvature(V, F)[inner] / igl.massmatrix(V, F, igl.MASSMATRIX_TYPE_BARYCENTRIC).diagonal()[inner]
    assert K.min() < -0.1 * K0["bump"]
