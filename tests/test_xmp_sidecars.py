"""Issue 19, item 10: Camera Raw XMP sidecars where editors look for them.

``wandell white-balance --xmp`` and ``wandell batch --xmp`` write the sidecar
beside the RAW (``IMG_0001.dng`` -> ``IMG_0001.xmp``, Lightroom/Camera Raw;
``--xmp-name full``: ``IMG_0001.dng.xmp``, darktable/digiKam), never over an
existing one unless ``--xmp-overwrite``, and into OUT (saying so) when the
RAW's folder cannot be written. With the real CinemaDNG."""

from __future__ import annotations

import contextlib
import io
import os
import re
import shutil
from concurrent.futures import ThreadPoolExecutor

import pytest

from service import cli, outputs

from .test_dng_render import real_file


@pytest.fixture()
def shoot(tmp_path):
    """A folder with the real CinemaDNG, and an output folder elsewhere."""
    raw = tmp_path / "card"
    raw.mkdir()
    shutil.copy(real_file("Blackmagic.dng"), raw / "IMG_0001.dng")
    out = tmp_path / "out"
    out.mkdir()
    return raw, out


def _run(*argv) -> tuple[int, str, str]:
    o, e = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(o), contextlib.redirect_stderr(e):
        rc = cli.main(list(argv))
    return rc, o.getvalue(), e.getvalue()


def _temperature(path) -> int:
    return int(re.search(r'crs:Temperature="(\d+)"', path.read_text(encoding="utf-8")).group(1))


def test_sidecar_names():
    assert cli.sidecar_path("/a/b/IMG_0001.dng") == "/a/b/IMG_0001.xmp"
    assert cli.sidecar_path("/a/b/IMG_0001.dng", "full") == "/a/b/IMG_0001.dng.xmp"
    assert cli.sidecar_path("rel/IMG_1.CR2") == os.path.join(os.getcwd(), "rel", "IMG_1.xmp")


def test_white_balance_xmp_goes_beside_the_raw_and_is_never_overwritten(shoot):
    raw, out = shoot
    src = raw / "IMG_0001.dng"
    rc, stdout, stderr = _run("white-balance", str(src), str(out / "IMG_0001.jpg"), "--xmp")
    assert rc == 0, stderr
    side = raw / "IMG_0001.xmp"
    assert side.exists() and not (out / "IMG_0001.xmp").exists()
    assert f"XMP sidecar: {side}" in stdout
    text = side.read_text(encoding="utf-8")
    assert 'crs:WhiteBalance="Custom"' in text
    got = outputs.read_wandell_xmp(text)
    assert got["Method"] and len(got["CameraRGB"]) == 3 and 2000 < got["CCT"] < 12000
    # an existing sidecar (an editor's) is kept, and the run says so
    side.write_text("<editor's own/>", encoding="utf-8")
    rc, stdout, _ = _run("white-balance", str(src), str(out / "IMG_0001.jpg"), "--xmp")
    assert rc == 0
    assert side.read_text(encoding="utf-8") == "<editor's own/>"
    assert "exists: kept" in stdout and "--xmp-overwrite" in stdout
    rc, _, _ = _run("white-balance", str(src), str(out / "IMG_0001.jpg"), "--xmp", "--xmp-overwrite")
    assert rc == 0 and side.read_text(encoding="utf-8") == text
    # darktable's name, on request
    rc, _, _ = _run("white-balance", str(src), str(out / "IMG_0001.jpg"), "--xmp-name", "full", "--xmp")
    assert rc == 0 and (raw / "IMG_0001.dng.xmp").read_text(encoding="utf-8") == text


def test_xmp_is_a_flag_that_never_takes_the_raw_as_its_value(shoot):
    """Issue 29, item 5: ``wandell white-balance --xmp IMG.dng out.tif`` took
    the RAW as the sidecar's path and then said "arguments are required:
    out". ``--xmp`` is a flag; ``--xmp-dir DIR`` puts the sidecar elsewhere
    (the sidecar's name still follows the RAW's)."""
    raw, out = shoot
    src = raw / "IMG_0001.dng"
    rc, stdout, stderr = _run("white-balance", "--xmp", str(src), str(out / "IMG_0001.png"))
    assert rc == 0, stderr
    assert (out / "IMG_0001.png").stat().st_size > 0 and (raw / "IMG_0001.xmp").exists()
    side_dir = out / "sidecars"
    rc, stdout, stderr = _run("white-balance", "--xmp-dir", str(side_dir), str(src), str(out / "IMG_0001.jpg"))
    assert rc == 0, stderr
    assert (side_dir / "IMG_0001.xmp").read_text(encoding="utf-8") == (raw / "IMG_0001.xmp").read_text(encoding="utf-8")
    # a misused sidecar option is named, exit 2
    with contextlib.redirect_stderr(io.StringIO()) as err:
        assert cli.main(["white-balance", str(src), str(out / "x.png"), "--xmp", "--xmp-name", "ful"]) == 2
    assert "--xmp-name 'ful' unknown; accepted: stem, full" in err.getvalue()
    assert not (out / "x.png").exists()
    # a value after the flag is not its argument: it is a (surplus) positional, and argparse says so
    with pytest.raises(SystemExit) as e, contextlib.redirect_stderr(io.StringIO()) as err:
        cli.main(["white-balance", str(src), str(out / "x.png"), "--xmp", "elsewhere.xmp"])
    assert e.value.code == 2 and "unrecognized arguments: elsewhere.xmp" in err.getvalue()


def test_white_balance_xmp_falls_back_beside_out_when_the_raw_folder_is_read_only(shoot, monkeypatch):
    raw, out = shoot
    real_access = os.access

    def access(path, mode, *a, **k):      # the card is read-only (root ignores chmod, so say it here)
        if mode & os.W_OK and os.path.abspath(path) == str(raw):
            return False
        return real_access(path, mode, *a, **k)

    monkeypatch.setattr(cli.os, "access", access)
    rc, stdout, stderr = _run("white-balance", str(raw / "IMG_0001.dng"), str(out / "IMG_0001.jpg"), "--xmp")
    assert rc == 0, stderr
    assert not (raw / "IMG_0001.xmp").exists() and (out / "IMG_0001.xmp").exists()
    assert f"the RAW's folder {raw} is not writable" in stdout
    assert f"written to {out / 'IMG_0001.xmp'} instead" in stdout and "move it there" in stdout


def test_batch_xmp_writes_one_sidecar_per_raw_beside_it(shoot):
    """``wandell batch --xmp``: a sidecar beside every RAW (the
    subfolder's too with ``--recursive``); a rerun keeps them (and lists
    them as no "not processed" files); the sidecar's light is the item's."""
    raw, out = shoot
    sub = raw / "day2"
    sub.mkdir()
    shutil.copy(raw / "IMG_0001.dng", sub / "IMG_0002.dng")
    rc, stdout, stderr = _run("batch", str(raw), str(out), "--format", "jpeg", "--workers", "1", "-r", "--xmp")
    assert rc == 0, stderr
    for side in (raw / "IMG_0001.xmp", sub / "IMG_0002.xmp"):
        assert side.exists(), sorted(os.listdir(side.parent))
        assert 'crs:WhiteBalance="Custom"' in side.read_text(encoding="utf-8")
    assert not list(out.rglob("*.xmp"))
    assert "XMP sidecars: 2 written (2 beside their RAW)" in stdout
    first = (raw / "IMG_0001.xmp").read_text(encoding="utf-8")
    rc, stdout, _ = _run("batch", str(raw), str(out), "--format", "jpeg", "--workers", "1", "-r", "--xmp")
    assert rc == 0
    assert "2 kept as they were" in stdout and "not processed" not in stdout
    assert (raw / "IMG_0001.xmp").read_text(encoding="utf-8") == first


def test_batch_xmp_read_only_card_and_darktable_names(shoot, monkeypatch):
    """A read-only card: the sidecars go into OUT_DIR (same relative
    tree) and each row says so; ``--xmp-name full`` names them as darktable
    does; ``--xmp DIR`` puts them in DIR."""
    from service import jobs

    raw, out = shoot
    real_access = os.access

    def access(p, m, *a, **k):
        return False if m & os.W_OK and os.path.abspath(p) == str(raw) else real_access(p, m, *a, **k)

    monkeypatch.setattr(cli.os, "access", access)
    opts = jobs.batch_options(format="jpeg")
    with ThreadPoolExecutor(1) as ex:
        rows = cli.run_batch(str(raw), str(out), opts, executor=ex, quiet=True,
                             xmp={"folder": None, "name": "full", "overwrite": False})
    (row,) = rows
    assert row["status"] == "done" and row["xmp"] == str(out / "IMG_0001.dng.xmp")
    assert "is not writable" in row["note"] and (out / "IMG_0001.dng.xmp").exists()
    assert not (raw / "IMG_0001.dng.xmp").exists()
    elsewhere = raw.parent / "sidecars"
    with ThreadPoolExecutor(1) as ex:
        (row,) = cli.run_batch(str(raw), str(out), opts, executor=ex, quiet=True,
                               xmp={"folder": str(elsewhere), "name": "stem", "overwrite": False})
    assert row["status"] == "skipped" and row["xmp"] == str(elsewhere / "IMG_0001.xmp")
    assert _temperature(elsewhere / "IMG_0001.xmp") == _temperature(out / "IMG_0001.dng.xmp")


def test_sidecar_options_are_declared_once():
    """The flags come from service.schemas.fields.SIDECAR for both commands."""
    from service.schemas.fields import SIDECAR

    for command in ("white-balance", "batch"):
        o = io.StringIO()
        with contextlib.redirect_stdout(o), pytest.raises(SystemExit):
            cli.main([command, "--help"])
        text = o.getvalue()
        for name in SIDECAR:
            assert "--" + name.replace("_", "-") in text, (command, name)
        assert "one of: stem, full" in text


def test_readme_and_page_say_what_a_sidecar_does_for_a_dng():
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    readme = root.joinpath("README.md").read_text(encoding="utf-8")
    section = readme.split("### XMP sidecars and DNGs", 1)[1].split("\n## ", 1)[0]
    for word in ("Lightroom", "DNG", "darktable", "NAME.EXT.xmp", "RawTherapee", ".pp3", "--xmp-overwrite"):
        assert word in section, word
    page = root.joinpath("service", "static", "index.html").read_text(encoding="utf-8")
    help_text = page.split('id="xmp-help"', 1)[1].split("</details>", 1)[0]
    for word in ("Lightroom", "DNG", "darktable", "RawTherapee", "wandell batch IN OUT --xmp"):
        assert word in help_text, word
