"""Scene files are UTF-8: a UTF-8 byte order mark at the start is skipped; any other encoding is a ConfigError naming
the file, line, column and byte offset of the first byte that is not UTF-8 (not a traceback)."""

from __future__ import annotations

import pytest

from fepr.cli import EXIT_INVALID, main
from fepr.errors import ConfigError
from fepr.scene import load_scene

SCENE = """\
[scene]
name = "encoded"
description = "{description}"

[mesh]
builtin = "box"
size = 0.1
resolution = 1

[material]
youngs_modulus = 1e5
poisson_ratio = 0.3

[mass]
density = 1000.0

[run]
steps = 2
"""


def test_utf8_scene_with_non_ascii_text_loads(tmp_path):
    path = tmp_path / "s.toml"
    path.write_bytes(SCENE.format(description="café à Zürich").encode("utf-8"))
    assert load_scene(path).description == "café à Zürich"


def test_utf8_bom_is_accepted(tmp_path):
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf" + SCENE.format(description="café").encode("utf-8"))
    scene = load_scene(path)
    assert scene.name == "encoded" and scene.description == "café"


def test_utf8_bom_keeps_toml_error_lines(tmp_path):
    path = tmp_path / "bom_bad.toml"
    path.write_bytes(b"\xef\xbb\xbf[scene]\nname = \n")
    with pytest.raises(ConfigError, match=r"invalid TOML: .*line 2"):
        load_scene(path)


def test_latin1_scene_names_file_line_column_and_offset(tmp_path):
    path = tmp_path / "latin1.toml"
    raw = SCENE.format(description="café").encode("latin-1")
    path.write_bytes(raw)
    offset = raw.index(b"\xe9")
    with pytest.raises(ConfigError) as info:
        load_scene(path)
    msg = str(info.value)
    assert msg.startswith(f"{path} line 3, column 19 (byte offset {offset}): not UTF-8 text: byte 0xe9"), msg
    assert "after 'description = \"caf'" in msg
    assert "save the file as UTF-8" in msg


def test_utf16_scene_says_so(tmp_path):
    path = tmp_path / "utf16.toml"
    path.write_bytes(SCENE.format(description="x").encode("utf-16"))
    with pytest.raises(ConfigError, match=r"utf16\.toml: the file is UTF-16 text .*save it as UTF-8"):
        load_scene(path)


def test_cli_reports_non_utf8_scene_without_traceback(tmp_path, capsys):
    path = tmp_path / "latin1.toml"
    path.write_bytes(SCENE.format(description="café").encode("latin-1"))
    code = main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code == EXIT_INVALID
    assert "line 3, column 19" in err and "not UTF-8 text" in err, err
    assert "Traceback" not in err and "UnicodeDecodeError" not in err


def test_cli_runs_scene_with_bom(tmp_path, capsys):
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf" + SCENE.format(description="ok").encode("utf-8"))
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 0
