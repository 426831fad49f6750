"""The curvature law's generation timed serially and on the local Dask cluster in one run (issue 21's
figure: the wall-time ratio serial / cluster on the machine's cores).

Runs validation.law_tables.main (studies/thickness_law_sim.py) twice on the same grid, serially in
this process and with ``--workers N`` (a LocalCluster of N single-threaded processes, its start
included), in the order asked, and prints ONE JSON line: both wall times (s), their ratio, the
1-minute load average before, between and after (the machine's other work moves such a ratio
more than anything else), and whether the two tables and their rows are identical (they must
be: the same simulations, only their placement differs). The default grid is the one of
docs/notes.md "Sweeps on Dask": t 0.2/0.3 mm x mu2 3.9/6.5 mm, 3 rows x 2 motifs, mesh 3 mm, one
triangle row across a ribbon, the front simulated and the back mirrored with one simulated
check row (5 simulations), the plastic of the measured strips. A few minutes on 2 cores.

    python studies/law_cluster_speedup.py [--workers 2] [--cluster-first] [--out out/law_speedup]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import time

from validation.law_tables import main as law_main

GRID = ["--model", "sim", "--thickness", "0.2", "0.3", "--spacing", "3.9", "6.5", "--rows", "3", "--motifs", "2",
        "--mesh-size", "3", "--across", "1", "--back", "mirror", "-q",
        "--calibration", os.path.join("inverse", "data", "strips_S1_calibration.json")]


def timed_law(extra: list, out_csv: str) -> dict:
    """One law generation (GRID + ``extra``) into ``out_csv``: wall time (s), exit status, the
    simulated rows without their per-row times, and the table's data lines (no header)."""
    buf = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(buf):
        rc = law_main(GRID + extra + ["--out", out_csv])
    wall = time.perf_counter() - t0
    rows = [{k: v for k, v in r.items() if k != "time_s"} for r in json.loads(buf.getvalue())["rows"]]
    with open(out_csv) as f:
        table = [line for line in f if not line.startswith("#")]
    return {"wall_s": wall, "rc": rc, "rows": rows, "table": table}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2, help="local cluster processes (default 2)")
    ap.add_argument("--cluster-first", action="store_true", help="time the cluster run first")
    ap.add_argument("--out", default="out/law_speedup", help="folder of the two tables")
    a = ap.parse_args(argv)
    if a.workers < 1:
        ap.error(f"--workers must be >= 1, got {a.workers}")
    os.makedirs(a.out, exist_ok=True)
    runs = [("serial", []), ("cluster", ["--workers", str(a.workers)])]
    if a.cluster_first:
        runs.reverse()
    load, got = [os.getloadavg()[0]], {}
    for name, extra in runs:
        got[name] = timed_law(extra, os.path.join(a.out, f"{name}.csv"))
        load.append(os.getloadavg()[0])
    s, c = got["serial"], got["cluster"]
    print(json.dumps({"order": [n for n, _ in runs], "workers": a.workers, "serial_s": round(s["wall_s"], 1),
                      "cluster_s": round(c["wall_s"], 1), "ratio": round(s["wall_s"] / c["wall_s"], 2),
                      "load_average_1min": [round(x, 2) for x in load], "simulations": len(s["rows"]),
                      "identical": s["rows"] == c["rows"] and s["table"] == c["table"] and s["rc"] == c["rc"] == 0}))
    return 0 if s["rc"] == c["rc"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
