"""Reading the lab's text files (CSV tables, JSON) so that any bad file is a one-line
SelfshapeError naming the file and the line, never a raw UnicodeDecodeError, csv.Error or
RecursionError: binary or non-UTF-8 bytes, a field over the csv module's limit, malformed or
absurdly nested JSON, a path that is a directory or cannot be read. Also the rule that an
output path must not be one of the inputs (a verb refuses rather than overwrite data)."""
from __future__ import annotations

import csv
import io
import json
import math
import os

import numpy as np

from shellfem.errors import SelfshapeError
from shellfem.infiles import csv_error_text, read_input_text

#: A lab table or JSON beyond this is not one (bytes): the csv module's rows of a 64 MB file
#: take ~0.7 GB, and the readers' row caps (validation.strips.MAX_ROWS, fabric_files.MAX_TABLE_ROWS)
#: are reached far below it.
MAX_BYTES = 64 * 1024 * 1024


def read_text(path, what: str = "text file") -> str:
    """The file's text (UTF-8, an optional BOM removed), through shellfem.infiles: a folder,
    a device or pipe, or a file over MAX_BYTES is refused before reading. Errors name the
    file and, for bytes that are not UTF-8, the line they are on."""
    name = os.path.basename(str(path))
    if os.path.isdir(path):
        raise SelfshapeError(f"{path}: is a directory, expected a {what}")
    return read_input_text(path, what, name, MAX_BYTES)


def read_csv_rows(path, what: str = "CSV table") -> list:
    """All rows of a CSV file as lists of strings, with one-line errors naming file and line
    (binary content, NUL bytes, a field over the csv module's limit, an open quote)."""
    name = os.path.basename(str(path))
    text = read_text(path, what)
    if "\x00" in text:
        line = text[:text.index("\x00")].count("\n") + 1
        raise SelfshapeError(f"{name}: line {line}: NUL byte (binary content), expected a {what}")
    reader = csv.reader(io.StringIO(text, newline=""))
    rows = []
    try:
        for r in reader:
            rows.append(r)
    except csv.Error as e:
        raise SelfshapeError(f"{name}: line {reader.line_num + (0 if rows else 1)}: {csv_error_text(e)}") from None
    return rows


def read_json(path, what: str = "JSON file"):
    """Parsed JSON, with errors naming file and line (invalid JSON, NaN/Infinity literals
    are allowed by the parser and left to the caller's finiteness checks, nesting too deep,
    an integer of more digits than Python converts (4,300): a ValueError without a line)."""
    name = os.path.basename(str(path))
    text = read_text(path, what)
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise SelfshapeError(f"{name}: line {e.lineno}: invalid JSON ({e.msg})") from None
    except RecursionError:
        raise SelfshapeError(f"{name}: JSON nested too deeply to be a {what}") from None
    except ValueError as e:         # int('9' * 5000): the digit limit of int(), not a JSON error
        raise SelfshapeError(f"{name}: a number too long to be read ({' '.join(str(e).split()[:8])}); "
                             f"expected a {what}") from None


def refuse_overwrite(output, inputs, verb_option: str = "-o") -> None:
    """SelfshapeError when ``output`` is (or resolves to) one of ``inputs``: a verb never
    writes over its own input data."""
    out = os.path.realpath(str(output))
    for p in inputs:
        if p is not None and os.path.realpath(str(p)) == out:
            raise SelfshapeError(f"{output}: {verb_option} is the input file {os.path.basename(str(p))}; "
                                 "refusing to overwrite input data (choose another output path)")


def finite_json(o, where="parameters"):
    """A JSON-ready copy of o (numpy scalars and arrays to Python) with every number checked
    finite: a SelfshapeError naming the entry otherwise, so a verb fails with a reason rather
    than write NaN or Infinity (which are not JSON)."""
    if isinstance(o, dict):
        return {k: finite_json(v, f"{where}.{k}") for k, v in o.items()}
    if isinstance(o, np.ndarray):
        o = o.tolist()
    if isinstance(o, (list, tuple)):
        return [finite_json(v, f"{where}[{i}]") for i, v in enumerate(o)]
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        raise SelfshapeError(f"the calibration produced a non-finite {where} ({o!r}): the data do not determine it")
    return o
