"""Bending modes of the orthotropic ribbon sweep (studies/ortho_sweep.py, seed section 4.1).

A row is one simulated case: thickness_mm, pitch_mm, course_deg (0 or 90), seed, converged,
kappa_along_per_mm, kappa_across_per_mm (median curvatures along and across the ribbons, 1/mm)
and mode ("along" when |kappa_along| > |kappa_across|, else "across"). The seed's effect is
reproduced at a (thickness, pitch) where the two course orientations give different modes.
"""
from __future__ import annotations


def _along_over_across(row: dict) -> float:
    return round(abs(row["kappa_along_per_mm"]) / max(abs(row["kappa_across_per_mm"]), 1e-12), 3)


def summarise(rows: list, seed: int = 0) -> list:
    """Per (thickness, pitch) with both orientations converged (solver seed ``seed``): the modes
    and whether they differ."""
    out = []
    rows = [r for r in rows if r.get("seed", 0) == seed]
    keys = sorted({(r["thickness_mm"], r["pitch_mm"]) for r in rows})
    for t, p in keys:
        by = {r["course_deg"]: r for r in rows if (r["thickness_mm"], r["pitch_mm"]) == (t, p) and r["converged"]}
        if 0.0 in by and 90.0 in by:
            out.append({"thickness_mm": t, "pitch_mm": p, "mode_0": by[0.0]["mode"], "mode_90": by[90.0]["mode"],
                        "ratio_0": _along_over_across(by[0.0]), "ratio_90": _along_over_across(by[90.0]),
                        "modes_differ": by[0.0]["mode"] != by[90.0]["mode"]})
    return out


def markdown_table(rows: list) -> str:
    """One line per (thickness, pitch) at seed 0; other seeds' modes, where run, in the last column."""
    lines = ["| thickness (mm) | pitch (mm) | course 0 deg: along/across, mode | course 90 deg: along/across, mode | "
             "modes differ | other seeds (0 / 90 deg modes) |", "|---|---|---|---|---|---|"]
    seeds = sorted({r.get("seed", 0) for r in rows} - {0})
    other = {sd: {(s["thickness_mm"], s["pitch_mm"]): s for s in summarise(rows, sd)} for sd in seeds}
    for s in summarise(rows):
        key = (s["thickness_mm"], s["pitch_mm"])
        more = "; ".join(f"seed {sd}: {other[sd][key]['mode_0']} / {other[sd][key]['mode_90']}"
                         for sd in seeds if key in other[sd])
        lines.append(f"| {s['thickness_mm']:g} | {s['pitch_mm']:g} | {s['ratio_0']:.2f}, {s['mode_0']} | "
                     f"{s['ratio_90']:.2f}, {s['mode_90']} | {'yes' if s['modes_differ'] else 'no'} | {more} |")
    return "\n".join(lines)
