"""``selfshape law build``: a curvature-law table from measured (or simulated) calibration patches.

Input: a ``law_measurements.csv`` (the template of ``selfshape calibration-print law``,
validation.calibration_prints; schema in docs/calibration-prints.md) with ``kappa_per_mm``
filled for every patch. Output: the law CSV the designer reads (inverse.thickness_law: columns
thickness_mm, spacing_mm, side, kappa_per_mm, the ``# fabric_stretch = s`` key, provenance
comment lines naming the source file), the same format as the shipped
inverse/data/thickness_law_s<s>.csv, which ``selfshape design --law`` takes.

Why this checks rather than repairs: the designer inverts kappa(thickness) per spacing, so the
table must be a full grid per side (>= 2 thicknesses x >= 2 spacings) and kappa strictly
monotone in thickness, in one direction per side. A lab's table that is not is reported cell by
cell (what is missing, which step is not monotone, with the patch ids) in one line; nothing is
dropped, interpolated or smoothed on the lab's behalf. The lab chooses the sub-grid it trusts
with ``thickness`` / ``spacing`` (``--thickness`` / ``--spacing``), re-measures, or fills the
back from the front (``mirror_back``, as the shipped laws were made).

Replicates (several patches of one side, thickness and spacing) are averaged; their count and
spread go into the provenance. Units: mm, 1/mm.
"""
from __future__ import annotations

import datetime
import hashlib
import os

import numpy as np

from shellfem.errors import SelfshapeError, check_number
from shellfem.outfiles import check_output_file, write_text_file
from validation.textfiles import read_csv_rows, read_text, refuse_overwrite

REQUIRED = ("patch", "side", "stretch", "thickness_mm", "spacing_mm", "kappa_per_mm")
OPTIONAL_NUMERIC = ("kappa_across_per_mm", "contraction_along", "contraction_across", "ribbon_length_mm",
                    "ribbon_width_mm", "ribbon_gap_mm")
#: physical range of each numeric column: a printable thickness, a spacing on a bed, a curvature
#: of radius >= 0.1 mm (both curvatures are magnitudes, docs/calibration-prints.md, as the
#: simulated fills write them), a contraction factor (printed / deployed) of a fabric that
#: stretches <= 5x
RANGES = {"stretch": (1.0, 5.0), "thickness_mm": (1e-3, 10.0), "spacing_mm": (0.1, 1e3),
          "kappa_per_mm": (0.0, 10.0), "kappa_across_per_mm": (0.0, 10.0), "contraction_along": (0.1, 10.0),
          "contraction_across": (0.1, 10.0), "ribbon_length_mm": (0.1, 1e3), "ribbon_width_mm": (0.1, 1e3),
          "ribbon_gap_mm": (0.0, 1e3)}
SIDES = ("front", "back")
MAX_LISTED = 12       # problems named in the one-line error (the rest are counted)


def _problems_line(name, what, problems, hint=""):
    shown = "; ".join(problems[:MAX_LISTED])
    more = f"; and {len(problems) - MAX_LISTED} more" if len(problems) > MAX_LISTED else ""
    return f"{name}: {what}: {shown}{more}" + (f" ({hint})" if hint else "")


def read_measurements(path) -> dict:
    """Read and check a law_measurements.csv. Lines whose first cell starts with ``#`` are
    comments (kept). Returns {"cells": list of per-row dicts (patch, side, stretch, thickness_mm,
    spacing_mm, kappa_per_mm, optional columns, note), "comments", "file", "sha256"}.

    Every problem of every row (an empty or non-numeric measurement, a value outside RANGES, a
    bad side, a missing patch id, a patch id given to two rows) is collected and raised as ONE
    SelfshapeError line naming the file and, per problem, the patch id and the column. A
    repeated id is refused rather than read as a replicate: it is a row pasted twice or a
    mislabelled patch, and averaging or placing it would be a silent guess (a replicate
    has its own id: ``calibration-print law --repetitions``)."""
    name = os.path.basename(str(path))
    text = read_text(path, "law_measurements CSV")
    table = read_csv_rows(path, "law_measurements CSV")
    comments = [",".join(r).rstrip(",").strip()[1:].strip() for r in table if r and r[0].strip().startswith("#")]
    table = [r for r in table if any(c.strip() for c in r) and not r[0].strip().startswith("#")]
    if not table:
        raise SelfshapeError(f"{name}: no header line (expected columns {', '.join(REQUIRED)})")
    header = [h.strip() for h in table[0]]
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise SelfshapeError(f"{name}: missing column(s) {', '.join(missing)} in the header")
    if len(set(header)) != len(header):
        raise SelfshapeError(f"{name}: duplicate column names in the header")
    body = table[1:]
    if not body:
        raise SelfshapeError(f"{name}: no data rows (one row per printed patch)")
    col = {h: i for i, h in enumerate(header)}
    problems, cells, first_row = [], [], {}
    for i, r in enumerate(body):
        if len(r) != len(header):
            pid = r[col["patch"]].strip() if len(r) > col["patch"] else ""
            problems.append(f"{f'patch {pid} (row {i + 1})' if pid else f'row {i + 1}'}: {len(r)} fields, the header "
                            f"has {len(header)} (a decimal comma? write 0.18, not 0,18)")
            continue
        get = lambda c: r[col[c]].strip() if c in col else ""  # noqa: E731
        pid = get("patch")
        who = f"patch {pid}" if pid else f"row {i + 1}"
        if not pid:
            problems.append(f"row {i + 1}, column patch: empty")
        elif pid in first_row:
            problems.append(f"patch {pid} (row {i + 1}), column patch: the id of row {first_row[pid]} too (a row "
                            f"pasted twice or a mislabelled patch; every printed patch has its own id)")
        else:
            first_row[pid] = i + 1
        cell = {"patch": pid or f"row {i + 1}", "row": i + 1, "note": get("note")}
        side = get("side").lower()
        if side not in SIDES:
            problems.append(f"{who}, column side: must be front or back, got {get('side')!r}")
        cell["side"] = side
        for c in REQUIRED[2:] + OPTIONAL_NUMERIC:
            t = get(c)
            if not t:
                if c in REQUIRED:
                    why = f" ({cell['note']})" if cell["note"] and c == "kappa_per_mm" else ""
                    problems.append(f"{who}, column {c}: empty{why}")
                continue
            lo, hi = RANGES[c]
            try:
                cell[c] = check_number("", t, lo=lo, hi=hi)
            except SelfshapeError as e:
                msg = str(e).strip()
                problems.append(f"{who}, column {c}: {msg}" if "must be" in msg else f"{who}, column {c}: {t!r}")
        cells.append(cell)
    if problems:
        what = f"{len(problems)} unusable entr{'y' if len(problems) == 1 else 'ies'}"
        hint = ("fill in every patch's kappa_per_mm as a number in 1/mm" if all(", column kappa_per_mm:" in p
                                                                             for p in problems)
                else "units and ranges: docs/calibration-prints.md, law_measurements.csv")
        raise SelfshapeError(_problems_line(name, what, problems, hint))
    s = np.array([c["stretch"] for c in cells])
    if np.ptp(s) > 1e-6:
        j = int(np.argmax(np.abs(s - s[0]) > 1e-6))
        raise SelfshapeError(f"{name}: patch {cells[j]['patch']}, column stretch: {s[j]:g}, but patch "
                             f"{cells[0]['patch']} has {s[0]:g}; a law holds at one fabric stretch (build one law "
                             f"per stretch)")
    return {"cells": cells, "comments": comments, "file": name,
            "sha256": hashlib.sha256(text.encode("utf-8")).hexdigest()}


def grid_table(m: dict, thickness=None, spacing=None, mirror_back=False) -> dict:
    """Per side the (thickness x spacing) grid of mean kappa, with replicate counts and patch
    ids, from read_measurements' cells restricted to ``thickness`` / ``spacing`` (mm lists,
    each value must occur). ``mirror_back``: the back grid is the front one (no back rows may be
    given then). Raises ONE SelfshapeError line naming every cell that is missing, every side
    with fewer than 2 thicknesses or spacings (too sparse to interpolate and invert) and every
    step of a spacing column that is not strictly monotone in thickness (in the side's direction)."""
    name = m["file"]
    cells = m["cells"]
    for what, sel, key in (("thickness", thickness, "thickness_mm"), ("spacing", spacing, "spacing_mm")):
        if sel is not None:
            have = {round(c[key], 9) for c in cells}
            for v in sel:
                if round(float(v), 9) not in have:
                    raise SelfshapeError(f"{name}: --{what} {float(v):g} mm: no patch has {key} {float(v):g} (has "
                                         f"{', '.join(f'{x:g}' for x in sorted(have))})")
            keep = {round(float(v), 9) for v in sel}
            cells = [c for c in cells if round(c[key], 9) in keep]
    sides = sorted({c["side"] for c in cells}, key=SIDES.index)
    if mirror_back:
        if "back" in sides:
            ids = [c["patch"] for c in cells if c["side"] == "back"][:3]
            raise SelfshapeError(f"{name}: --mirror-back copies the front grid to the back, but back patches are given "
                                 f"({', '.join(ids)}...): measured backs are used as they are (drop --mirror-back)")
        sides = ["front"]
    problems, grids = [], {}
    for side in SIDES:
        if side not in sides:
            if not mirror_back:
                problems.append(f"side {side}: no patch (print both sides, or --mirror-back to use the front "
                                f"grid for the back)")
            continue
        sc = [c for c in cells if c["side"] == side]
        T = np.unique([round(c["thickness_mm"], 9) for c in sc])
        S = np.unique([round(c["spacing_mm"], 9) for c in sc])
        if len(T) < 2 or len(S) < 2:
            ids = [c["patch"] for c in sc]
            problems.append(f"side {side}: {len(T)} thickness(es) x {len(S)} spacing(s), too sparse to invert (column "
                            f"thickness_mm has {', '.join(f'{x:g}' for x in T)}, "
                            f"spacing_mm {', '.join(f'{x:g}' for x in S)}"
                            f" over patches {', '.join(ids[:4])}{', ...' if len(ids) > 4 else ''}; the law needs >= 2 "
                            f"thicknesses and >= 2 spacings per side)")
            continue
        K = np.zeros((len(T), len(S)))
        n = np.zeros_like(K, dtype=int)
        sd = np.zeros_like(K)
        ids = [[[] for _ in S] for _ in T]
        vals = [[[] for _ in S] for _ in T]
        for c in sc:
            i, j = np.searchsorted(T, round(c["thickness_mm"], 9)), np.searchsorted(S, round(c["spacing_mm"], 9))
            vals[i][j].append(c["kappa_per_mm"])
            ids[i][j].append(c["patch"])
        for i in range(len(T)):
            for j in range(len(S)):
                if not vals[i][j]:
                    problems.append(f"side {side}, thickness {T[i]:g} mm, spacing {S[j]:g} mm: no patch (missing cell)")
                    continue
                v = np.asarray(vals[i][j])
                K[i, j], n[i, j], sd[i, j] = v.mean(), v.size, (v.std(ddof=1) if v.size > 1 else 0.0)
        if (n == 0).any():
            continue
        d = np.sign(np.diff(K, axis=0))
        direction = -1.0 if d.sum() < 0 else 1.0
        word = "decreasing" if direction < 0 else "increasing"
        for i, j in np.argwhere(d != direction):
            how = "equal" if d[i, j] == 0 else ("rises" if d[i, j] > 0 else "falls")
            problems.append(f"side {side}, spacing {S[j]:g} mm: not {word} in thickness between {T[i]:g} and "
                            f"{T[i + 1]:g} mm (kappa {K[i, j]:.4g} -> {K[i + 1, j]:.4g} 1/mm, {how}; patches "
                            f"{', '.join(ids[i][j] + ids[i + 1][j])})")
        grids[side] = {"thickness": T, "spacing": S, "kappa": K, "n": n, "sd": sd, "ids": ids, "direction": word}
    if problems:
        raise SelfshapeError(_problems_line(name, "cannot build a law", problems,
                                            "re-measure, or choose the trusted sub-grid with --thickness/--spacing"))
    if mirror_back:
        grids["back"] = dict(grids["front"], mirrored=True)
    return grids


def _git_hash() -> str:
    from validation.law_tables import git_hash
    return git_hash()


def build_law(measured_csv, out_path, *, thickness=None, spacing=None, mirror_back=False,
              plastic_young_modulus_mpa=None, calibration=None) -> dict:
    """Write the law table of ``measured_csv`` to ``out_path`` (checked before reading, written
    atomically, loadable by inverse.thickness_law: it is parsed before it is written). The
    plastic modulus key (``# plastic_young_modulus_mpa``, MPa) is ``plastic_young_modulus_mpa``
    if given, else the modulus ratio of ``calibration`` (the lab's `calibrate strips`
    parameters.json) x the fabric's E, as `calibration-print law --calibration` takes it, else
    the one the template states in its comments (a simulated fill), else absent. It matters
    downstream: `design --law` writes it into pattern.toml's [plastic], so a law without it is
    simulated (`--verify`) with the default plastic, not the lab's; the summary's
    ``plastic_source`` says which. Returns a summary dict (cells, sides, stretch, replicates,
    output, plastic modulus and its source)."""
    from inverse.thickness_law import PLASTIC_KEY, STRETCH_KEY, format_thickness_law, parse_thickness_law
    if plastic_young_modulus_mpa is not None and calibration is not None:
        raise SelfshapeError("--plastic-modulus and --calibration both state the plastic: give one")
    refuse_overwrite(out_path, [measured_csv, calibration])
    out = check_output_file(out_path, inputs=[p for p in (measured_csv, calibration) if p is not None],
                            suffix=".csv", what="law file (-o)")
    m = read_measurements(measured_csv)
    grids = grid_table(m, thickness, spacing, mirror_back)
    stretch = float(m["cells"][0]["stretch"])
    if stretch <= 1.0:
        raise SelfshapeError(f"{m['file']}: stretch {stretch:g}: a law needs pre-stretched fabric (stretch > 1)")
    modulus, source = None, None
    if plastic_young_modulus_mpa is not None:
        modulus = check_number("--plastic-modulus", plastic_young_modulus_mpa, lo=0.0, lo_open=True, hi=1e6)
        source = "--plastic-modulus"
    elif calibration is not None:
        from validation.calibration_prints import plastic_from_calibration
        _, plastic, source = plastic_from_calibration(calibration)
        modulus = plastic.young_modulus
    stated = [c.partition("=")[2].strip() for c in m["comments"] if c.partition("=")[0].strip() == PLASTIC_KEY]
    if modulus is None and stated:
        modulus = check_number(f"{m['file']}: comment {PLASTIC_KEY}", stated[0], lo=0.0, lo_open=True, hi=1e6)
        source = f"stated by {m['file']}"
    rows = []
    for side in SIDES:
        g = grids[side]
        for i, t in enumerate(g["thickness"]):
            for j, mu in enumerate(g["spacing"]):
                rows.append((float(t), float(mu), side, float(g["kappa"][i, j])))
    geo = {}
    for c in ("ribbon_length_mm", "ribbon_width_mm", "ribbon_gap_mm"):
        v = sorted({round(x[c], 6) for x in m["cells"] if c in x})
        geo[c] = v
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    reps = {s: int(grids[s]["n"].sum()) for s in SIDES}
    n_rep = sum(int((grids[s]["n"] > 1).sum()) for s in SIDES if not grids[s].get("mirrored"))
    head = [f"selfshape curvature law kappa(thickness, transverse spacing, side) at fabric stretch {stretch:g}",
            "columns: thickness_mm (printed plastic, mm), spacing_mm (transverse ribbon spacing mu2, printed mm),",
            "  side (front|back), kappa_per_mm (|normal curvature| along the ribbons, 1/mm of deployed length)",
            f"generated {stamp} by selfshape law build (validation.law_build), git {_git_hash()}",
            f"SOURCE: {m['file']} (sha256 {m['sha256'][:16]}), {len(m['cells'])} patch rows; "
            f"{n_rep} cell(s) averaged over replicates",
            "  ribbons " + ", ".join(f"{c.replace('ribbon_', '').replace('_mm', '')} "
                                     f"{'/'.join(f'{x:g}' for x in v) if v else '?'} mm" for c, v in geo.items()),
            f"  grid per side: thickness {', '.join(f'{x:g}' for x in grids['front']['thickness'])} mm x spacing "
            f"{', '.join(f'{x:g}' for x in grids['front']['spacing'])} mm; kappa {grids['front']['direction']} in "
            f"thickness (front)" + ("" if grids["back"].get("mirrored") else f", {grids['back']['direction']} (back)"),
            f"  patches per side: front {reps['front']}, back "
            + ("= front (--mirror-back: mirror symmetry through the fabric mid-surface)"
               if grids["back"].get("mirrored") else str(reps["back"]))]
    if thickness is not None or spacing is not None:
        head.append(f"  sub-grid chosen with --thickness {thickness or 'all'} --spacing {spacing or 'all'}")
    for side in SIDES:
        g = grids[side]
        if g.get("mirrored"):
            continue
        for i, j in np.argwhere(g["n"] > 1):
            head.append(f"  {side} t={g['thickness'][i]:g} mu2={g['spacing'][j]:g}: mean of {g['n'][i, j]} patches "
                        f"({', '.join(g['ids'][i][j])}), sd {g['sd'][i, j]:.3g} 1/mm")
    head += [f"  template: {c}" for c in m["comments"] if c.partition("=")[0].strip() not in (PLASTIC_KEY, STRETCH_KEY)]
    if modulus is not None:
        head.append(f"  plastic: {source}")
        head.append(f"{PLASTIC_KEY} = {modulus:.6g}")
    head.append(f"{STRETCH_KEY} = {stretch:g}")
    text = format_thickness_law(rows, head)
    parse_thickness_law(text, out)     # never write a table the designer cannot load
    write_text_file(out, text)
    return {"output": out, "stretch": stretch, "cells": len(rows), "patches": len(m["cells"]),
            "replicated_cells": n_rep, "plastic_young_modulus_mpa": modulus, "plastic_source": source,
            "thickness_mm": grids["front"]["thickness"].tolist(), "spacing_mm": grids["front"]["spacing"].tolist()}
