"""Contact on a rolled tube: a star pattern simulated without and with self-contact (issue 20).

For each pattern (default: the gallery's tube, examples/gallery/tube.toml) the study solves the
same mesh twice, ``[contact] enabled = false`` and ``true`` (nested iteration as `selfshape
simulate` does), and reports per run: converged, Newton iterations, wall time (s), energy (N mm),
whether the deployed surface intersects itself (ipctk, non-excluded parts) and the smallest
distance between parts of the sheet printed far apart (exact triangle distances over the pairs a
KD-tree finds within reach; mm; the offset is the sheet's largest total thickness), the active
contact pairs; and writes a picture of each deployed shape (forward.render) to the output folder.

    python studies/contact_tube.py [--pattern examples/gallery/tube.toml ...] [--out out/contact_tube]
        [--max-iterations N]

prints ONE JSON line and writes OUT/contact_tube.json and OUT/<name>_{off,on}.png.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np


def _far_min_distance(sim, contact):
    """Smallest exact distance (mm) between triangles farther apart in the printed state than the
    contact's exclusion (tests/test_contact.far_pairs_min_distance), inf if none is within reach."""
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))
    from test_contact import far_pairs_min_distance
    sheet = sim.sheet
    edge = float(np.linalg.norm(np.diff(sheet.points[sheet.triangles][:, [0, 1, 2, 0]], axis=1), axis=2).max())
    return far_pairs_min_distance(sheet, sim.positions, np.sqrt(2) * contact.exclusion_mm,
                                  contact.offset + 2 * edge)


def run_pattern(path: str, out: str, max_iterations: int | None = None) -> dict:
    from forward.render import render_deployed
    from forward.simulate import make_contact, simulate
    from geometry.patterns import load_pattern

    name = os.path.splitext(os.path.basename(path))[0]
    rows = {}
    for on in (False, True):
        pat = load_pattern(path)
        pat.contact = on
        t0 = time.perf_counter()
        sim = simulate(pat, max_iterations=max_iterations)
        wall = time.perf_counter() - t0
        c = sim.model.contact or make_contact(sim.sheet, pat.fabric, sim.fixed, True, None)
        rep = sim.contact_report() if on else {}
        tag = "on" if on else "off"
        render_deployed(sim, os.path.join(out, f"{name}_{tag}.png"), title=f"{name}: contact {tag}")
        d = _far_min_distance(sim, c)
        rows[tag] = dict(converged=bool(sim.result.converged), reason=sim.result.reason,
                         iterations=int(sim.result.iterations), wall_s=round(wall, 1),
                         energy_nmm=float(sim.result.energy), intersects=bool(c.intersects(sim.positions)),
                         far_min_distance_mm=None if not np.isfinite(d) else round(d, 4),
                         offset_mm=c.offset, active_pairs=int(rep.get("active_pairs", 0)),
                         contact_builds=int(c.builds), contact_skips=int(c.skips),
                         contact_cuts=int(sim.result.timings.get("contact_cuts", 0)))
    rows["n_vertices"] = int(sim.sheet.n_vertices)
    rows["time_ratio"] = round(rows["on"]["wall_s"] / max(rows["off"]["wall_s"], 1e-9), 2)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pattern", nargs="+", default=["examples/gallery/tube.toml"])
    ap.add_argument("--out", default="out/contact_tube")
    ap.add_argument("--max-iterations", type=int, default=None)
    a = ap.parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    result = {os.path.basename(p): run_pattern(p, a.out, a.max_iterations) for p in a.pattern}
    with open(os.path.join(a.out, "contact_tube.json"), "w") as f:
        json.dump(result, f, indent=1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
