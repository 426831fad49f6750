"""The files a verb reads: a regular file of bounded size, read once, errors in one line.

Every reader of a user's file (pattern and printer TOML, G-code, target meshes, law and
contraction tables, the lab's CSV and JSON) opens it through this module (the lowest layer,
beside shellfem.outfiles, so that geometry, inverse and validation share it). Why: a path
can name something that is not a file, and reading it naively either never ends or
exhausts memory before any check runs (``selfshape mesh /dev/zero`` read until a
MemoryError, a named pipe (FIFO) blocked forever, a directory gave a raw IsADirectoryError
or "file not found"). So, before a byte is parsed:

- the path must exist (a dangling link is "file not found"), not be a folder, and be a
  *regular file*: devices (``/dev/zero``, ``/dev/urandom``), pipes and sockets are refused,
  also behind a symbolic link (links to regular files are fine);
- it must be at most ``max_bytes`` long (default :data:`MAX_INPUT_BYTES`; readers pass
  smaller caps where parsing multiplies memory), checked on the open file descriptor and
  again by reading at most ``max_bytes + 1`` bytes, so a file that grows while read is caught;
- the file is opened without blocking (``O_NONBLOCK``), and its type is checked on the open
  descriptor (``fstat``), so a pipe swapped in after the check cannot block the read either;
- text is UTF-8, an optional byte-order mark (``EF BB BF``, what Windows editors write) is
  dropped; bytes that are not UTF-8 are an error naming the line they are on.

Errors are :class:`shellfem.errors.SelfshapeError` of one line starting with the caller's
``label`` (the path or file name it shows its user). File contents are never quoted.
"""
from __future__ import annotations

import os
import stat

from shellfem.errors import SelfshapeError

#: Largest input file any verb reads (bytes): 256 MB. A pattern is kilobytes, a large print's
#: G-code tens of megabytes, a lab's tensile CSV a few megabytes.
MAX_INPUT_BYTES = 256 * 1024 * 1024


def _kind(mode: int) -> str | None:
    """What a non-regular file is, in words (None for a regular file)."""
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a named pipe (FIFO)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def _refuse(label: str, kind: str, what: str):
    raise SelfshapeError(f"{label}: is {kind}, not a file; expected a {what}")


def _oserror(label: str, e: OSError, what: str):
    if isinstance(e, FileNotFoundError):
        raise SelfshapeError(f"{label}: file not found") from None
    if isinstance(e, NotADirectoryError):
        raise SelfshapeError(f"{label}: file not found (a folder on its path is a file)") from None
    if isinstance(e, IsADirectoryError):
        _refuse(label, "a directory", what)
    raise SelfshapeError(f"{label}: cannot read ({e.strerror or type(e).__name__})") from None


def check_input_file(path, what: str = "input file", label: str | None = None,
                     max_bytes: int = MAX_INPUT_BYTES) -> int:
    """Check that ``path`` is a regular file (links followed) of at most ``max_bytes``;
    returns its size in bytes. For readers that hand the path to a library (meshio) which
    opens it itself. SelfshapeError otherwise (see the module doc)."""
    label = str(path) if label is None else label
    try:
        p = os.fspath(path)
        if "\0" in (p if isinstance(p, str) else os.fsdecode(p)):
            raise SelfshapeError(f"{label}: the path contains a NUL character")
        st = os.stat(p)
    except TypeError:
        raise SelfshapeError(f"{label}: not a file path") from None
    except OSError as e:
        _oserror(label, e, what)
    kind = _kind(st.st_mode)
    if kind:
        _refuse(label, kind, what)
    if st.st_size > max_bytes:
        raise SelfshapeError(f"{label}: {st.st_size} bytes, larger than any {what} ({max_bytes} bytes)")
    return int(st.st_size)


def read_input_bytes(path, what: str = "input file", label: str | None = None,
                     max_bytes: int = MAX_INPUT_BYTES) -> bytes:
    """The bytes of a regular input file of at most ``max_bytes`` (see the module doc)."""
    label = str(path) if label is None else label
    check_input_file(path, what, label, max_bytes)
    try:
        fd = os.open(os.fspath(path), os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as e:
        _oserror(label, e, what)
    try:
        st = os.fstat(fd)
        kind = _kind(st.st_mode)
        if kind:                        # replaced between the check and the open
            _refuse(label, kind, what)
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        with os.fdopen(fd, "rb", closefd=True) as f:
            fd = None
            data = f.read(max_bytes + 1)
    except OSError as e:
        _oserror(label, e, what)
    finally:
        if fd is not None:
            os.close(fd)
    if len(data) > max_bytes:
        raise SelfshapeError(f"{label}: larger than any {what} ({max_bytes} bytes)")
    return data


def decode_text(data: bytes, what: str, label: str) -> str:
    """UTF-8 text of ``data`` without a leading byte-order mark; bytes that are not UTF-8
    are a SelfshapeError naming the line and the byte."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[:e.start].count(b"\n") + 1
        raise SelfshapeError(f"{label}: line {line}: not UTF-8 text (byte 0x{data[e.start]:02x}); "
                             f"expected a {what}") from None


def read_input_text(path, what: str = "text file", label: str | None = None,
                    max_bytes: int = MAX_INPUT_BYTES) -> str:
    """The UTF-8 text of a regular input file (BOM dropped); see the module doc."""
    label = str(path) if label is None else label
    return decode_text(read_input_bytes(path, what, label, max_bytes), what, label)


def read_meshio(path, what: str = "mesh file", label: str | None = None, file_format: str | None = None,
                max_bytes: int = MAX_INPUT_BYTES):
    """``meshio.read(path)`` of a checked regular input file, with every failure a one-line
    SelfshapeError: meshio raises many exception types, and some of its readers call
    ``exit()`` on a malformed file (an empty .ply, a truncated .vtu: SystemExit, which ended
    ``selfshape design`` with status 1 and a stray line instead of status 2), and print to
    stdout while reading; both are kept from the user."""
    import contextlib
    import io

    import meshio
    label = str(path) if label is None else label
    check_input_file(path, what, label, max_bytes)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            return meshio.read(os.fspath(path), file_format=file_format)
    except (Exception, SystemExit) as exc:
        text = str(exc.code if isinstance(exc, SystemExit) else exc)
        msg = " ".join(text.split()[:20]) or type(exc).__name__
        raise SelfshapeError(f"{label}: cannot read the {what} ({msg})") from None


def csv_error_text(error) -> str:
    """The user's reading of a csv.Error: the csv module's field limit named with its size."""
    import csv
    msg = " ".join(str(error).split())
    if "field larger than field limit" in msg:
        return f"a field longer than {csv.field_size_limit()} characters (the csv module's limit)"
    return msg
