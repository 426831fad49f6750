"""Read a TOML file with one-line errors (pattern files, printer files)."""
from __future__ import annotations

import tomllib

from shellfem.errors import SelfshapeError


def read_toml(path: str, label: str | None = None) -> dict:
    """Parsed TOML of ``path``; any failure is a SelfshapeError of one line starting with
    ``label`` (default: the path): file not found, a directory, unreadable, not UTF-8, malformed."""
    label = label or str(path)
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise SelfshapeError(f"{label}: file not found") from None
    except IsADirectoryError:
        raise SelfshapeError(f"{label}: is a directory, not a TOML file") from None
    except OSError as e:
        raise SelfshapeError(f"{label}: cannot read ({e.strerror})") from None
    except UnicodeDecodeError as e:
        raise SelfshapeError(f"{label}: not a UTF-8 text file ({e.reason} at byte {e.start})") from None
    except tomllib.TOMLDecodeError as e:
        raise SelfshapeError(f"{label}: malformed TOML: {e}") from None
