"""shellfem.infiles: what a verb may read (issue 19). A path that is not a regular file (a
device, a named pipe, a folder) is refused before a byte is read: /dev/zero was read until a
MemoryError and a FIFO blocked forever; a file over the cap is refused; a byte-order mark is
not content; meshio's exit() on a malformed file is one line."""
from __future__ import annotations

import contextlib
import os
import signal

import pytest

from shellfem.errors import SelfshapeError
from shellfem.infiles import check_input_file, decode_text, read_input_bytes, read_input_text, read_meshio


@contextlib.contextmanager
def deadline(seconds=10):
    """Fail instead of hanging if a read blocks (a FIFO opened without O_NONBLOCK)."""
    def boom(*_):
        raise TimeoutError("the read blocked")
    old = signal.signal(signal.SIGALRM, boom)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _fifo(d):
    p = d / "pipe.toml"
    os.mkfifo(p)
    return p


def _link(d, target):
    p = d / "link.csv"
    p.symlink_to(target)
    return p


@pytest.mark.parametrize("make, word", [
    (lambda d: d / "missing.csv", "file not found"),
    (lambda d: _link(d, d / "nowhere"), "file not found"),
    (lambda d: d, "is a directory"),
    (_fifo, "is a named pipe (FIFO)"),
    (lambda d: "/dev/zero", "is a device"),
    (lambda d: _link(d, "/dev/urandom"), "is a device"),
])
@pytest.mark.parametrize("reader", [read_input_bytes, read_input_text, check_input_file])
def test_what_is_not_a_regular_file_is_refused_before_reading(tmp_path, make, word, reader):
    path = make(tmp_path)
    with deadline(), pytest.raises(SelfshapeError) as e:
        reader(path, "lab table", "my.csv")
    msg = str(e.value)
    assert msg.startswith("my.csv: ") and word in msg and "\n" not in msg


def test_symlink_loop_and_size_cap(tmp_path):
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    with pytest.raises(SelfshapeError, match="cannot read"):
        read_input_bytes(tmp_path / "a", "file", "a")
    big = tmp_path / "big.toml"
    big.write_bytes(b"#" * 1001)
    with pytest.raises(SelfshapeError, match=r"big.toml: 1001 bytes, larger than any TOML file \(1000 bytes\)"):
        read_input_bytes(big, "TOML file", "big.toml", max_bytes=1000)
    assert read_input_bytes(big, "TOML file", "big.toml", max_bytes=1001) == b"#" * 1001


def test_a_link_to_a_regular_file_is_read(tmp_path):
    (tmp_path / "data.csv").write_text("a,b\n")
    assert read_input_text(_link(tmp_path, tmp_path / "data.csv")) == "a,b\n"


def test_text_drops_a_byte_order_mark_and_names_the_line_of_bad_bytes():
    assert decode_text(b"\xef\xbb\xbfa,b\r\n1,2\r\n", "CSV", "x.csv") == "a,b\r\n1,2\r\n"
    with pytest.raises(SelfshapeError, match=r"x.csv: line 3: not UTF-8 text \(byte 0xe9\); expected a CSV"):
        decode_text(b"a\nb\ncaf\xe9\n", "CSV", "x.csv")


@pytest.mark.parametrize("name, content", [
    ("empty.ply", b""),                                     # meshio calls exit("Expected ply")
    ("garbage.vtu", b"<VTKFile>"),                          # meshio calls exit() too
    ("cut.msh", b"$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 3 1 3\n"),
], ids=["empty-ply", "garbage-vtu", "cut-msh"])
def test_meshio_failures_are_one_line(tmp_path, capsys, name, content):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(SelfshapeError) as e:
        read_meshio(tmp_path / name, "target mesh", name)
    assert str(e.value).startswith(f"{name}: cannot read the target mesh") and "\n" not in str(e.value)
    assert capsys.readouterr().out == ""
