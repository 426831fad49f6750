"""studies/design_targets.py --table: the README table is rebuilt from report.json files alone."""
import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _report(dev=None, back=None, converged=None):
    r = {"stretch": 1.2, "n_faces": 100, "time_s": 1.25, "lambda": 0, "k1_deviation_deg": 1.5, "sigma_bound_violation": [0.1, 0.2],
         "sigma_out_of_bounds_pct": [1.0, 2.0], "residual_energy": 1e-3, "ribbons_per_side": {"front": 3, "back": 1},
         "thickness_histogram": {"front": {"0.4": 3}, "back": {"0.2": 1}}}
    if converged is not None:
        r.update(verify_converged=converged, verify_reason="maximum number of iterations reached",
                 deviation_pct_bbox=dev, deviation_target_to_deployed_pct_bbox=back)
    return r


def test_table_only_rebuilds_from_reports(tmp_path):
    out, docs = tmp_path / "out", tmp_path / "docs"
    for name, rep in (("a", _report([2.5, 10.9], [8.2, 27.3], True)), ("b", _report(None, None, False)),
                      ("c", _report())):
        os.makedirs(out / name)
        (out / name / "report.json").write_text(json.dumps(rep))
    run = subprocess.run([sys.executable, os.path.join("studies", "design_targets.py"), "--table", "--out", str(out),
                          "--docs", str(docs)], cwd=ROOT, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")])})
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout)["table"].endswith("table.md")
    rows = (docs / "table.md").read_text().splitlines()
    assert "target to deployed % (mean / max)" in rows[0]
    assert rows[2].startswith("| a | 1.2 | 100 | 1.2 | 0 | 2.5 / 10.9 | 8.2 / 27.3 |")
    assert "| b |" in rows[3] and "not converged (maximum number of iterations reached) | - |" in rows[3]
    assert "| c |" in rows[4] and "| not run | - |" in rows[4] and rows[4].endswith("| 3 / 1 | 0.2-0.4 |")
