"""Recovery of known fabric parameters by ``selfshape calibrate fabric`` over generated test
folders (tests/fabric_folders.py: the project's fabric model forward, seeded, every schema
variation the data README allows). Prints one line per seed and the worst errors;
``--json`` writes them. Tolerances of issue 19: a1, a2, b1, b2 within 5 %, g1, g2 within
0.005, k_B within 5 %.

    python studies/fabric_recovery.py --seeds 0-39 [--json out/validation/fabric_recovery.json]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))
sys.path.insert(0, os.path.join(HERE, ".."))

import fabric_folders as FF  # noqa: E402
from validation.fabric import calibrate_fabric  # noqa: E402

TOL = {"a1": 0.05, "a2": 0.05, "b1": 0.05, "b2": 0.05, "g1": 0.005, "g2": 0.005, "k_B": 0.05}


def seeds_of(text):
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="0-39")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    rows, t0 = [], time.time()
    for seed in seeds_of(a.seeds):
        spec = FF.random_spec(seed)
        with tempfile.TemporaryDirectory() as tmp:
            folder = FF.write_folder(spec, os.path.join(tmp, "fabric"))
            try:
                res = calibrate_fabric(folder, os.path.join(tmp, "out"), plots=False)
            except Exception as e:  # a study reports every failure and goes on
                rows.append({"seed": seed, "error": f"{type(e).__name__}: {e}"})
                print(f"seed {seed}: FAILED {type(e).__name__}: {e}", flush=True)
                continue
        err = FF.recovery_errors(spec, res)
        kb = max(v for k, v in err.items() if k.startswith("k_B"))
        ok = all(err[k] <= TOL[k] for k in ("a1", "a2", "b1", "b2", "g1", "g2")) and kb <= TOL["k_B"]
        # error in units of the reported standard error (honest SEs: mostly |z| < 3)
        z = {k: (res["orthotropic"][k][0] - spec.params[k]) / res["orthotropic"][k][1]
             for k in ("a1", "a2", "a3", "b1", "b2", "g1", "g2")}
        rows.append({"seed": seed, "ok": ok, "errors": err, "z": z, "thickness_mm": spec.thickness_mm, "pcts": spec.pcts,
                     "cycles": spec.cycles, "rate_hz": spec.rate_hz, "orientations": spec.orientations,
                     "poisson_in_meta": spec.poisson is not None, "params": spec.params})
        print(f"seed {seed}: {'ok ' if ok else 'OUT'} h {spec.thickness_mm:.2f} mm, pcts {spec.pcts}, "
              f"{spec.cycles} cycles, {spec.rate_hz:.1f} Hz; rel a1 {err['a1']:.2%} a2 {err['a2']:.2%} "
              f"b1 {err['b1']:.2%} b2 {err['b2']:.2%} a3 {err['a3']:.2%}; abs g1 {err['g1']:.4f} g2 {err['g2']:.4f}; "
              f"k_B worst {kb:.2%}", flush=True)
    done = [r for r in rows if "errors" in r]
    worst = {k: max(r["errors"][k] for r in done) for k in ("a1", "a2", "a3", "b1", "b2", "g1", "g2")} if done else {}
    if done:
        worst["k_B"] = max(v for r in done for k, v in r["errors"].items() if k.startswith("k_B"))
        worst["median_abs_z"] = {k: float(sorted(abs(r["z"][k]) for r in done)[len(done) // 2]) for k in done[0]["z"]}
    summary = {"folders": len(rows), "failed": len(rows) - len(done), "within_tolerance": sum(r["ok"] for r in done),
               "worst": worst, "tolerance": TOL, "seconds": time.time() - t0}
    print(json.dumps(summary))
    if a.json:
        os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
        with open(a.json, "w") as f:
            json.dump({"summary": summary, "rows": rows}, f, indent=1)
    return 0 if summary["failed"] == 0 and summary["within_tolerance"] == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
