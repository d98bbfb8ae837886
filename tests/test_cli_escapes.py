"""``wandell`` never writes a raw control character it did not mean
(issue 17, item 11; reproduction ``cli_terminal_escapes.py``): file names,
errors, notes, warnings and usage errors are shown with visible escapes."""

from __future__ import annotations

import io
import os

import pytest

from service import cli
from testing.dngwriter import scene_dng

RAW_CONTROLS = [chr(c) for c in range(0x20) if chr(c) not in "\n\r\t"] + ["\x7f", "\x9b", "\u202e"]


def test_term_safe_escapes_controls_and_keeps_text():
    assert cli.term_safe("b\x1b[1A\x1b[2K.dng") == "b\\x1b[1A\\x1b[2K.dng"
    assert cli.term_safe("c\x1b]0;owned\x07.dng") == "c\\x1b]0;owned\\x07.dng"
    assert cli.term_safe("a\rb\nc\td\x7fe\x9bf\u202eg\u2066h") == "a\\x0db\\x0ac\\x09d\\x7fe\\x9bf\\u202eg\\u2066h"
    assert cli.term_safe(os.fsdecode(b"caf\xff.dng")) == "caf\\xff.dng"  # not UTF-8: the byte, not a crash
    assert cli.term_safe("José 写真 Привет.dng (2)") == "José 写真 Привет.dng (2)"
    assert cli.term_safe("x\ny\r", keep="\n") == "x\ny\\x0d"


def _no_controls(text: str) -> bool:
    return not any(ch in text for ch in RAW_CONTROLS)


def test_batch_table_failures_and_usage_errors_show_names_escaped(tmp_path, capsys):
    """A valid file named b ESC[1A ESC[2K .dng erased the table row of the
    failed file above it on a terminal; ESC]0;...BEL set the window title;
    a broken file so named did the same in --quiet's failure lines."""
    d = tmp_path / "in"
    d.mkdir()
    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D50", 48, 64, seed=1)
    (d / "a_broken.dng").write_bytes(b"not a raw file")
    (d / "d\x1b[2K\r\x9b_broken.dng").write_bytes(b"not a raw file either")
    for name in ("b\x1b[1A\x1b[2K.dng", "c\x1b]0;owned\x07.dng"):
        (d / name).write_bytes(buf.getvalue())
    out = tmp_path / "out"
    args = ["batch", str(d), str(out), "--format", "jpeg", "--method", "gray-world", "--workers", "1"]
    assert cli.main(args) == 1
    std = capsys.readouterr()
    assert _no_controls(std.out) and _no_controls(std.err), (std.out, std.err)
    assert "b\\x1b[1A\\x1b[2K.dng" in std.out and "c\\x1b]0;owned\\x07.dng" in std.out
    assert "d\\x1b[2K\\x0d\\x9b_broken.dng" in std.out and "a_broken.dng" in std.out
    assert len([ln for ln in std.out.splitlines() if "failed" in ln and "broken" in ln]) == 2
    assert cli.main(args + ["--quiet"]) == 1  # the done ones are skipped, the broken ones fail again
    std = capsys.readouterr()
    assert std.out == "" and _no_controls(std.err) and "d\\x1b[2K\\x0d\\x9b_broken.dng: failed:" in std.err
    with pytest.raises(SystemExit):
        cli.main(["batch", str(d), str(out), "\x1b]0;title\x07", "--bogus\x1b[2J"])
    std = capsys.readouterr()
    assert _no_controls(std.err) and "\\x1b]0;title\\x07" in std.err
    assert cli.main(["batch", str(tmp_path / "no\x1b[2Jdir"), str(out)]) == 2
    std = capsys.readouterr()
    assert _no_controls(std.err) and "\\x1b[2J" in std.err
