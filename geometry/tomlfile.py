"""Read a TOML file with one-line errors (pattern files, printer files, sweep files)."""
from __future__ import annotations

import tomllib

from shellfem.errors import SelfshapeError
from shellfem.infiles import read_input_bytes

#: Largest TOML file read (bytes): a pattern is kilobytes (a 100,000-point polygon ~3 MB);
#: tomllib builds Python objects of ~10x the text, so 64 MB bounds its memory below 1 GB.
MAX_TOML_BYTES = 64 * 1024 * 1024


#: Deepest nesting of arrays and tables a selfshape TOML file may have: patterns need 4
#: ([fabric.orthotropic], a list of [x, y] points); deeper input only risks recursion later.
MAX_DEPTH = 32


def nesting_depth(value) -> int:
    """Depth of nested dicts/lists (a scalar is 0), walked iteratively."""
    depth, stack = 0, [(value, 0)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, dict):
            v = list(v.values())
        if isinstance(v, list):
            depth = max(depth, d + 1)
            stack.extend((x, d + 1) for x in v)
    return depth


def read_toml(path: str, label: str | None = None) -> dict:
    """Parsed TOML of ``path``; any failure is a SelfshapeError of one line starting with
    ``label`` (default: the path): file not found, a folder, a device or pipe, larger than
    MAX_TOML_BYTES, unreadable (shellfem.infiles), not UTF-8, malformed, nested deeper than
    MAX_DEPTH (tomllib itself recurses: thousands of ``[`` raise RecursionError). A leading
    UTF-8 byte-order mark (Windows editors write one) is dropped: TOML forbids it, but it is
    not the user's content."""
    label = label or str(path)
    raw = read_input_bytes(path, "TOML file", label, MAX_TOML_BYTES)
    try:
        data = tomllib.loads(raw.decode("utf-8-sig"))
        if nesting_depth(data) > MAX_DEPTH:
            raise RecursionError
        return data
    except RecursionError:
        raise SelfshapeError(f"{label}: arrays or tables nested deeper than {MAX_DEPTH} levels") from None
    except UnicodeDecodeError as e:
        raise SelfshapeError(f"{label}: not a UTF-8 text file ({e.reason} at byte {e.start})") from None
    except tomllib.TOMLDecodeError as e:
        raise SelfshapeError(f"{label}: malformed TOML: {e}") from None
