"""The fabric test folder as a lab writes it (seed 4.3-4.4): meta.json, tensile_<deg>deg_<pct>pct.csv,
shear_<deg>deg.csv and cantilever.csv, read and checked with one-line errors naming file, row
and column. Units: mm, N; see validation/data/README.md for the schemas."""
from __future__ import annotations

import math
import os
import re

import numpy as np

from shellfem.errors import SelfshapeError
from validation.textfiles import read_csv_rows, read_json

DEFAULT_POISSON = 0.3  # seed 4.3: measured from videos of a uniaxial test

TENSILE_COLUMNS = {"time_s": "float", "cycle": "int", "branch": ("load", "unload"),
                   "extension_mm": "float", "load_N": "float"}
SHEAR_COLUMNS = {"lateral_displacement_mm": "float", "lateral_load_N": "float"}
CANTILEVER_COLUMNS = {"orientation_deg": "float", "face_up": ("front", "back"), "free_length_mm": "float",
                      "areal_weight_N_per_mm2": "float", "height_over_width": "float"}
META_KEYS = ("fabric_thickness_mm", "tensile_width_mm", "tensile_gauge_length_mm", "shear_sample_side_mm")
#: physical upper bounds of meta.json's sizes (mm): a fabric, a test-machine specimen
META_MAX = {"fabric_thickness_mm": 20.0, "tensile_width_mm": 1000.0, "tensile_gauge_length_mm": 1000.0,
            "shear_sample_side_mm": 1000.0}

#: Most data rows of one test file: the shipped tensile curves have 720, a 1 kHz logger over
#: 3 minutes 180,000; the fits evaluate every row per iteration, so 1.9 million rows (60 MB)
#: ran for minutes (issue 19).
MAX_TABLE_ROWS = 200_000

_TENSILE_RE = re.compile(r"^tensile_(\d+(?:\.\d+)?)deg_(\d+(?:\.\d+)?)pct\.csv$")
_SHEAR_RE = re.compile(r"^shear_(\d+(?:\.\d+)?)deg\.csv$")


# ----------------------------------------------------------------------------- reading

def number_key(x: float) -> str:
    """'0', '15', '45', '37.5': the key of an orientation or stretch percent."""
    return f"{float(x):g}"


def read_table(path: str, columns: dict) -> dict:
    """Read a CSV whose header must be exactly the keys of columns.

    columns maps name -> "float" | "int" | tuple of allowed strings. Returns name -> array.
    Raises SelfshapeError (file, row, column) on a missing/extra/duplicate column, a short
    or long row, an empty or non-numeric cell, a non-finite number, an unknown label, or no rows.
    """
    name = os.path.basename(path)
    rows = read_csv_rows(path, "CSV table")
    rows = [r for r in rows if any(c.strip() for c in r)]
    if not rows:
        raise SelfshapeError(f"{name}: empty file (expected header {','.join(columns)})")
    header = [c.strip() for c in rows[0]]
    dup = sorted({c for c in header if header.count(c) > 1})
    if dup:
        raise SelfshapeError(f"{name}: duplicate column(s) {', '.join(dup)}")
    missing = [c for c in columns if c not in header]
    if missing:
        raise SelfshapeError(f"{name}: missing column(s) {', '.join(missing)}")
    extra = [c for c in header if c not in columns]
    if extra:
        raise SelfshapeError(f"{name}: unexpected column(s) {', '.join(extra)}")
    body = rows[1:]
    if not body:
        raise SelfshapeError(f"{name}: no data rows after the header")
    if len(body) > MAX_TABLE_ROWS:
        raise SelfshapeError(f"{name}: {len(body)} data rows, more than the {MAX_TABLE_ROWS:,} a test file may hold "
                             f"(resample it: the fits' time grows with the rows)")
    out = {}
    for j, col in enumerate(header):
        kind = columns[col]
        vals = []
        for i, r in enumerate(body, start=1):
            if len(r) != len(header):
                raise SelfshapeError(f"{name}: row {i}: expected {len(header)} fields, got {len(r)}")
            cell = r[j].strip()
            where = f"{name}: row {i}, column {col}"
            if cell == "":
                raise SelfshapeError(f"{where}: empty cell")
            if isinstance(kind, tuple):
                if cell not in kind:
                    raise SelfshapeError(f"{where}: unknown value {cell!r} (expected one of {', '.join(kind)})")
                vals.append(cell)
                continue
            try:
                v = float(cell)
            except ValueError:
                raise SelfshapeError(f"{where}: {cell!r} is not a number") from None
            if not math.isfinite(v):
                raise SelfshapeError(f"{where}: {cell!r} is not finite")
            if kind == "int":
                if v != int(v):
                    raise SelfshapeError(f"{where}: {cell!r} is not an integer")
                v = int(v)
            vals.append(v)
        out[col] = np.array(vals, dtype=object if isinstance(kind, tuple) else
                            (np.int64 if kind == "int" else float))
        if isinstance(kind, tuple):
            out[col] = out[col].astype(str)
    return out


def read_meta(folder: str) -> dict:
    """meta.json of a fabric test folder: thickness and sample geometry (mm), all > 0.

    Optional "poisson" overrides the default Poisson's ratio 0.3.
    """
    path = os.path.join(folder, "meta.json")
    if not os.path.exists(path):
        raise SelfshapeError(f"{path}: missing (thickness and sample geometry are read from it)")
    meta = read_json(path, "meta.json object")
    if not isinstance(meta, dict):
        raise SelfshapeError(f"{path}: expected a JSON object")
    out = dict(meta)
    for k in META_KEYS:
        if k not in meta:
            raise SelfshapeError(f"{path}: missing key {k!r}")
        v = meta[k]
        top = META_MAX[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not 0 < v <= top:
            raise SelfshapeError(f"{path}: {k} must be a number in (0, {top:g}] mm, got {v!r}")
        out[k] = float(v)
    nu = meta.get("poisson", DEFAULT_POISSON)
    if isinstance(nu, bool) or not isinstance(nu, (int, float)) or not (-1.0 < nu < 1.0):
        raise SelfshapeError(f"{path}: poisson must be a number in (-1, 1), got {nu!r}")
    out["poisson"] = float(nu)
    return out


def read_tensile(path: str) -> dict:
    """A tensile_<deg>deg_<pct>pct.csv table (cycles integers >= 1, branch load/unload)."""
    t = read_table(path, TENSILE_COLUMNS)
    bad = np.flatnonzero(t["cycle"] < 1)
    if bad.size:
        raise SelfshapeError(f"{os.path.basename(path)}: row {bad[0] + 1}, column cycle: must be >= 1")
    return t


def read_shear(path: str) -> dict:
    return read_table(path, SHEAR_COLUMNS)


def read_cantilever(path: str) -> dict:
    """cantilever.csv: lengths, weights and aspect ratios > 0, aspect ratios within the heavy
    elastica's tabulated range (a ribbon hanging nearly vertical does not measure k_B)."""
    from validation.elastica import master_curve_table
    t = read_table(path, CANTILEVER_COLUMNS)
    name = os.path.basename(path)
    for col, top in (("free_length_mm", 1e4), ("areal_weight_N_per_mm2", 1e-2), ("height_over_width", np.inf)):
        bad = np.flatnonzero(t[col] <= 0)
        if bad.size:
            raise SelfshapeError(f"{name}: row {bad[0] + 1}, column {col}: must be > 0")
        bad = np.flatnonzero(t[col] > top)
        if bad.size:
            raise SelfshapeError(f"{name}: row {bad[0] + 1}, column {col}: {t[col][bad[0]]:g} is beyond {top:g}")
    r_max = float(master_curve_table()[1][-1])
    bad = np.flatnonzero(t["height_over_width"] > r_max)
    if bad.size:
        raise SelfshapeError(f"{name}: row {bad[0] + 1}, column height_over_width: {t['height_over_width'][bad[0]]:g} "
                             f"is beyond the heavy elastica's range ({r_max:.4g}: the ribbon hangs vertically)")
    return t


def find_test_files(folder: str) -> dict:
    """Locate the tests in folder: {"tensile": {pct: {deg: path}}, "shear": {deg: path},
    "cantilever": path}. Other files are ignored; missing kinds raise SelfshapeError."""
    if not os.path.isdir(folder):
        raise SelfshapeError(f"{folder}: not a directory (expected a fabric test folder)")
    tensile, shear = {}, {}
    for fn in sorted(os.listdir(folder)):
        m = _TENSILE_RE.match(fn)
        if m:
            tensile.setdefault(number_key(m.group(2)), {})[number_key(m.group(1))] = os.path.join(folder, fn)
            continue
        m = _SHEAR_RE.match(fn)
        if m:
            shear[number_key(m.group(1))] = os.path.join(folder, fn)
    if not tensile:
        raise SelfshapeError(f"{folder}: no tensile_<deg>deg_<pct>pct.csv files")
    for pct, files in tensile.items():
        for need in ("0", "90"):
            if need not in files:
                raise SelfshapeError(f"{folder}: missing tensile_{int(float(need)):02d}deg_{pct}pct.csv "
                                     f"(the 0 and 90 deg tests define the model at {pct} %)")
    if not shear:
        raise SelfshapeError(f"{folder}: no shear_<deg>deg.csv file")
    cant = os.path.join(folder, "cantilever.csv")
    if not os.path.isfile(cant):
        raise SelfshapeError(f"{folder}: missing cantilever.csv")
    return {"tensile": tensile, "shear": shear, "cantilever": cant}
