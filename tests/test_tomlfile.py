"""geometry.tomlfile.read_toml: one reader, one wording, for pattern and printer files."""
import pytest

from shellfem.errors import SelfshapeError
from geometry.tomlfile import read_toml


def test_reads_a_table(tmp_path):
    p = tmp_path / "a.toml"
    p.write_text("[mesh]\nsize_mm = 2.0\n")
    assert read_toml(str(p)) == {"mesh": {"size_mm": 2.0}}


@pytest.mark.parametrize("make, word", [
    (lambda d: d / "missing.toml", "file not found"),
    (lambda d: d, "is a directory"),
    (lambda d: (d / "b.toml").write_bytes(b"\xff\xfe\x00") and d / "b.toml", "not a UTF-8 text file"),
    (lambda d: (d / "c.toml").write_text("[mesh\n") and d / "c.toml", "malformed TOML: "),
])
def test_failures_are_one_line_with_the_label(tmp_path, make, word):
    with pytest.raises(SelfshapeError) as e:
        read_toml(str(make(tmp_path)), "my file")
    msg = str(e.value)
    assert msg.startswith("my file: ") and word in msg and "\n" not in msg


def test_a_byte_order_mark_is_not_content(tmp_path):
    """Windows editors save UTF-8 with a BOM, which TOML forbids; it was "malformed TOML:
    Invalid statement (at line 1, column 1)" (issue 19)."""
    p = tmp_path / "bom.toml"
    p.write_bytes(b"\xef\xbb\xbf[mesh]\r\nsize_mm = 2.0\r\n")
    assert read_toml(str(p)) == {"mesh": {"size_mm": 2.0}}
