"""Issue 13, item 6: the CLI without traps: format from the output's
extension, --force, a note when a rerun's options differ from the stored
ones, warnings in the summary, --version, --quiet, a light start-up."""

from __future__ import annotations

import io
import os
import subprocess
import sys

import pytest

from service import cli, jobs
from service.errors import ServiceError
from testing.dngwriter import scene_dng

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _cli(*args):
    env = dict(os.environ, PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True,
                          timeout=300, env=env, cwd=ROOT)


@pytest.fixture(scope="module")
def shoot(tmp_path_factory):
    d = tmp_path_factory.mktemp("traps")
    scene_dng(d / "a.dng", "Nikon 5100 (NPL)", "D5000", 48, 64, seed=1)
    return d


@pytest.mark.parametrize("out,given,want", [
    ("x.tif", None, "tiff"), ("x.TIFF", None, "tiff"), ("x.png", None, "png"), ("x.png", "png16", "png16"),
    ("x.jpg", None, "jpeg"), ("x.jpeg", "jpeg", "jpeg"), ("noext", "png", "png")])
def test_format_from_the_extension(out, given, want):
    assert cli.format_for(out, given) == want


@pytest.mark.parametrize("out,given,code", [
    ("x.png", "tiff", "format_mismatch"), ("x.jpg", "png", "format_mismatch"), ("x.tif", "jpeg", "format_mismatch"),
    ("x.bmp", None, "invalid_parameter"), ("noext", None, "invalid_parameter")])
def test_format_disagreement_is_an_error(out, given, code):
    with pytest.raises(ServiceError) as e:
        cli.format_for(out, given)
    assert e.value.code == code


def test_white_balance_writes_what_the_name_says(shoot, tmp_path):
    r = _cli("white-balance", str(shoot / "a.dng"), str(tmp_path / "a.jpg"))
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "a.jpg").read_bytes()[:2] == b"\xff\xd8"            # a JPEG, not a TIFF named .jpg
    r = _cli("white-balance", str(shoot / "a.dng"), str(tmp_path / "b.png"), "--format", "tiff")
    assert r.returncode == 2 and "disagrees" in r.stderr and not (tmp_path / "b.png").exists()
    assert "Traceback" not in r.stderr


def test_force_recomputes_and_a_changed_option_is_noted(shoot, tmp_path):
    out = tmp_path / "out"
    ex = jobs.LocalExecutor(1)
    try:
        opts = jobs.batch_options(format="png")
        rows = cli.run_batch(str(shoot), str(out), opts, executor=ex, stream=io.StringIO())
        assert [r["status"] for r in rows] == ["done"]
        mt = os.stat(out / "a.png").st_mtime_ns
        # the same options: skipped, no note
        rows = cli.run_batch(str(shoot), str(out), opts, executor=ex, stream=io.StringIO())
        assert rows[0]["status"] == "skipped" and "note" not in rows[0]
        # other options: still skipped (resumable) but said
        other = jobs.batch_options(format="png", exposure="1.5")
        rows = cli.run_batch(str(shoot), str(out), other, executor=ex, stream=io.StringIO())
        assert rows[0]["status"] == "skipped" and "exposure" in rows[0]["note"] and "--force" in rows[0]["note"]
        buf = io.StringIO()
        cli._summary(rows, buf)
        assert "notes:" in buf.getvalue() and "exposure: None -> 1.5" in buf.getvalue()
        # --force: computed again with the new options, and stored
        rows = cli.run_batch(str(shoot), str(out), other, executor=ex, stream=io.StringIO(), force=True)
        assert rows[0]["status"] == "done" and os.stat(out / "a.png").st_mtime_ns != mt
        rows = cli.run_batch(str(shoot), str(out), other, executor=ex, stream=io.StringIO())
        assert rows[0]["status"] == "skipped" and "note" not in rows[0]
    finally:
        ex.shutdown()


def test_warnings_reach_the_summary():
    rows = [{"name": "a.dng", "status": "done", "illuminant": {"cct": 5000, "camera_rgb": [0.5, 1, 0.6],
                                                               "warnings": ["3.2 % of the image is saturated"]}}]
    buf = io.StringIO()
    cli._summary(rows, buf)
    assert "warnings:" in buf.getvalue() and "a.dng: 3.2 % of the image is saturated" in buf.getvalue()


def test_version_and_quiet(shoot, tmp_path):
    r = _cli("--version")
    assert r.returncode == 0 and r.stdout.startswith("wandell ")
    r = _cli("batch", str(shoot), str(tmp_path / "q"), "--format", "png", "--workers", "1", "--quiet")
    assert r.returncode == 0, r.stderr
    assert r.stdout == "" and "img/min" not in r.stderr                    # no table, no progress bar
    assert (tmp_path / "q" / "a.png").exists()


def test_help_imports_no_numerical_library():
    """``wandell --help`` builds the parser without numpy, OpenCV, rawpy or
    colour (their import is what costs seconds); measured whole-process
    times are in the README."""
    code = ("import sys\nfrom service import cli\ntry:\n    cli.main(['--help'])\nexcept SystemExit:\n    pass\n"
            "heavy = [m for m in ('numpy', 'cv2', 'rawpy', 'colour', 'scipy') if m in sys.modules]\n"
            "print('HEAVY', heavy)")
    env = dict(os.environ, PYTHONPATH=ROOT)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env, cwd=ROOT)
    assert "HEAVY []" in r.stdout, r.stdout + r.stderr
