"""Parameter sweeps: `selfshape sweep SWEEP.toml -o DIR`, many simulations or designs as Dask tasks.

A sweep file (TOML, docs/sweeps.md) names a base pattern (each case: `selfshape simulate` of
it with some keys changed) or a list of targets (each case: `selfshape design` with some
options changed), and the values: a ``[grid]`` (every combination), a list of ``[[case]]``
tables, seeded ``[random]`` draws, or a product of them. Keys are dotted paths into the
pattern TOML (``fabric.stretch``, ``mesh.size_mm``, ``ribbon.0.thickness_mm``: 0-based index
into an array of tables) or design options (``stretch``, ``diagonal``, ``mesh_size``, ...).

Each case is one task of shellfem.cluster.map_tasks (a LocalCluster of one single-threaded
process per core, a running scheduler, or serially) and writes its own folder
``DIR/case-<hash>`` with the verb's normal outputs (forward.simulate.simulate_pattern_file,
inverse.design.design_file; for simulate also the case's resolved ``pattern.toml``) and,
written last and atomically, ``case.json``: its inputs, status, reason, figures and time.
The hash is the sha256 of the case's resolved pattern text (or target file content and design
options) and the package version, so:

- **resumable**: a case whose folder holds a ``case.json`` of the same hash is not run again
  (neither by this process nor by a worker that reruns a task), and a rerun of a finished
  sweep only rewrites the table;
- **nothing lost to a dead worker**: Dask gives the task to another worker; a half-written
  case folder (no case.json) is cleared and run again.

A case that fails is a row, not a crash of the sweep: status ``ok``, ``not_converged`` (the
verb's own result: the simulation or the design's verification did not converge),
``error`` (a SelfshapeError for this case's values found while it ran, e.g. a design
stretch without a shipped law; its one-line reason) or ``failed`` (an unexpected exception
or a task whose workers kept dying; no case.json, so a resume runs it again).

Results, in DIR: ``results.csv`` and ``results.parquet`` (one row per case: index, folder,
status, reason, time_s, ran (run by this invocation), worker, the case's inputs under their
keys, every scalar of summary.json / report.json flattened as ``summary.KEY`` /
``report.KEY`` with list indices and nested keys dotted, and the paths of its files relative to DIR),
``contact_sheet.png`` (a labelled grid of the cases' deployed.png, or verify.png /
pattern.png for designs) and ``sweep.json`` (counts and times), all written after the cases
(the table also every PARTIAL_TABLE_S while they run, with the cases finished so far).

A bad sweep file (unknown key, empty list, a value of the wrong type, a missing base pattern,
target or law, more than MAX_CASES cases, a case whose pattern the pattern reader refuses or
a design option outside its range) is a one-line SelfshapeError naming the file and the key,
raised before anything is written: the user's mistake is never a case that runs, and no
output holds NaN or Infinity (a non-finite figure is an empty cell). The module sits in
validation, above inverse, because design sweeps call inverse.design (the layers: shellfem <
geometry < forward < inverse < validation); it only imports forward and inverse inside the
tasks.
"""
from __future__ import annotations

import difflib
import hashlib
import itertools
import json
import math
import os
import shutil
import socket
import time

import numpy as np

from shellfem.errors import SelfshapeError

#: Files of DIR that a sweep writes (besides the case folders).
OUTPUTS = ("results.csv", "results.parquet", "contact_sheet.png", "sweep.json")
#: A case folder's name: ``case-`` and the first 12 hex digits of its inputs' hash.
CASE_PREFIX = "case-"
TOP_KEYS = {"sweep", "options", "grid", "case", "random"}
SWEEP_KEYS = {"pattern", "targets", "samples", "seed", "retries", "render"}
#: Design options a sweep may set: sweep key -> (design_file keyword, kind). Kinds: "number"
#: (in the keyword's range, :func:`design_number_spec`), "bool", "path" (an existing file,
#: relative to the sweep file), "stretch" (a number in the range, or "auto").
DESIGN_OPTIONS = {
    "stretch": ("stretch", "stretch"), "diagonal": ("diagonal_mm", "number"), "law": ("thickness_law", "path"),
    "lam": ("lam", "number"), "mesh_size": ("mesh_size_mm", "number"), "mesh_across": ("mesh_across", "number"),
    "verify": ("verify", "bool"), "verify_iterations": ("verify_iterations", "number"), "refine": ("refine", "bool"),
    "seed": ("seed", "number"), "edge_mm": ("edge_mm", "number"), "gap_mm": ("gap_mm", "number"),
    "layout_edge_mm": ("layout_edge_mm", "number"),
}
#: design_file keywords that become keys of the designed pattern.toml, so their range is that
#: key's (geometry.schema.PATTERN_NUMBERS); the others are geometry.schema.DESIGN_NUMBERS.
DESIGN_PATTERN_KEYS = {"mesh_size_mm": ("mesh", "size_mm"), "mesh_across": ("mesh", "across"),
                       "verify_iterations": ("solver", "max_iterations"), "seed": ("solver", "seed")}
#: Most cases one sweep may have ([[case]] x [grid] points x [random] samples x targets),
#: counted before any case is built: every case is validated (its pattern read) before any
#: runs and is a folder and a table row, so 10,000 cases are hours of a cluster's work and
#: seconds of checking, while 10^8 (a 10,000 x 10,000 grid) exhausted memory building the
#: list. A larger study is several sweep files.
MAX_CASES = 10_000
#: While a sweep runs, the table of the cases finished so far is rewritten at most this often, s.
PARTIAL_TABLE_S = 60.0
#: Statuses whose case.json makes a case finished (not rerun on resume).
FINISHED = ("ok", "not_converged", "error")


# ----------------------------------------------------------------------------- reading
def version_tag() -> str:
    """The package version that enters every case's hash (a new version reruns the cases)."""
    try:
        from importlib.metadata import version
        return version("selfshape")
    except Exception:
        import tomllib
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        try:
            with open(os.path.join(root, "pyproject.toml"), "rb") as f:
                return str(tomllib.load(f)["project"]["version"])
        except (OSError, KeyError, ValueError):
            return "unknown"


def _flatten_keys(table: dict, prefix: str = "") -> dict:
    """{dotted key: leaf} of a nested table: ``fabric.stretch = [...]`` (a TOML dotted key) and
    ``"fabric.stretch" = [...]`` (a quoted one) read the same."""
    out = {}
    for k, v in table.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict):
            out.update(_flatten_keys(v, key))
        else:
            out[key] = v
    return out


def _unknown(where: str, name: str, allowed) -> SelfshapeError:
    allowed = sorted(str(a) for a in allowed)
    close = difflib.get_close_matches(name, allowed, n=1, cutoff=0.6)
    hint = f"did you mean {close[0]!r}?" if close else f"allowed: {', '.join(allowed)}"
    return SelfshapeError(f"{where}: unknown key {name!r:.60} ({hint})")


def _what(v) -> str:
    if isinstance(v, bool):
        return "true/false"
    if isinstance(v, str):
        return f"the string {v!r:.40}"
    if isinstance(v, list):
        return "a list"
    if isinstance(v, dict):
        return "a table"
    return f"{v!r:.40}"


def _is_finite_num(v) -> bool:
    """A number that is a finite float (an integer beyond the float range is not)."""
    try:
        return _is_num(v) and math.isfinite(v)
    except OverflowError:
        return False


def _is_num(v) -> bool:
    from geometry.schema import is_number
    return is_number(v)


def pattern_key_kind(raw: dict, key: str, where: str) -> str:
    """Check that the dotted ``key`` names a value of a pattern (its tables and keys as
    geometry.patterns reads them, arrays of tables by 0-based index into the base ``raw``) and
    return the kind its values must have: "number", "stretch" (a number or [sx, sy]),
    "field" (stars: a number or an expression string), "string", "bool", "points" (a list) or
    "any". One-line SelfshapeError naming ``where`` and the key otherwise."""
    from geometry.patterns import KEYS, TOP_LEVEL, fabric_keys
    from geometry.schema import PATTERN_NUMBERS
    from shellfem.materials import MEMBRANE_MODELS
    parts = key.split(".")
    w = f"{where} {key}"
    top = parts[0]
    if top not in TOP_LEVEL or top == "meta":
        raise _unknown(w, top, TOP_LEVEL - {"meta"})
    arrays = ("region", "ribbon", "support")
    rest = parts[1:]
    if top in arrays:
        entries = raw.get(top, [])
        entries = [entries] if isinstance(entries, dict) else entries
        if not rest or not rest[0].isdigit():
            raise SelfshapeError(f"{w}: [[{top}]] entries are named by their 0-based index, e.g. {top}.0."
                                 f"{sorted(KEYS[top])[0]}")
        i = int(rest[0])
        if i >= len(entries):
            raise SelfshapeError(f"{w}: the base pattern has {len(entries)} [[{top}]] entr"
                                 f"{'y' if len(entries) == 1 else 'ies'} (indices from 0)")
        rest = rest[1:]
    if not rest:
        raise SelfshapeError(f"{w}: names a table; give one of its keys (e.g. {top}.{sorted(_allowed(top))[0]})")
    name = rest[0]
    allowed = fabric_keys() if top == "fabric" else set(PATTERN_NUMBERS["solver"]) if top == "solver" else KEYS[top]
    if name not in allowed:
        raise _unknown(w, name, allowed)
    if top == "fabric" and name in MEMBRANE_MODELS:
        params = {p.name for p in MEMBRANE_MODELS[name].parameters}
        if len(rest) != 2:
            raise SelfshapeError(f"{w}: give one parameter of [fabric.{name}] ({', '.join(sorted(params))})")
        if rest[1] not in params:
            raise _unknown(w, rest[1], params)
        return "number"
    if len(rest) > 1:
        raise SelfshapeError(f"{w}: {top}.{name} is a value, not a table")
    if top == "fabric" and name == "stretch":
        return "stretch"
    if top == "stars" and name in ("arm_length", "thickness_mm", "arm_width_mm"):
        return "field"
    if top == "solver" and name == "coarse_levels":
        return "any"
    section = "region" if top == "region" else top
    if name in PATTERN_NUMBERS.get(section, {}):
        return "number"
    if name in ("side", "ends", "model", "fix", "gcode"):
        return "string"
    if name == "boundary":
        return "bool"
    return "points"


def _allowed(top):
    from geometry.patterns import KEYS, fabric_keys
    from geometry.schema import PATTERN_NUMBERS
    return fabric_keys() if top == "fabric" else set(PATTERN_NUMBERS["solver"]) if top == "solver" else KEYS[top]


def design_number_spec(kw: str):
    """The range (a geometry.schema.Num) of a numeric design_file keyword: the pattern key's
    for the keywords that design_file writes into pattern.toml (DESIGN_PATTERN_KEYS), else
    geometry.schema.DESIGN_NUMBERS, the ranges inverse.design and `selfshape design` apply."""
    from geometry.schema import DESIGN_NUMBERS, PATTERN_NUMBERS
    if kw in DESIGN_PATTERN_KEYS:
        table, key = DESIGN_PATTERN_KEYS[kw]
        return PATTERN_NUMBERS[table][key]
    return DESIGN_NUMBERS[kw]


def _check_value(v, kind: str, where: str, spec=None):
    """The value of a case, checked by type and, given ``spec`` (a design option's
    geometry.schema.Num), by range: a one-line SelfshapeError naming ``where`` otherwise. A
    pattern key's range is checked on the whole case by the pattern reader
    (Sweep._check_patterns), since its valid values can depend on the other keys."""
    if spec is not None and not (kind == "stretch" and v == "auto"):
        if kind == "stretch" and isinstance(v, str):
            raise SelfshapeError(f'{where} must be "auto" or a number in {spec.describe()}, got {_what(v)}')
        from geometry.schema import number
        return number(v, where, spec)
    ok = {"number": _is_num(v),
          "stretch": _is_num(v) or (isinstance(v, list) and len(v) == 2 and all(_is_num(x) for x in v)),
          "field": _is_num(v) or isinstance(v, str), "string": isinstance(v, str), "bool": isinstance(v, bool),
          "path": isinstance(v, str) and bool(v.strip()), "points": isinstance(v, list), "any": True}[kind]
    if kind == "stretch" and isinstance(v, str):
        ok = ok or v == "auto"
    if not ok:
        need = {"number": "a number", "stretch": "a number or [sx, sy]", "field": "a number or an expression string",
                "string": "a string", "bool": "true or false", "path": "a file name", "points": "a list"}[kind]
        raise SelfshapeError(f"{where} must be {need}, got {_what(v)}")
    return v


def _show(v) -> str:
    """A case's value as the sweep file spells it (``135``, ``nan``, ``[1.2, 1.3]``), cut to 60 characters."""
    if isinstance(v, float):
        text = repr(v) if math.isfinite(v) else ("nan" if v != v else ("inf" if v > 0 else "-inf"))
    elif isinstance(v, bool):
        text = "true" if v else "false"
    elif isinstance(v, list):
        text = "[" + ", ".join(_show(x) for x in v) + "]"
    elif isinstance(v, str):
        text = json.dumps(v)
    else:
        text = str(v)
    return text if len(text) <= 60 else text[:57] + "..."


def resolve_case(base: dict, inputs: dict) -> dict:
    """The base pattern dict with a case's ``inputs`` {dotted key: value} set (arrays of tables
    by 0-based index; a single table where an array is allowed counts as an array of one).
    Only the tables and arrays on the keys' paths are copied: the base is shared and never
    changed, so a large base (a 100,000-point outline) is not deep-copied for each of
    thousands of cases (each is validated before any runs, then resolved again for its task)."""
    raw = dict(base)
    for key, value in inputs.items():
        parts = key.split(".")
        node = raw
        for j, p in enumerate(parts[:-1]):
            at = int(p) if isinstance(node, list) else p
            child = node[at] if isinstance(node, list) else node.get(p)
            if child is None:
                child = {}
            elif isinstance(child, dict) and parts[j + 1].isdigit():
                child = [child]
            else:
                child = list(child) if isinstance(child, list) else dict(child)
            node[at] = child
            node = child
        node[int(parts[-1]) if isinstance(node, list) else parts[-1]] = value
    return raw


class Sweep:
    """A checked sweep file: ``verb`` ("simulate" or "design"), ``cases`` (list of {key:
    value} in file order: [[case]] x grid x random draws), ``origins`` (per case, {key: the
    table that set it, e.g. "[grid]"}), ``base`` (the base pattern dict) or
    ``targets`` (absolute paths), ``keys`` (the varied keys, in order), ``render``, ``retries``."""

    def __init__(self, path: str):
        from geometry.tomlfile import read_toml
        self.path = os.fspath(path)
        src = self.path
        raw = read_toml(src)
        for k in raw:
            if k not in TOP_KEYS:
                raise _unknown(src, k, TOP_KEYS)
        head = raw.get("sweep")
        if not isinstance(head, dict):
            raise SelfshapeError(f"{src}: missing [sweep] table (with pattern = \"FILE.toml\" or targets = [...])")
        for k in head:
            if k not in SWEEP_KEYS:
                raise _unknown(f"{src}: [sweep]", k, SWEEP_KEYS)
        folder = os.path.dirname(os.path.abspath(src))
        self.folder = folder
        if ("pattern" in head) == ("targets" in head):
            raise SelfshapeError(f"{src}: [sweep] needs exactly one of pattern (simulate a pattern) or targets "
                                 f"(design each target)")
        self.render = head.get("render", True)
        if not isinstance(self.render, bool):
            raise SelfshapeError(f"{src}: [sweep] render must be true or false, got {_what(self.render)}")
        self.retries = head.get("retries", 2)
        if not (isinstance(self.retries, int) and not isinstance(self.retries, bool) and 0 <= self.retries <= 100):
            raise SelfshapeError(f"{src}: [sweep] retries must be an integer in [0, 100], got {_what(self.retries)}")
        if "pattern" in head:
            self.verb = "simulate"
            p = head["pattern"]
            if not isinstance(p, str) or not p.strip():
                raise SelfshapeError(f"{src}: [sweep] pattern must be a file name, got {_what(p)}")
            self.pattern_path = p if os.path.isabs(p) else os.path.join(folder, p)
            self._load_base(src)
            self.targets = []
        else:
            self.verb = "design"
            t = head["targets"]
            if isinstance(t, str):
                t = [t]
            if not isinstance(t, list) or not t:
                raise SelfshapeError(f"{src}: [sweep] targets must be a non-empty list of target files, got "
                                     f"{_what(t) if t != [] else 'an empty list'}")
            self.targets = []
            for i, name in enumerate(t):
                if not isinstance(name, str) or not name.strip():
                    raise SelfshapeError(f"{src}: [sweep] targets #{i + 1} must be a file name, got {_what(name)}")
                p = name if os.path.isabs(name) else os.path.join(folder, name)
                if not os.path.isfile(p):
                    raise SelfshapeError(f"{src}: [sweep] targets #{i + 1}: {name}: file not found")
                self.targets.append(os.path.abspath(p))
            self.base = None
        self.fixed = self._values(raw.get("options", {}), f"{src}: [options]", lists=False)
        grid = self._values(raw.get("grid", {}), f"{src}: [grid]", lists=True)
        listed = raw.get("case", [])
        if isinstance(listed, dict):
            listed = [listed]
        if not isinstance(listed, list):
            raise SelfshapeError(f"{src}: [[case]] must be an array of tables")
        if len(listed) > MAX_CASES:
            raise SelfshapeError(f"{src}: [[case]] has {len(listed):,} tables, more than the {MAX_CASES:,} cases a "
                                 f"sweep may have; split it into several sweep files")
        cases = [self._values(c, f"{src}: [[case]] #{i + 1}", lists=False) if isinstance(c, dict) else
                 _raise(SelfshapeError(f"{src}: [[case]] #{i + 1} must be a table")) for i, c in enumerate(listed)]
        ranges, samples, seed = self._random(raw.get("random", {}), head, src)
        if not (grid or cases or ranges):
            raise SelfshapeError(f"{src}: nothing to vary: give a [grid], [[case]] tables or [random] ranges")
        self._check_count(src, cases, grid, samples)
        draws = _draw(ranges, samples, seed)
        points = [dict(zip(grid, combo)) for combo in itertools.product(*grid.values())] if grid else [{}]
        self.cases, self.origins = [], []
        for (i, c), g, r in itertools.product(enumerate(cases or [{}]), points, draws or [{}]):
            self.cases.append({**self.fixed, **c, **g, **r})
            self.origins.append({**{k: "[options]" for k in self.fixed}, **{k: f"[[case]] #{i + 1}" for k in c},
                                 **{k: "[grid]" for k in g}, **{k: "[random]" for k in r}})
        self.keys = list(dict.fromkeys(k for case in self.cases for k in case if k not in self.fixed)) or \
            list(self.fixed)
        if self.verb == "simulate":
            self._check_patterns(src)

    def _check_count(self, src, cases, grid, samples):
        """Refuse more than MAX_CASES cases in one line naming the keys that multiply, from
        the counts alone (before any case, grid point or draw is built)."""
        factors = ([(f"{len(cases):,} [[case]] tables", len(cases))] if cases else []) + \
            [(f"[grid] {k} ({len(v):,} values)", len(v)) for k, v in grid.items()] + \
            ([(f"[sweep] samples = {samples:,}", samples)] if samples else []) + \
            ([(f"{len(self.targets):,} [sweep] targets", len(self.targets))] if len(self.targets) > 1 else [])
        total = math.prod(n for _, n in factors)
        if total > MAX_CASES:
            names = [name for name, n in factors if n > 1]           # a factor of 1 does not multiply
            raise SelfshapeError(f"{src}: {total:,} cases ({' x '.join(names)}), more than "
                                 f"the {MAX_CASES:,} a sweep may have; split it into several sweep files")

    def _check_patterns(self, src):
        """Every case's pattern (the base with the case's values) through the reader of a
        pattern file, geometry.patterns.parse_pattern, before any case runs: a value that the
        reader refuses (out of range, NaN, a ribbon off the fabric) is the sweep file's error,
        not a case that runs and writes it. The message names the sweep file, the key that
        alone gives the reader's reason (or the case's varied values when only their
        combination is refused), the value, the case (0-based, as the table's index) and the
        reader's one-line reason. Identical cases are read once."""
        from geometry.patterns import _plain, parse_pattern
        base_dir = os.path.dirname(os.path.abspath(self.pattern_path))
        name = "<case>"

        def reason(inputs):
            try:
                parse_pattern(_plain(resolve_case(self.base, inputs)), name, base_dir, from_file=True)
            except SelfshapeError as e:
                text = str(e)
                return text[len(name) + 2:] if text.startswith(name + ": ") else text.replace(name, "the case")
            return None

        seen = set()
        for i, (case, origin) in enumerate(zip(self.cases, self.origins)):
            ident = json.dumps(case, sort_keys=True)
            if ident in seen:
                continue
            seen.add(ident)
            why = reason(case)
            if why is None:
                continue
            key = next((k for k in case if reason({k: case[k]}) == why), None)
            if key is None:
                values = ", ".join(f"{k} = {_show(v)}" for k, v in case.items() if k not in self.fixed)
                raise SelfshapeError(f"{src}: case #{i} ({values}): {why}")
            at = "" if origin[key] == "[options]" else f" (case #{i})"
            raise SelfshapeError(f"{src}: {origin[key]} {key} = {_show(case[key])}{at}: {why}")

    def _load_base(self, src):
        from geometry.patterns import load_pattern
        from geometry.tomlfile import read_toml
        label = f"{src}: [sweep] pattern {os.path.basename(self.pattern_path)}"
        if not os.path.isfile(self.pattern_path):
            raise SelfshapeError(f"{label}: file not found")
        if not self.pattern_path.lower().endswith(".toml"):
            raise SelfshapeError(f"{label}: the base pattern must be a .toml pattern file")
        self.base = read_toml(self.pattern_path, label)
        try:                                       # a bad base pattern is the sweep's error
            load_pattern(self.pattern_path)
        except SelfshapeError as e:
            raise SelfshapeError(f"{src}: [sweep] pattern: {e}") from None
        if "print" in self.base:
            raise SelfshapeError(f"{label}: [print] G-code in a swept pattern is not supported (each case is "
                                 f"written to its own folder); import the print as [[ribbon]] tables")

    def _kind(self, key: str, where: str) -> str:
        if self.verb == "simulate":
            return pattern_key_kind(self.base, key, where)
        if key not in DESIGN_OPTIONS:
            raise _unknown(where, key, DESIGN_OPTIONS)
        return DESIGN_OPTIONS[key][1]

    def _values(self, table, where: str, lists: bool) -> dict:
        """{key: value} ([[case]], [options]) or {key: [values]} ([grid]), keys and types checked."""
        if not isinstance(table, dict):
            raise SelfshapeError(f"{where} must be a table")
        out = {}
        for key, v in _flatten_keys(table).items():
            kind = self._kind(key, f"{where}")
            spec = self._spec(key, kind)
            if lists:
                if not isinstance(v, list):
                    raise SelfshapeError(f"{where} {key} must be a list of values, got {_what(v)}")
                if not v:
                    raise SelfshapeError(f"{where} {key}: the list of values is empty")
                if len(v) > MAX_CASES:
                    raise SelfshapeError(f"{where} {key} has {len(v):,} values, more than the {MAX_CASES:,} cases a "
                                         f"sweep may have; split it into several sweep files")
                for i, x in enumerate(v):
                    self._check_one(x, kind, spec, f"{where} {key} value #{i + 1}")
            else:
                self._check_one(v, kind, spec, f"{where} {key}")
            out[key] = v
        return out

    def _spec(self, key: str, kind: str):
        """A design option's range (None for pattern keys: the reader checks those per case)."""
        if self.verb == "design" and kind in ("number", "stretch"):
            return design_number_spec(DESIGN_OPTIONS[key][0])
        return None

    def _check_one(self, v, kind: str, spec, where: str):
        """One value (_check_value); a design sweep's law file must exist."""
        _check_value(v, kind, where, spec)
        if kind == "path" and not os.path.isfile(v if os.path.isabs(v) else os.path.join(self.folder, v)):
            raise SelfshapeError(f"{where}: {v}: file not found")

    def _random(self, table, head, src) -> tuple:
        """The [random] ranges {key: [lo, hi]} (finite, lo <= hi; a design option's ends in its
        range, so every draw is; integer ends within int64), [sweep] samples and seed, checked."""
        where = f"{src}: [random]"
        if not isinstance(table, dict):
            raise SelfshapeError(f"{where} must be a table")
        ranges = {}
        for key, v in _flatten_keys(table).items():
            kind = self._kind(key, where)
            if kind not in ("number", "stretch", "field", "any"):
                raise SelfshapeError(f"{where} {key}: only numeric keys can be drawn at random")
            if not (isinstance(v, list) and len(v) == 2 and all(_is_finite_num(x) for x in v)):
                raise SelfshapeError(f"{where} {key} must be a range [lo, hi] of two finite numbers, got "
                                     f"{_show(v) if isinstance(v, list) else _what(v)}")
            if not v[0] <= v[1]:
                raise SelfshapeError(f"{where} {key}: the range [lo, hi] has lo > hi ({v[0]} > {v[1]})")
            if all(isinstance(x, int) for x in v) and not all(abs(x) < 2 ** 62 for x in v):
                raise SelfshapeError(f"{where} {key}: the integer range {_show(v)} goes beyond +-2^62")
            if not math.isfinite(float(v[1]) - float(v[0])):
                raise SelfshapeError(f"{where} {key}: the range {_show(v)} is wider than a float can hold")
            spec = self._spec(key, kind)
            for end, x in zip(("lo", "hi"), v):
                self._check_one(x, kind, spec, f"{where} {key} {end}")
            ranges[key] = v
        samples, seed = head.get("samples"), head.get("seed", 0)
        if not ranges:
            if samples is not None:
                raise SelfshapeError(f"{src}: [sweep] samples needs [random] ranges")
            return {}, None, None
        if not (isinstance(samples, int) and not isinstance(samples, bool) and samples >= 1):
            raise SelfshapeError(f"{src}: [sweep] samples must be an integer >= 1 with [random] ranges, got "
                                 f"{_what(samples) if samples is not None else 'nothing'}")
        if not (isinstance(seed, int) and not isinstance(seed, bool) and seed >= 0):
            raise SelfshapeError(f"{src}: [sweep] seed must be an integer >= 0, got {_what(seed)}")
        return ranges, samples, seed


def _draw(ranges: dict, samples, seed) -> list:
    """``samples`` draws (seeded by ``seed``) uniform in each key's [lo, hi] (integers:
    uniform integers in [lo, hi]); [] without ranges."""
    if not ranges:
        return []
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(samples):
        d = {}
        for key, (lo, hi) in ranges.items():
            if isinstance(lo, int) and isinstance(hi, int):
                d[key] = int(rng.integers(lo, hi + 1))
            else:
                # 6 digits: readable labels, exact inputs; kept in [lo, hi], whose ends were checked
                d[key] = min(max(float(f"{rng.uniform(lo, hi):.6g}"), float(lo)), float(hi))
        draws.append(d)
    return draws


def _raise(e):
    raise e


def load_sweep(path) -> Sweep:
    """Read and check a sweep file (see the module doc); one-line SelfshapeError if it is bad."""
    return Sweep(path)


# ----------------------------------------------------------------------------- the cases
def _file_sha(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def case_specs(sweep: Sweep, out_dir: str) -> list[dict]:
    """One task description per case (plain data, for the workers): index, inputs, hash, folder,
    and the resolved pattern text (simulate) or target and design_file keywords (design)."""
    import tomli_w
    from geometry.patterns import _plain
    version = version_tag()
    specs = []
    targets = sweep.targets or [None]
    for target in targets:
        for inputs in sweep.cases:
            i = len(specs)
            spec = {"index": i, "verb": sweep.verb, "inputs": dict(inputs), "render": sweep.render}
            if sweep.verb == "simulate":
                text = tomli_w.dumps(_plain(resolve_case(sweep.base, inputs)))
                ident = {"verb": "simulate", "pattern": text, "render": sweep.render, "version": version}
                spec.update(pattern_text=text, pattern_name=os.path.basename(sweep.pattern_path))
            else:
                options = {}
                for key, v in inputs.items():
                    kw, kind = DESIGN_OPTIONS[key]
                    if kind == "path":
                        v = os.path.abspath(v if os.path.isabs(v) else os.path.join(sweep.folder, v))
                    options[kw] = v
                law = options.get("thickness_law")
                ident = {"verb": "design", "target": _file_sha(target), "target_name": os.path.basename(target),
                         "options": options, "law": _file_sha(law) if law and os.path.isfile(law) else None,
                         "version": version}
                spec["inputs"] = {"target": os.path.relpath(target, sweep.folder), **spec["inputs"]}
                spec.update(target=target, options=options)
            digest = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()
            spec["hash"] = digest
            spec["folder"] = os.path.join(os.path.abspath(out_dir), CASE_PREFIX + digest[:12])
            specs.append(spec)
    seen = {}
    for s in specs:                      # identical cases (a repeated value) are one folder, run once
        s["duplicate_of"] = seen.setdefault(s["hash"], s["index"])
    return specs


def read_marker(folder: str, digest: str) -> dict | None:
    """The case.json of a finished case of this hash in ``folder``, else None."""
    try:
        with open(os.path.join(folder, "case.json"), encoding="utf-8") as f:
            m = json.load(f)
    except (OSError, ValueError):
        return None
    if isinstance(m, dict) and m.get("hash") == digest and m.get("status") in FINISHED:
        return m
    return None


def _finite(v):
    """``v``, or None for a NaN or infinite float: no output of a sweep holds a non-finite number
    (case.json would refuse it and fail the case; the table writes None as an empty cell)."""
    return None if isinstance(v, float) and not math.isfinite(v) else v


def flatten_figures(obj, prefix: str) -> dict:
    """Every scalar of a summary/report dict as {prefix.key.sub.0: value} (numbers, bools,
    strings; None kept as None, a non-finite number becomes None)."""
    out = {}

    def walk(v, key):
        if isinstance(v, dict):
            for k, x in v.items():
                walk(x, f"{key}.{k}")
        elif isinstance(v, (list, tuple)):
            for j, x in enumerate(v):
                walk(x, f"{key}.{j}")
        elif v is None or isinstance(v, (bool, int, float, str)):
            out[key] = _finite(v)
        elif isinstance(v, np.generic):
            out[key] = _finite(v.item())
    walk(obj, prefix)
    return out


def _files(folder: str) -> dict:
    names = ("summary.json", "report.json", "deployed.png", "verify.png", "pattern.png", "pattern.toml",
             "deployed.vtu")
    # relative to DIR (case-<hash>/NAME): the table stays right when DIR is moved or mounted elsewhere
    case = os.path.basename(folder)
    return {f"path.{n}": f"{case}/{n}" for n in names if os.path.isfile(os.path.join(folder, n))}


def run_case(spec: dict) -> dict:
    """Run one case (a Dask task, or called serially) and return its row; see the module doc.
    A finished case.json of the same hash is returned as it is (``ran`` False)."""
    from shellfem.outfiles import write_json, write_text_file
    folder = spec["folder"]
    done = read_marker(folder, spec["hash"])
    if done is not None:
        return {**done["row"], "ran": False}
    t0 = time.perf_counter()
    marker = os.path.join(folder, "case.json")
    if os.path.isdir(folder):                         # a killed run's half-written folder: start clean
        shutil.rmtree(folder, ignore_errors=True)
    os.makedirs(folder, exist_ok=True)
    status, reason, figures = "ok", "", {}
    try:
        if spec["verb"] == "simulate":
            from forward.simulate import simulate_pattern_file
            pattern = os.path.join(folder, "pattern.toml")
            write_text_file(pattern, spec["pattern_text"])
            s = simulate_pattern_file(pattern, folder, render=spec["render"])
            if not s["converged"]:
                status, reason = "not_converged", s["reason"]
            figures = flatten_figures({k: v for k, v in s.items() if k != "pattern"}, "summary")
        else:
            from inverse.design import design_file
            r = design_file(spec["target"], folder, **spec["options"])
            if r.get("verify_converged") is False:
                status, reason = "not_converged", str(r.get("verify_reason", ""))
            figures = flatten_figures(r, "report")
    except SelfshapeError as e:
        status, reason = "error", str(e)
    except Exception as e:                              # noqa: BLE001 - a row, not a crashed sweep
        status, reason = "failed", f"{type(e).__name__}: {' '.join(str(e).split())[:300]}"
    row = {"index": spec["index"], "case": os.path.basename(folder), "status": status, "reason": reason,
           "time_s": round(time.perf_counter() - t0, 3), "worker": f"{socket.gethostname()}:{os.getpid()}",
           **spec["inputs"], **figures, **_files(folder)}
    if status in FINISHED:
        write_json(marker, {"hash": spec["hash"], "status": status, "row": row})       # last: the case is finished
    return {**row, "ran": True}


# ----------------------------------------------------------------------------- the table
def _column_types(rows, columns):
    """Per column: "bool", "int", "float" or "string" (mixed numbers are floats, anything else strings)."""
    types = {}
    for c in columns:
        vals = [r.get(c) for r in rows if r.get(c) is not None]
        if vals and all(isinstance(v, bool) for v in vals):
            types[c] = "bool"
        elif vals and all(isinstance(v, int) and not isinstance(v, bool) for v in vals):
            types[c] = "int"
        elif vals and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
            types[c] = "float"
        else:
            types[c] = "string"
    return types


def _cell(v, kind):
    v = _finite(v)
    if v is None:
        return None
    if kind == "string":
        return v if isinstance(v, str) else json.dumps(v)
    if kind == "float":
        return float(v)
    return v


def table_columns(rows) -> list[str]:
    """index, case, status, reason, time_s, ran, worker, then the inputs and figures in order of first appearance."""
    first = ["index", "case", "status", "reason", "time_s", "ran", "worker"]
    rest = list(dict.fromkeys(k for r in rows for k in r if k not in first))
    paths = [k for k in rest if k.startswith("path.")]
    return first + [k for k in rest if not k.startswith("path.")] + paths


def write_table(out, rows) -> None:
    """results.csv and results.parquet of ``rows`` (OutputDir ``out``); floats in the CSV with
    repr's 17 digits, so that a number read back is the number written."""
    import csv
    import io
    columns = table_columns(rows)
    types = _column_types(rows, columns)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        cells = [_cell(r.get(c), types[c]) for c in columns]
        w.writerow(["" if v is None else (repr(v) if types[c] == "float" else v) for c, v in zip(columns, cells)])
    out.write_text("results.csv", buf.getvalue())
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise SelfshapeError("results.parquet needs pyarrow: pip install pyarrow") from None
    pa_types = {"bool": pa.bool_(), "int": pa.int64(), "float": pa.float64(), "string": pa.string()}
    table = pa.table({c: pa.array([_cell(r.get(c), types[c]) for r in rows], type=pa_types[types[c]])
                      for c in columns})
    out.write("results.parquet", lambda tmp: pq.write_table(table, tmp))


def _label(row, keys) -> str:
    vals = [f"{k} {row.get(k):g}" if isinstance(row.get(k), float) else f"{k} {row.get(k)}" for k in keys]
    return f"#{row['index']} {row['status']}\n" + "\n".join(vals)


def write_contact_sheet(out, rows, keys, path_key_order=("path.deployed.png", "path.verify.png",
                                                         "path.pattern.png")) -> None:
    """contact_sheet.png: a grid of the cases' pictures, each labelled with its index, status and
    varied values (a grey cell where a case has no picture)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.image as mpimg
    import matplotlib.pyplot as plt
    n = max(1, len(rows))
    ncol = int(math.ceil(math.sqrt(n)))
    nrow = int(math.ceil(n / ncol))
    cell = 3.0 if n <= 36 else 2.0
    fig, axes = plt.subplots(nrow, ncol, figsize=(cell * ncol, cell * nrow * 1.15), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, row in zip(axes.ravel(), rows):
        pic = next((os.path.join(out.path, row[k]) for k in path_key_order if row.get(k)), None)
        if pic:
            try:
                ax.imshow(mpimg.imread(pic))
            except (OSError, ValueError, SyntaxError):
                pic = None
        if not pic:
            ax.add_patch(plt.Rectangle((0, 0), 1, 1, color="0.85", transform=ax.transAxes))
            ax.text(0.5, 0.5, (row.get("reason") or "no picture")[:80], ha="center", va="center", wrap=True,
                    fontsize=6, transform=ax.transAxes)
        colour = "black" if row["status"] == "ok" else "firebrick"
        ax.set_title(_label(row, keys), fontsize=7, color=colour, loc="left")
    fig.tight_layout()
    out.write("contact_sheet.png", lambda tmp: fig.savefig(tmp, dpi=100))
    plt.close(fig)


# ----------------------------------------------------------------------------- the verb
def run_sweep(sweep_path, out_dir, *, scheduler: str | None = None, workers: int | None = None,
              progress=None) -> dict:
    """`selfshape sweep SWEEP.toml -o DIR`: run every case not finished yet (shellfem.cluster:
    ``scheduler`` address, or a LocalCluster of ``workers`` processes (default one per core),
    ``workers=0`` serially in this process), then write the table, the contact sheet and
    sweep.json. ``progress(row, done, total)`` is called once with ``row=None`` before any case
    runs (``done``: the cases finished in an earlier run) and then as each case finishes. Returns
    {cases, ran, reused, failed (statuses other than ok), statuses, time_s, files}."""
    from shellfem.cluster import check_options, default_workers, map_tasks
    from shellfem.outfiles import OutputDir
    t0 = time.perf_counter()
    check_options(scheduler, workers)
    sweep = load_sweep(sweep_path)
    out = OutputDir(out_dir, OUTPUTS, inputs=[sweep_path, getattr(sweep, "pattern_path", None), *sweep.targets])
    specs = case_specs(sweep, out_dir)
    rows = [None] * len(specs)
    todo = []
    for s in specs:
        if s["duplicate_of"] != s["index"]:
            continue
        m = read_marker(s["folder"], s["hash"])
        if m is not None:
            rows[s["index"]] = {**m["row"], "ran": False}
        else:
            todo.append(s)
    done = [len(specs) - len(todo)]
    last_table = [time.perf_counter()]

    def finished(j, row):
        done[0] += 1
        rows[todo[j]["index"]] = row
        if progress is not None:
            progress(row, done[0], len(specs))
        if time.perf_counter() - last_table[0] > PARTIAL_TABLE_S:      # a long sweep's table so far
            write_table(out, [r for r in rows if r is not None])
            last_table[0] = time.perf_counter()

    def lost(j, e):
        s = todo[j]
        return {"index": s["index"], "case": os.path.basename(s["folder"]), "status": "failed",
                "reason": f"{type(e).__name__}: {' '.join(str(e).split())[:300]}", "time_s": None, "ran": True,
                "worker": None, **s["inputs"]}

    with out:
        if progress is not None:
            progress(None, done[0], len(specs))
        if todo:
            map_tasks(run_case, todo, scheduler=scheduler, workers=workers, retries=sweep.retries,
                      keys=[f"sweep-case-{s['hash'][:16]}-{s['index']}" for s in todo], on_result=finished,
                      on_error=lost)
        for s in specs:                                   # repeated cases share the first one's result
            if s["duplicate_of"] != s["index"]:
                first = rows[s["duplicate_of"]]
                rows[s["index"]] = {**first, "index": s["index"], "ran": False, **s["inputs"]}
        write_table(out, rows)
        write_contact_sheet(out, rows, (["target"] if sweep.verb == "design" else []) + sweep.keys)
        statuses = {}
        for r in rows:
            statuses[r["status"]] = statuses.get(r["status"], 0) + 1
        summary = {"sweep": os.path.abspath(sweep.path), "verb": sweep.verb, "cases": len(rows),
                   "ran": sum(bool(r.get("ran")) for r in rows), "reused": sum(not r.get("ran") for r in rows),
                   "failed": sum(r["status"] != "ok" for r in rows), "statuses": statuses,
                   "scheduler": scheduler or ("serial" if workers == 0 else "local"),
                   "workers": (default_workers() if workers is None and not scheduler else workers),
                   "keys": sweep.keys, "version": version_tag(),
                   "time_s": round(time.perf_counter() - t0, 2),
                   "files": [os.path.join(out.path, n) for n in OUTPUTS]}
        out.write_json("sweep.json", summary)
    return summary
