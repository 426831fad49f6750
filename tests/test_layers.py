"""The packages form layers: each imports only the packages below it, never one above.

    shellfem  <  geometry  <  forward  <  inverse  <  validation  <  selfshape

Checked twice: statically, over every import statement of every module (function-local
imports included), and dynamically, by importing each package's modules in a fresh
interpreter and listing which project packages got loaded.
"""
import ast
import json
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
LAYERS = ["shellfem", "geometry", "forward", "inverse", "validation", "selfshape"]


def _modules(package):
    for path in sorted((ROOT / package).rglob("*.py")):
        rel = path.relative_to(ROOT).with_suffix("")
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
        yield path, ".".join(parts)


def _imported_packages(path):
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name.split(".")[0], node.lineno
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module.split(".")[0], node.lineno


@pytest.mark.parametrize("package", LAYERS)
def test_no_import_statement_reaches_up(package):
    above = set(LAYERS[LAYERS.index(package) + 1:])
    bad = [f"{path.relative_to(ROOT)}:{line} imports {top}"
           for path, _ in _modules(package) for top, line in _imported_packages(path) if top in above]
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("package", LAYERS)
def test_importing_a_package_loads_only_the_layers_below(package):
    names = [name for _, name in _modules(package)]
    code = ("import importlib, json, sys\n"
            f"for n in {names!r}: importlib.import_module(n)\n"
            f"print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & set({LAYERS!r}))))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    loaded = set(json.loads(out.stdout.strip().splitlines()[-1]))
    allowed = set(LAYERS[:LAYERS.index(package) + 1])
    assert loaded <= allowed, f"importing {package} loaded {sorted(loaded - allowed)}"
    assert package in loaded
