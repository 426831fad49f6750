"""The files a verb writes: checked before the work, written atomically, every number finite.

Every ``selfshape`` verb writes through this module (it sits in the lowest layer so that
geometry's ``mesh`` verb can use it as well as forward, inverse and validation):

- **checked before computing**: :class:`OutputDir` (a verb that writes known names into a folder)
  and :func:`check_output_file` (a verb that writes one file) refuse, with a one-line
  SelfshapeError naming the path, an empty path, a folder where a file is asked or a file
  (or ``/dev/null``) where a folder is asked, a path under a file, a folder that cannot be
  written (probed by creating a temporary file, so a read-only file system is caught even for
  root), a symbolic link at an output path (never written through nor replaced: the user
  planted it, and we say so), and an output that is one of the run's input files;
- **stale outputs cleared**: :meth:`OutputDir.begin` removes the files an earlier run of the
  same verb left in the folder (its known names only, never other files) before the work
  starts, so a rerun with fewer outputs (``--no-png``) or an interrupted rerun never mixes
  with the old run's files;
- **atomic**: :func:`write_atomic` writes each file to a temporary file in the same folder
  (same suffix, so writers that choose the format by extension work) and renames it into
  place; the temporary file is removed on any failure, Ctrl-C included;
- **finite**: :func:`write_json` refuses NaN/Infinity (naming the key) instead of writing
  the non-JSON tokens ``NaN``/``Infinity``; :func:`check_finite_arrays` does the same for the
  numeric arrays of VTU/CSV outputs. The caller writes its summary (summary.json,
  report.json, parameters.json) last, so a folder holding it is complete.

A write that fails after the checks (disk full, folder removed meanwhile) is a SelfshapeError
naming the file, not a raw OSError.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import re
import tempfile

import numpy as np

from shellfem.errors import SelfshapeError


class NonFiniteOutput(SelfshapeError):
    """A value that would be written is NaN or infinite (the verb writes nothing instead)."""


# ----------------------------------------------------------------------------- checks
def _same(a: str, b) -> bool:
    try:
        return os.path.samefile(a, os.fspath(b))
    except (OSError, TypeError, ValueError):
        return False


def _probe_writable(folder: str, shown: str) -> None:
    """Create and remove a temporary file in ``folder``: the only test that also holds for
    root (os.access ignores permissions for root) and for read-only file systems."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=".selfshape-probe-", dir=folder)
    except OSError as e:
        raise SelfshapeError(f"{shown}: cannot write in {folder} ({e.strerror or e})") from None
    os.close(fd)
    os.remove(tmp)


def _probe_folder(folder: str, shown: str) -> None:
    """The folder exists and can be written, or it can be created (tried: its missing parts are
    made, probed and removed again, so a name too long, a path under a file or a read-only
    file system is caught before the work, not after it)."""
    if os.path.isdir(folder):
        _probe_writable(folder, shown)
        return
    a = os.path.abspath(folder)
    missing = []
    while not os.path.lexists(a):
        missing.append(a)
        a = os.path.dirname(a)
    if not os.path.isdir(a):
        raise SelfshapeError(f"{shown}: {a} is not a folder")
    try:
        os.makedirs(folder)
    except OSError as e:
        for d in missing:
            with contextlib.suppress(OSError):
                os.rmdir(d)
        raise SelfshapeError(f"{shown}: cannot create the folder ({e.strerror or e})") from None
    try:
        _probe_writable(folder, shown)
    finally:
        for d in missing:                   # deepest first
            with contextlib.suppress(OSError):
                os.rmdir(d)


def _name_fits(path: str, shown: str) -> None:
    """The file name is not longer than its file system allows (else the final rename fails)."""
    folder = os.path.dirname(os.path.abspath(path))
    try:
        limit = os.pathconf(folder if os.path.isdir(folder) else "/", "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    if len(os.fsencode(os.path.basename(path))) > limit:
        raise SelfshapeError(f"{shown}: the file name is longer than the {limit} bytes the file system allows")


def _check_entry(path: str, shown: str, inputs) -> None:
    """An output file path that may exist already: only a regular file (not a link, a folder,
    a device such as /dev/null) that is not one of the inputs may be replaced."""
    if os.path.islink(path):
        raise SelfshapeError(f"{shown}: is a symbolic link; outputs are never written through links "
                             f"(remove it or choose another output)")
    if not os.path.exists(path):
        return
    if os.path.isdir(path):
        raise SelfshapeError(f"{shown}: is a folder, a file is asked")
    if not os.path.isfile(path):
        raise SelfshapeError(f"{shown}: exists and is not a regular file")
    for i in inputs:
        if _same(path, i):
            raise SelfshapeError(f"{shown}: is the input file {os.fspath(i)}; choose another output")


def _text_path(path, what: str) -> str:
    try:
        p = os.fspath(path)
    except TypeError:
        raise SelfshapeError(f"{what}: the output path must be a path, got {path!r}") from None
    if not isinstance(p, str):
        p = os.fsdecode(p)
    if not p.strip():
        raise SelfshapeError(f"{what}: the path is empty")
    if "\0" in p:
        raise SelfshapeError(f"{what}: the output path contains a NUL character")
    return p


def check_output_file(path, *, inputs=(), suffix: str | None = None, create_parents: bool = True,
                      what: str = "output file (-o)") -> str:
    """Check, before any work, that one output file can be written at ``path``; returns it as a str.

    Refused (SelfshapeError naming the path): empty, a folder, a symbolic link, an existing
    non-regular file (/dev/null), one of ``inputs``, a path under a file, an unwritable
    folder, a wrong ``suffix`` (e.g. ".msh", case-insensitive). ``create_parents``: missing
    parent folders will be created (else their absence is refused)."""
    p = _text_path(path, what)
    if suffix is not None and os.path.splitext(p)[1].lower() != suffix.lower():
        raise SelfshapeError(f"{p}: the {what} must be a {suffix} file")
    if p.endswith(os.sep) or (os.altsep and p.endswith(os.altsep)):
        raise SelfshapeError(f"{p}: names a folder, a file is asked")
    _check_entry(p, p, inputs)
    parent = os.path.dirname(os.path.abspath(p))
    if not os.path.isdir(parent) and not create_parents:
        if os.path.lexists(parent):
            raise SelfshapeError(f"{p}: {parent} is not a folder")
        raise SelfshapeError(f"{p}: directory {parent} does not exist")
    _probe_folder(parent, p)
    _name_fits(p, p)
    return p


class OutputDir:
    """The files one run of a verb writes into a folder: ``names`` (exact file names) and
    ``patterns`` (regular expressions of names whose number depends on the data, e.g. one
    plot per tensile orientation). Constructing it checks the folder and every existing
    output entry (see the module doc); call it before the work.

        out = OutputDir(out_dir, ("deployed.vtu", "summary.json"), inputs=[pattern_path])
        with out:                      # begin(): stale outputs removed
            ...compute...
            out.write("deployed.vtu", lambda tmp: meshio.write(tmp, mesh))
            out.write_json("summary.json", summary)       # last

    On an exception (Ctrl-C included) inside the ``with`` block every file this run wrote is
    removed, and the folders it created if they are empty; the exception propagates."""

    def __init__(self, path, names=(), *, patterns=(), inputs=(), what: str = "output folder (-o)"):
        p = _text_path(path, what)
        self.path = p
        self.names = tuple(names)
        self.patterns = tuple(re.compile(x) for x in patterns)
        self.inputs = [os.fspath(i) for i in inputs if i is not None]
        self.written: list[str] = []
        self._created: list[str] = []
        self._begun = False
        self.check()

    # -- checks
    def known(self, name: str) -> bool:
        """Whether ``name`` is one of this verb's output names."""
        return name in self.names or any(r.fullmatch(name) for r in self.patterns)

    def file(self, name: str) -> str:
        """The path of output ``name`` in the folder (``name`` must be a known output)."""
        if not self.known(name):
            raise ValueError(f"{name!r} is not one of this verb's outputs {self.names}")
        return os.path.join(self.path, name)

    def _entries(self):
        names = list(self.names)
        if self.patterns and os.path.isdir(self.path):
            try:
                listed = os.listdir(self.path)
            except OSError as e:
                raise SelfshapeError(f"{self.path}: cannot list the folder ({e.strerror or e})") from None
            names += sorted(n for n in listed if n not in self.names and any(r.fullmatch(n) for r in self.patterns))
        return [(n, os.path.join(self.path, n)) for n in names]

    def check(self) -> None:
        """The folder can hold this run's outputs: see the module doc (SelfshapeError if not)."""
        p = self.path
        if os.path.lexists(p) and not os.path.isdir(p):
            kind = "a symbolic link that does not lead to a folder" if os.path.islink(p) else \
                "a file" if os.path.isfile(p) else "not a folder"
            raise SelfshapeError(f"{p}: exists and is {kind}; the output must be a folder")
        for i in self.inputs:
            if _same(p, i):
                raise SelfshapeError(f"{p}: is the input {i}; choose another output folder")
        if os.path.isdir(p):
            for _, f in self._entries():
                _check_entry(f, f, self.inputs)
        _probe_folder(p, p)

    # -- the run
    def begin(self) -> "OutputDir":
        """Check again (time has passed) and remove the outputs an earlier run of this verb
        left in the folder (its known names only, regular files only). The folder itself is
        created by the first write, so a run that fails before writing creates nothing."""
        if self._begun:
            return self
        self.check()
        if os.path.isdir(self.path):
            for _, f in self._entries():
                if os.path.isfile(f) and not os.path.islink(f):
                    try:
                        os.remove(f)
                    except OSError as e:
                        raise SelfshapeError(f"{f}: cannot remove the earlier run's output "
                                             f"({e.strerror or e})") from None
        self._begun = True
        return self

    def makedirs(self) -> str:
        """Create the folder and its missing parents (remembered, so that abort() can remove
        them again if they are left empty); returns the folder."""
        self.begin()
        if not os.path.isdir(self.path):
            a = os.path.abspath(self.path)
            missing = []
            while not os.path.isdir(a):
                missing.append(a)
                a = os.path.dirname(a)
            try:
                os.makedirs(self.path, exist_ok=True)
            except OSError as e:
                raise SelfshapeError(f"{self.path}: cannot create the folder ({e.strerror or e})") from None
            self._created = missing + self._created          # deepest first
        return self.path

    def write(self, name: str, writer) -> str:
        """Write output ``name`` atomically: ``writer(tmp_path)`` writes the content to a
        temporary path in the folder with the same suffix; it is then renamed into place."""
        p = self.file(name)
        self.makedirs()
        self.written.append(p)
        write_atomic(p, writer)
        return p

    def write_json(self, name: str, obj, *, indent=2) -> str:
        """Write ``obj`` as JSON (numpy values converted; NaN/Infinity refused: NonFiniteOutput)."""
        text = json_text(obj, self.file(name), indent=indent)
        return self.write(name, lambda tmp: _write_text(tmp, text))

    def write_text(self, name: str, text: str) -> str:
        """Write the string ``text`` (UTF-8)."""
        return self.write(name, lambda tmp: _write_text(tmp, text))

    def abort(self) -> None:
        """Remove this run's outputs and the folders it created if they are left empty. After
        begin() every known output in the folder is this run's (the earlier ones were removed),
        so files written by helpers that write on their own (e.g. G-code, plots) go too."""
        if self._begun and os.path.isdir(self.path):
            for _, f in self._entries():
                try:
                    if os.path.isfile(f) and not os.path.islink(f):
                        os.remove(f)
                except OSError:
                    pass
        self.written = []
        for d in self._created:            # deepest first
            try:
                os.rmdir(d)
            except OSError:
                break
        self._created = []

    def __enter__(self):
        return self.begin()

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None:
            self.abort()
        return False


# ----------------------------------------------------------------------------- writing
def _write_text(path: str, text: str) -> None:
    with open(path, "w", encoding="utf-8", newline="") as f:
        f.write(text)


@contextlib.contextmanager
def parents_created(path):
    """Create the missing parent folders of the file ``path`` for the duration of a write; if
    the block fails (or is interrupted), the folders this call created are removed again
    (innermost first, only while empty), so a failed run leaves no trace."""
    parent = os.path.dirname(os.path.abspath(os.fspath(path)))
    missing = []
    d = parent
    while not os.path.isdir(d):
        missing.append(d)
        d = os.path.dirname(d)
    try:
        os.makedirs(parent, exist_ok=True)
    except OSError as e:
        raise SelfshapeError(f"{path}: cannot create {parent} ({e.strerror or e})") from None
    try:
        yield
    except BaseException:
        for d in missing:                       # innermost first
            try:
                os.rmdir(d)
            except OSError:
                break
        raise


def write_atomic(path, writer) -> str:
    """Write ``path`` through a temporary file in the same folder (same suffix) that
    ``writer(tmp_path)`` fills, then os.replace: readers never see a partial file, and a
    failure or Ctrl-C leaves the old state (the temporary file is removed). A symbolic link
    at ``path`` is refused, never written through. OSError becomes a one-line SelfshapeError."""
    path = os.fspath(path)
    if os.path.islink(path):
        raise SelfshapeError(f"{path}: is a symbolic link; outputs are never written through links")
    folder = os.path.dirname(os.path.abspath(path))
    stem, ext = os.path.splitext(os.path.basename(path))
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{stem}.", suffix=ext or ".partial", dir=folder)
    except OSError as e:
        raise SelfshapeError(f"cannot write {path}: {e.strerror or e}") from None
    os.close(fd)
    try:
        writer(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except OSError as e:
        raise SelfshapeError(f"cannot write {path}: {e.strerror or e}") from None
    finally:
        if os.path.lexists(tmp):
            os.remove(tmp)
    return path


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def write_text_file(path, text: str) -> str:
    """Write a text file atomically (see write_atomic)."""
    return write_atomic(path, lambda tmp: _write_text(tmp, text))


# ----------------------------------------------------------------------------- finiteness
def _fmt_key(where: str, keys) -> str:
    k = "".join(f"[{x}]" if isinstance(x, int) else (f".{x}" if i else str(x)) for i, x in enumerate(keys))
    return f"{where}: {k}" if k else where


def plain(obj, where: str = "output", _keys=()):
    """A JSON-ready copy of ``obj``: numpy scalars and arrays to Python numbers and lists,
    tuples to lists; a NaN or infinite number is a NonFiniteOutput naming ``where`` and its key."""
    if isinstance(obj, dict):
        return {str(k): plain(v, where, _keys + (k,)) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v, where, _keys + (i,)) for i, v in enumerate(obj)]
    if isinstance(obj, np.ndarray):
        return plain(obj.tolist(), where, _keys)
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        raise NonFiniteOutput(f"{_fmt_key(where, _keys)} is {obj}, not a finite number; nothing is written")
    return obj


def check_finite(obj, where: str = "output") -> None:
    """NonFiniteOutput if any number in the nested dict/list/array ``obj`` is NaN or infinite."""
    plain(obj, where)


def json_text(obj, where: str = "output", *, indent=2) -> str:
    """``obj`` as strict JSON text (trailing newline); NaN/Infinity refused (NonFiniteOutput)."""
    return json.dumps(plain(obj, os.path.basename(str(where))), indent=indent, allow_nan=False) + "\n"


def write_json(path, obj, *, indent=2) -> str:
    """Write ``obj`` to ``path`` as strict JSON, atomically; NaN/Infinity refused, naming the key."""
    text = json_text(obj, path, indent=indent)
    return write_text_file(path, text)


def check_finite_arrays(where: str, arrays: dict) -> None:
    """NonFiniteOutput naming ``where`` and the array (and its first bad index) if any of the
    numeric ``arrays`` {name: array} holds NaN or infinity."""
    for name, a in arrays.items():
        a = np.asarray(a)
        if a.dtype.kind not in "fc":
            continue
        bad = ~np.isfinite(a)
        if bad.any():
            idx = np.unravel_index(int(np.flatnonzero(bad.ravel())[0]), a.shape) if a.ndim else ()
            at = f"[{', '.join(str(int(i)) for i in idx)}]" if a.ndim else ""
            raise NonFiniteOutput(f"{where}: {name}{at} is {a[idx] if a.ndim else a}, not a finite number "
                                  f"({int(bad.sum())} such values); nothing is written")
