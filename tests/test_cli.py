"""The ``wandell`` CLI (issue 6): batch (resumable, exit codes, summary),
analyze, white-balance. Real DNGs from testing.dngwriter."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from recovery import angular_error
from service import cli, jobs
from testing.dngwriter import scene_dng

from .test_jobs import in_model_surfaces

OPTS = ["--format", "png", "--method", "maloney-wandell", "--surface-model", "fourier"]


@pytest.fixture(scope="module")
def shoot(tmp_path_factory):
    d = tmp_path_factory.mktemp("shoot")
    truths = [scene_dng(d / f"im{i}.dng", "Nikon 5100 (NPL)", "D4000", 160, 240, seed=i, grid=(4, 6),
                        surfaces=in_model_surfaces(0.03 * (i - 1)), noise_multiplicative=0, noise_additive=0)
              for i in range(2)]
    return d, truths


@pytest.fixture(scope="module")
def pool():
    """One local pool for the in-process runs (spawn start-up once)."""
    ex = jobs.LocalExecutor(2)
    yield ex
    ex.shutdown()


def test_batch_twice_second_run_skips_all(shoot, tmp_path, pool, capsys):
    d, truths = shoot
    out = tmp_path / "out"
    opts = jobs.batch_options(format="png", method="maloney-wandell", surface_model="fourier")
    rows = cli.run_batch(str(d), str(out), opts, executor=pool)
    assert [r["status"] for r in rows] == ["done", "done"]
    for r, t in zip(rows, truths):
        assert angular_error(r["illuminant"]["camera_rgb"], t.light_rgb) < 0.25  # in-model (test_jobs)
    mt = {p: os.stat(out / p).st_mtime_ns for p in ("im0.png", "im1.png")}
    assert cv2.imread(str(out / "im0.png")).shape == (160, 240, 3)
    # a partial file left by a killed run is never a result: removed, not skipped
    (out / ".im1.png.abcd1234.part").write_bytes(b"half")  # tempfile.mkstemp's pattern
    rows2 = cli.run_batch(str(d), str(out), opts, executor=pool)
    assert [r["status"] for r in rows2] == ["skipped", "skipped"]
    assert rows2[0]["illuminant"]["camera_rgb"] == rows[0]["illuminant"]["camera_rgb"]
    assert {p: os.stat(out / p).st_mtime_ns for p in mt} == mt
    assert not (out / ".im1.png.abcd1234.part").exists()
    err = capsys.readouterr().err
    assert "2/2" in err and "skipped 2" in err  # the progress bar


def test_batch_shared_light_is_reused_on_resume(shoot, tmp_path, pool):
    d, truths = shoot
    out = tmp_path / "out"
    opts = jobs.batch_options(format="png", method="maloney-wandell", surface_model="fourier", lighting="shared")
    rows = cli.run_batch(str(d), str(out), opts, executor=pool)
    assert [r["status"] for r in rows] == ["done", "done"]
    assert rows[0]["illuminant"]["camera_rgb"] == rows[1]["illuminant"]["camera_rgb"]
    # pooled in-model data: the single-image bound holds (test_jobs)
    assert angular_error(rows[0]["illuminant"]["camera_rgb"], truths[0].light_rgb) < 0.25
    os.unlink(out / "im1.png")  # lost one output: redone with the saved shared light
    rows2 = cli.run_batch(str(d), str(out), opts, executor=pool)
    assert [r["status"] for r in rows2] == ["skipped", "done"]
    assert rows2[1]["illuminant"]["camera_rgb"] == rows[1]["illuminant"]["camera_rgb"]


def _cli(*args, **kw):
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True,
                          timeout=300, **kw)


def test_cli_exit_codes_and_summary(shoot, tmp_path):
    """One process run: 0 when all succeed, 1 when something failed (and
    again 1 on the rerun, which skips the finished ones), 2 for bad options."""
    d, _ = shoot
    src = tmp_path / "in"
    src.mkdir()
    (src / "good.dng").write_bytes((d / "im0.dng").read_bytes())
    out = tmp_path / "out"
    r = _cli("batch", str(src), str(out), "--workers", "1", *OPTS)
    assert r.returncode == 0, r.stderr
    assert "good.dng" in r.stdout and "1 done, 0 skipped" in r.stdout
    (src / "bad.dng").write_bytes(b"II*\x00" + b"\x11" * 300)
    r = _cli("batch", str(src), str(out), "--workers", "1", *OPTS)
    assert r.returncode == 1
    assert "0 done, 1 skipped (already finished), 1 failed" in r.stdout and "corrupt_file" in r.stdout
    r = _cli("batch", str(src), str(out), "--lighting", "global")
    assert r.returncode == 2 and "lighting" in r.stderr
    r = _cli("batch", str(tmp_path / "nowhere"), str(out))
    assert r.returncode == 2 and "does not exist" in r.stderr


def test_analyze_and_white_balance_single_files(shoot, tmp_path):
    d, truths = shoot
    r = _cli("analyze", str(d / "im1.dng"), "--method", "maloney-wandell", "--surface-model", "fourier")
    assert r.returncode == 0, r.stderr
    body = json.loads(r.stdout)
    assert angular_error(body["illuminant"]["camera_rgb"], truths[1].light_rgb) < 0.25
    out = tmp_path / "one.tif"
    r = _cli("white-balance", str(d / "im1.dng"), str(out), "--format", "tiff")
    assert r.returncode == 0, r.stderr
    import tifffile

    img = tifffile.imread(out)
    assert img.shape == (160, 240, 3) and img.dtype == np.uint16
    assert not (tmp_path / ".wandell").exists()  # single files: no sidecar
    r = _cli("white-balance", str(tmp_path / "missing.dng"), str(out))
    assert r.returncode == 2 and "file_not_found" in r.stderr  # a usage error, in words (issue 19, item 9)
