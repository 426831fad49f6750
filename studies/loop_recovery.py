"""Recovery of undeclared effects by the closed validation loop, over seeds (issue 19).

For every case of validation.strip_sets.CASES (clean, two and three simultaneous
catalogue effects, some partly confounded) and every seed, generate a synthetic strip
set with known effects and known relative noise, run the loop as `selfshape validate`
does (validation.loop.validate: outer grouped K-fold held-out errors, the selection
nested in each training part, then the selection on all rows) and record:

- found: per present effect, whether the loop added it or reported it as confounded
  with an effect it added (the data cannot tell the two apart);
- false additions: added effects that are neither present nor confounded with a
  present one;
- held-out error / noise floor: the loop's relative held-out RMS error over its own
  noise-floor estimate (the replicate scatter's variance function), over the held-out
  floor (the same estimate x sqrt(1 + p / n_train): the held-out error of a correct model
  with p parameters fitted on n_train rows, validation.loop.held_out_floor), and over the
  true noise;
- identifiability (oracle, noise-free): for each present effect, the noncentrality
  sum (misfit / sigma)^2 of the best fit of the true model without it to the noise-free
  curvatures: below ~20 the other parameters absorb it and no selection rule can find
  it reliably from data of this size and noise.

One JSON line per (case, seed) on stdout, then a summary table; the whole record goes
to OUT/loop_recovery.json. Usage (repo root):

    python studies/loop_recovery.py --seeds 10            # full sweep
    python studies/loop_recovery.py --quick               # 3 seeds
    python studies/loop_recovery.py --cases clean,gravity+width_transition --seeds 5
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from validation import loop, strip_sets  # noqa: E402
from validation.strips import MEASURED  # noqa: E402


def groups_with(rep_or_sel, name):
    """The confounded groups (lists of effect names) that contain ``name``."""
    return [set(d["effects"]) for d in rep_or_sel.get("indistinguishable", []) if name in d["effects"]]


def found(added, indist, effect):
    """Added, or reported confounded with an effect that was added."""
    if effect in added:
        return True
    return any(effect in d["effects"] and set(d["effects"]) & set(added) for d in indist)


def false_additions(added, indist, truth):
    """Added effects neither present nor reported confounded with a present one."""
    out = []
    for a in added:
        if a in truth:
            continue
        if any(a in d["effects"] and set(d["effects"]) & set(truth) for d in indist):
            continue
        out.append(a)
    return out


def oracle(rows, truth):
    """Noise-free identifiability: {effect: noncentrality} where the noncentrality is
    sum_i (misfit_i / sigma_i)^2 of the best fit of the true model without that effect
    to the noise-free curvatures, weighted by the true noise variances sigma_i^2 (what
    the loop's weighted F test sees). An effect whose noncentrality is below ~20 is
    absorbed by the other parameters at this size of data and noise: the loop's F test
    (Bonferroni over ~12 effects) has little power for it."""
    k = rows["_truth"]["noise_free"]
    w = 1.0 / (rows["_truth"]["noise"] * k) ** 2
    w = np.minimum(w, 1e3 * np.mean(w))
    clean = dict(rows)
    clean[MEASURED] = k
    out = {}
    for e in truth:
        rest = [loop.fx.BY_NAME[x] for x in truth if x != e]
        f = loop.fit_best(clean, rest, [strip_sets.R_TRUE], n_new=len(rest), weights=w) if rest else \
            loop.fit(clean, [], weights=w)
        out[e] = float(f["wssr"])
    return out


def run_case(case, seed, n_points, reps, with_oracle=True):
    rows = strip_sets.strip_set(case, seed, n_points=n_points, reps=reps)
    truth = list(strip_sets.CASES[case])
    t0 = time.perf_counter()
    rep = loop.validate(rows, seed=seed)
    dt = time.perf_counter() - t0
    y = rows[MEASURED]
    rms_y = float(np.sqrt(np.mean(y ** 2)))
    true_sigma_rel = rows["_truth"]["noise"] * float(np.sqrt(np.mean(rows["_truth"]["noise_free"] ** 2))) / rms_y
    added, indist = rep["effects_added"], rep["indistinguishable"]
    rec = {"case": case, "seed": seed, "n_rows": int(y.size), "present": truth, "added": added,
           "indistinguishable": [d["effects"] for d in indist],
           "found": {e: found(added, indist, e) for e in truth},
           "false_additions": false_additions(added, indist, truth),
           "added_per_outer_fold": rep["effects_added_per_outer_fold"],
           "error_before": rep["error_before"], "error_after": rep["error_after"],
           "noise_relative": rep["noise_relative"], "true_noise_relative": true_sigma_rel,
           "heldout_over_floor": rep["error_after"] / rep["noise_relative"],
           "noise_relative_held_out": rep["noise_relative_held_out"],
           "heldout_over_held_out_floor": rep["error_after"] / rep["noise_relative_held_out"],
           "heldout_over_true_noise": rep["error_after"] / true_sigma_rel,
           "seconds": dt}
    if with_oracle and truth:
        rec["oracle_noncentrality_without"] = oracle(rows, truth)
    return rec


def clean_false_additions(seeds, n_points, reps):
    """False additions of the selection on clean sets (select_effects on all rows, as the
    final step of validate): {"sets", "with_additions", "additions"} and the effects added."""
    hits = []
    for seed in seeds:
        rows = strip_sets.strip_set("clean", seed, n_points=n_points, reps=reps)
        added = loop.select_effects(rows, seed=seed, report=False)["added"]
        if added:
            hits.append({"seed": seed, "added": added})
    return {"sets": len(seeds), "n_points": n_points, "reps": reps, "with_additions": len(hits),
            "additions": hits}


def summarise(records):
    """Per case: seeds, recovery rate per effect, false additions, held-out / floor."""
    table = []
    for case in dict.fromkeys(r["case"] for r in records):
        rs = [r for r in records if r["case"] == case]
        rec = {e: sum(r["found"][e] for r in rs) / len(rs) for e in rs[0]["present"]}
        ratio = np.array([r["heldout_over_floor"] for r in rs])
        ratio_true = np.array([r["heldout_over_true_noise"] for r in rs])
        ratio_ho = np.array([r.get("heldout_over_held_out_floor", np.nan) for r in rs])
        row = {"case": case, "seeds": len(rs), "recovery": rec,
               "all_found_rate": sum(all(r["found"].values()) for r in rs) / len(rs),
               "false_additions": sum(len(r["false_additions"]) for r in rs),
               "heldout_over_floor_mean": float(ratio.mean()), "heldout_over_floor_max": float(ratio.max()),
               "heldout_over_true_noise_mean": float(ratio_true.mean()),
               "heldout_over_held_out_floor_mean": float(ratio_ho.mean()),
               "heldout_over_held_out_floor_max": float(ratio_ho.max()),
               "error_before_over_floor_mean": float(np.mean([r["error_before"] / r["noise_relative"] for r in rs])),
               "seconds_mean": float(np.mean([r["seconds"] for r in rs]))}
        if "oracle_noncentrality_without" in rs[0]:
            row["oracle_min_noncentrality"] = {e: float(min(r["oracle_noncentrality_without"][e] for r in rs))
                                               for e in rs[0]["present"]}
        table.append(row)
    return table


def print_table(table, out=sys.stdout):
    print("| case | seeds | recovery per effect (found/present) | all found | false additions | "
          "held-out / floor mean (max) | held-out / held-out floor mean (max) | held-out / true noise | "
          "before / floor | min noncentrality |", file=out)
    print("|---|---|---|---|---|---|---|---|---|---|", file=out)
    for t in table:
        rec = ", ".join(f"{e} {v:.2f}" for e, v in t["recovery"].items()) or "-"
        print(f"| {t['case']} | {t['seeds']} | {rec} | {t['all_found_rate']:.2f} | {t['false_additions']} | "
              f"{t['heldout_over_floor_mean']:.3f} ({t['heldout_over_floor_max']:.3f}) | "
              f"{t['heldout_over_held_out_floor_mean']:.3f} ({t['heldout_over_held_out_floor_max']:.3f}) | "
              f"{t['heldout_over_true_noise_mean']:.3f} | {t['error_before_over_floor_mean']:.2f} | "
              f"{', '.join(f'{v:.0f}' for v in t.get('oracle_min_noncentrality', {}).values()) or '-'} |", file=out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=10, help="seeds per case (0 .. N-1)")
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="3 seeds")
    ap.add_argument("--cases", default="", help="comma-separated case names (default: all)")
    ap.add_argument("--n-points", type=int, default=24, help="design points per set")
    ap.add_argument("--reps", type=int, default=3, help="replicates per design point")
    ap.add_argument("--no-oracle", action="store_true")
    ap.add_argument("--clean-seeds", type=int, default=40,
                    help="clean sets (with replicates, and without: n-points x reps single strips) on which the "
                         "selection's false additions are counted (0: skip)")
    ap.add_argument("--out", default="out/validation")
    ap.add_argument("--from-json", default=None,
                    help="summarise the records of an earlier run's loop_recovery.json instead of running")
    ap.add_argument("--baseline", default=None,
                    help="an earlier run's loop_recovery.json (e.g. of the loop before a change) whose summary "
                         "is kept beside this one for comparison")
    a = ap.parse_args(argv)
    if a.from_json:
        with open(a.from_json) as fh:
            earlier = json.load(fh)
        records, command = earlier["records"], earlier["command"]
        a.n_points, a.reps = earlier["n_points"], earlier["reps"]
    else:
        cases = [c for c in a.cases.split(",") if c] or list(strip_sets.CASES)
        seeds = range(a.first_seed, a.first_seed + (3 if a.quick else a.seeds))
        records = []
        for case in cases:
            for seed in seeds:
                r = run_case(case, seed, a.n_points, a.reps, with_oracle=not a.no_oracle)
                records.append(r)
                print(json.dumps(r), flush=True)
        command = "python studies/loop_recovery.py " + " ".join(argv if argv is not None else sys.argv[1:])
    table = summarise(records)
    print_table(table)
    out = {"command": command, "n_points": a.n_points, "reps": a.reps, "noise_relative": strip_sets.NOISE,
           "records": records, "summary": table}
    if a.from_json and "clean_false_additions" in earlier:
        out["clean_false_additions"] = earlier["clean_false_additions"]
    elif a.clean_seeds and not a.from_json:
        seeds = list(range(1000, 1000 + a.clean_seeds))
        out["clean_false_additions"] = [clean_false_additions(seeds, a.n_points, a.reps),
                                        clean_false_additions(seeds, a.n_points * a.reps, 1)]
        for c in out["clean_false_additions"]:
            print(f"clean sets ({c['n_points']} points x {c['reps']}): {c['with_additions']} of {c['sets']} "
                  f"with a false addition {[h['added'] for h in c['additions']]}")
    if a.baseline:
        with open(a.baseline) as fh:
            base = json.load(fh)
        out["baseline"] = {"command": base["command"], "note": base.get("note", ""),
                           "summary": summarise(base["records"])}
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "loop_recovery.json"), "w") as fh:
        json.dump(out, fh, indent=2)


if __name__ == "__main__":
    main()
