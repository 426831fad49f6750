"""What the verification studies share on the command line: the options --quick, --out (JSON
directory) and --figures (PNG directory), and writing a study's JSON record while printing its
one-line summary. Imported by the scripts beside it (studies/ is on sys.path when one of them
is run as ``python studies/<name>.py``)."""
from __future__ import annotations

import argparse
import json
import os


def study_arguments(doc: str, quick_help: str, argv=None) -> argparse.Namespace:
    """Parse --quick (``quick_help``), --out (default out/validation) and --figures (default
    docs/validation); the description is the first line of ``doc``."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help=quick_help)
    ap.add_argument("--out", default="out/validation")
    ap.add_argument("--figures", default="docs/validation")
    return ap.parse_args(argv)


def write_result(out_dir: str, name: str, record: dict, summary: dict) -> None:
    """OUT/<name>.json = ``record`` (indented), and ``summary`` printed as one JSON line."""
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, f"{name}.json"), "w") as fh:
        json.dump(record, fh, indent=2)
    print(json.dumps(summary))


TARGETS = os.path.join("meshes", "targets", "*.obj")     # relative to the repository root


def target_paths(names=()) -> list:
    """The shipped target meshes (meshes/targets/*.obj), sorted, restricted to ``names`` (file
    stems) if given."""
    import glob
    paths = sorted(glob.glob(TARGETS))
    return [p for p in paths if not names or os.path.splitext(os.path.basename(p))[0] in names]
