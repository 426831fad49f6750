"""model.json, the fitted strip model that ``selfshape validate`` writes and ``selfshape
predict`` applies, checked key by key before it is used: readable UTF-8 JSON, the format tag,
known effects, one finite number per parameter within the loop's search bounds, finite
auxiliary data, the other keys `validate` writes agreeing with what predict applies (base
model, narrow mode, measured column, reference stretch and thickness, parameter names,
per-effect parameters, standard errors), no unknown key, and predictions that are finite
for every row of the data. Every problem is
a one-line SelfshapeError naming the file and the key (or the data row), so a malformed or
NaN-carrying model can never predict NaN. Units: curvatures 1/mm, thicknesses mm."""
from __future__ import annotations

import math
import os
import re

import numpy as np

from shellfem.errors import SelfshapeError
from validation.textfiles import read_json, refuse_overwrite

_COLUMN = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,63}$")
#: The top-level keys of a model.json (validation.loop.model_dict writes them all).
MODEL_KEYS = ("format", "model", "mode", "measured_column", "effects", "parameter_names", "theta",
              "standard_errors", "aux", "reference_stretch", "reference_thickness_mm")


def _finite_tree(o, where, name):
    """Every number in o finite (booleans are not numbers here)."""
    if isinstance(o, dict):
        for k, v in o.items():
            _finite_tree(v, f"{where}.{k}", name)
    elif isinstance(o, list):
        for i, v in enumerate(o):
            _finite_tree(v, f"{where}[{i}]", name)
    elif isinstance(o, bool):
        raise SelfshapeError(f"{name}: {where}: expected a number or text, got {o!r}")
    elif isinstance(o, (int, float)) and not math.isfinite(o):
        raise SelfshapeError(f"{name}: {where}: {o!r} is not finite")


def check_model(m, path) -> dict:
    """The model dict m read from path, checked (see module doc); returns m."""
    from validation import effects as fx
    from validation.loop import FORMAT
    name = os.path.basename(str(path))
    if not isinstance(m, dict):
        raise SelfshapeError(f"{name}: expected a JSON object (a selfshape strip model), got {type(m).__name__}")
    if m.get("format") != FORMAT:
        raise SelfshapeError(f"{name}: key 'format': not a selfshape strip model ({FORMAT!r} expected, "
                             f"got {str(m.get('format'))[:40]!r})")
    for key in ("effects", "theta"):
        if key not in m:
            raise SelfshapeError(f"{name}: missing key {key!r}")
        if not isinstance(m[key], list):
            raise SelfshapeError(f"{name}: key {key!r}: expected a list, got {type(m[key]).__name__}")
    eff = []
    for i, e in enumerate(m["effects"]):
        where = f"effects[{i}]"
        if not isinstance(e, dict) or not isinstance(e.get("name"), str):
            raise SelfshapeError(f"{name}: {where}: expected an object with a 'name' string")
        if e["name"] not in fx.BY_NAME:
            raise SelfshapeError(f"{name}: {where}.name: unknown effect {e['name'][:60]!r} "
                                 f"(known: {', '.join(fx.BY_NAME)})")
        if fx.BY_NAME[e["name"]] in eff:
            raise SelfshapeError(f"{name}: {where}.name: effect {e['name']!r} listed twice")
        eff.append(fx.BY_NAME[e["name"]])
    names = fx.parameter_names(eff)
    theta = m["theta"]
    if len(theta) != len(names):
        raise SelfshapeError(f"{name}: key 'theta': {len(theta)} values, the effects need {len(names)} "
                             f"({', '.join(names)})")
    lo, hi = [1.0], [1e7]          # the loop's search range of the modulus ratio (effects.bounds_internal)
    for e in eff:
        for a, b in e.bounds:
            lo.append(a)
            hi.append(b)
    for i, (q, v) in enumerate(zip(names, theta)):
        where = f"theta[{i}] ({q})"
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise SelfshapeError(f"{name}: {where}: expected a number, got {str(v)[:40]!r}")
        if not math.isfinite(v):
            raise SelfshapeError(f"{name}: {where}: {v!r} is not finite")
        if not lo[i] <= v <= hi[i]:
            raise SelfshapeError(f"{name}: {where}: {v:g} outside its range [{lo[i]:g}, {hi[i]:g}]")
    aux = m.get("aux", {})
    if not isinstance(aux, dict):
        raise SelfshapeError(f"{name}: key 'aux': expected an object, got {type(aux).__name__}")
    for k, v in aux.items():
        if not isinstance(v, dict):
            raise SelfshapeError(f"{name}: aux.{k}: expected an object, got {type(v).__name__}")
    _finite_tree(aux, "aux", name)
    col = m.get("measured_column", "curvature_per_mm")
    if not isinstance(col, str) or not _COLUMN.match(col):
        raise SelfshapeError(f"{name}: key 'measured_column': expected a column name (letters, digits, _), "
                             f"got {str(col)[:40]!r}")
    _check_written_keys(m, names, theta, name)
    return m


def _same_number(a, b) -> bool:
    return isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a) and \
        abs(a - b) <= 1e-9 * max(abs(a), abs(b), 1e-300)


def _check_written_keys(m, names, theta, name) -> None:
    """The keys ``validate`` writes besides format/effects/theta/aux (validation.loop.model_dict)
    hold what predict assumes, and no other key is present: predict implements one base model
    (``model``), the narrow strip (``mode``), the curvature column, the loop's reference stretch
    and thickness; a file saying otherwise, or whose ``parameter_names``, per-effect
    ``parameters`` or ``standard_errors`` disagree with ``theta``, was fitted for something else
    or edited, and was silently applied as if it said the defaults (issue 19)."""
    from geometry.schema import check_keys
    from validation import effects as fx
    from validation.strips import MEASURED, model_source
    check_keys(m, MODEL_KEYS, name)
    expected = {"model": model_source(), "mode": "narrow", "measured_column": MEASURED}
    for key, want in expected.items():
        if key in m and m[key] != want:
            raise SelfshapeError(f"{name}: key {key!r}: predict applies {want!r}, the file says {str(m[key])[:60]!r}")
    for key, want in (("reference_stretch", fx.REFERENCE_STRETCH), ("reference_thickness_mm", fx.REFERENCE_THICKNESS)):
        if key in m and not _same_number(m[key], want):
            raise SelfshapeError(f"{name}: key {key!r}: the effects are parametrised at {want:g}, "
                                 f"the file says {str(m[key])[:40]!r}")
    if "parameter_names" in m and m["parameter_names"] != names:
        raise SelfshapeError(f"{name}: key 'parameter_names': {str(m['parameter_names'])[:80]} is not the effects' "
                             f"{names} (theta follows the effects)")
    if "standard_errors" in m:
        se = m["standard_errors"]
        if not isinstance(se, list) or len(se) != len(names):
            raise SelfshapeError(f"{name}: key 'standard_errors': expected a list of {len(names)} numbers")
        for i, v in enumerate(se):
            if v is not None and not (isinstance(v, (int, float)) and not isinstance(v, bool)
                                      and math.isfinite(v) and v >= 0):
                raise SelfshapeError(f"{name}: standard_errors[{i}]: expected a finite number >= 0 or null, "
                                     f"got {str(v)[:40]!r}")
    value = dict(zip(names, theta))
    for i, e in enumerate(m["effects"]):
        check_keys(e, ("name", "parameters"), f"{name}: effects[{i}]")
        params = e.get("parameters", {})
        if not isinstance(params, dict):
            raise SelfshapeError(f"{name}: effects[{i}].parameters: expected an object")
        for q, v in params.items():
            if q not in value or not q.startswith(e["name"] + ".") or not _same_number(v, value[q]):
                raise SelfshapeError(f"{name}: effects[{i}].parameters.{str(q)[:60]}: does not match theta "
                                     f"({str(v)[:30]} against {value.get(q)})")


def load_checked_model(path) -> dict:
    """read and check a model.json (see check_model)."""
    return check_model(read_json(path, "selfshape strip model (model.json)"), path)


def check_predict(model_path, data_path, out_path) -> None:
    """Everything ``selfshape predict`` needs, checked before anything is written: the output
    is neither input, the model is well formed, the data read, and every predicted curvature
    is finite (else the row is named)."""
    from validation.loop import predict_rows
    from validation.strips import read_strips
    from shellfem.outfiles import check_output_file
    refuse_overwrite(out_path, [model_path, data_path])
    check_output_file(out_path, inputs=[model_path, data_path])     # the output, before any prediction
    model = load_checked_model(model_path)
    rows = read_strips(data_path, require_measured=False)
    name = os.path.basename(str(model_path))
    try:
        with np.errstate(all="ignore"):
            pred = np.asarray(predict_rows(model, rows), float)
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise SelfshapeError(f"{name}: key 'aux': malformed auxiliary data of the effects "
                             f"({type(e).__name__}: {' '.join(str(e).split())[:80]})") from None
    bad = np.flatnonzero(~np.isfinite(pred))
    if bad.size:
        i = int(bad[0])
        raise SelfshapeError(f"{os.path.basename(str(data_path))}: row {i + 1} (specimen {rows['specimen'][i]}): "
                             f"the model {name} predicts no finite curvature")
