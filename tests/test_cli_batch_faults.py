"""Issue 28, part A, what the new user met with ``wandell batch``: a shared
light over images that were not under one light says so (CLI and the
batch's JSON), and Ctrl-C during ``--xmp`` leaves every finished image with
its sidecar and no ``.lock`` file behind. Real ``python -m service.cli``
subprocesses on DNGs written by testing.dngwriter; SIGINT to the whole
process group, as a terminal's Ctrl-C."""

from __future__ import annotations

import glob
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from service import jobs
from testing.dngwriter import scene_dng

ROOT = Path(__file__).resolve().parents[1]


def test_shared_light_over_two_lights_warns_in_the_cli_and_the_batch_json(tmp_path):
    d = tmp_path / "shoot"
    d.mkdir()
    scene_dng(d / "day.dng", "Nikon 5100 (NPL)", "D65", 200, 300, seed=1)
    scene_dng(d / "tungsten.dng", "Nikon 5100 (NPL)", "A", 200, 300, seed=2)
    r = subprocess.run([sys.executable, "-m", "service.cli", "batch", str(d), str(tmp_path / "out"), "--workers",
                        "1", "--format", "png", "--lighting", "shared"], cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert "warning: shared light: the images' own lights are up to" in r.stderr, r.stderr
    assert "may not all be under one light" in r.stderr and "confidence" in r.stderr, r.stderr
    # the same words in the batch's JSON (what the page shows under its progress bar)
    store = jobs.JobStore(str(tmp_path / "data"))
    bid = store.new_batch_id()
    store.create_batch(bid, jobs.batch_options(lighting="shared"), [("a.dng", str(d / "day.dng"))])
    light = {"warnings": ["the images' own lights are up to 13.2 degrees from the shared light (RMS 9.0): "
                          "they may not all be under one light"], "confidence": 0.08, "low_confidence": True}
    store.set_light(bid, light)
    doc = store.progress(bid)
    assert doc["warnings"] == [f"shared light: {light['warnings'][0]} (shared light confidence 0.08)"]


def test_ctrl_c_during_xmp_batch_leaves_sidecars_of_finished_images_and_no_locks(tmp_path):
    d = tmp_path / "shoot"
    d.mkdir()
    for i in range(8):
        scene_dng(d / f"im{i}.dng", "Nikon 5100 (NPL)", "D4000", 800, 1200, seed=i)
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "batch", str(d), str(out), "--workers", "2",
                             "--format", "png", "--xmp"], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        t_end = time.monotonic() + 180
        while not glob.glob(str(out / "*.png")):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < t_end, "no output within 180 s"
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=300)   # sidecars of finished images are made before it exits
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 130, (stdout, stderr)
    assert "Traceback" not in stdout + stderr, stderr
    done = {p.stem for p in out.glob("*.png")}
    assert done and len(done) < 8, "every image finished before the Ctrl-C: the test proves nothing"
    sidecars = {p.stem for p in d.glob("*.xmp")}
    assert done <= sidecars, f"finished without a sidecar: {done - sidecars}"
    assert not list(out.rglob("*.lock")), list(out.rglob("*.lock"))
    assert not list(out.rglob("*.part")), list(out.rglob("*.part"))


SPY = """
import sys
from service import cli
seen = []
make = cli.jobs.make_executor
def spy(*a, **k):
    seen.append(type(sys.modules["service.sidecars"]).__name__)
    return make(*a, **k)
cli.jobs.make_executor = spy
code = cli.main(["batch", sys.argv[1], sys.argv[2], "--workers", "1", "--xmp", "-q"])
print("SEEN", seen, code)
"""


def test_an_xmp_batch_loads_the_sidecar_code_before_its_pool_starts(tmp_path):
    """Found by a full test run under load (the test above failed once with
    "module 'service.sidecars' has no attribute 'sidecar_path'"): the CLI
    imports the sidecar code lazily, its first use was when the first image
    finished, and the Ctrl-C that stopped the batch landed in that import,
    leaving the module half-made for the sidecars made after the stop. A
    batch with --xmp now loads it before the pool starts (and the Ctrl-C
    handler is set): checked when the pool is made, in a fresh process."""
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    scene_dng(src / "a.dng", "Nikon 5100 (NPL)", "D65", 64, 96, seed=1)
    p = subprocess.run([sys.executable, "-c", SPY, str(src), str(out)], cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert "SEEN ['module'] 0" in p.stdout, (p.stdout, p.stderr)     # loaded (not importlib's _LazyModule), done
    assert (src / "a.xmp").is_file() or glob.glob(str(src / "a*.xmp")), os.listdir(src)


def test_an_image_that_kills_its_worker_fails_alone_and_the_others_are_done(tmp_path):
    """One RAW whose processing kills its worker process (a decoder crash,
    the OOM killer; :func:`testing.faults.process_or_die`) broke the local
    pool and failed every image in flight with it, and a rerun met it again.
    Now the images in flight run again one at a time, each alone, and only
    the one whose worker dies alone fails, as ``worker_killed``; each other
    image is written once and its row says done."""
    from service import cli
    from testing.faults import process_or_die

    d = tmp_path / "shoot"
    d.mkdir()
    for k, name in enumerate(("a", "b", "c")):
        scene_dng(d / f"{name}.dng", "Nikon 5100 (NPL)", "D65", 120, 160, seed=k)
    out = tmp_path / "out"
    rows = cli.run_batch(str(d), str(out), jobs.batch_options(format="png"), workers=2, quiet=True,
                         item_fn=process_or_die({"b.dng"}, delay_s=0.5))
    by = {r["name"]: r for r in rows}
    assert by["b.dng"]["status"] == "failed", by["b.dng"]
    assert by["b.dng"]["error"].startswith("worker_killed:"), by["b.dng"]["error"]
    assert "3 times" in by["b.dng"]["error"]
    for n in ("a.dng", "c.dng"):
        assert by[n]["status"] == "done", by[n]
        assert (out / n.replace(".dng", ".png")).is_file()
    assert not (out / "b.png").exists()
    assert not glob.glob(str(out / "*.lock")) and not glob.glob(str(out / "*.part"))


def test_shared_light_with_an_image_that_kills_its_worker_is_made_from_the_others(tmp_path):
    """``--lighting shared``: the estimation of one image kills its worker
    (:func:`testing.faults.sample_or_die`). The broken pool raised out of the
    whole command. Now the images in flight are estimated again, each alone;
    the culprit fails as ``worker_killed``, the light is made from the
    others, and their images are corrected with it on a new pool."""
    from service import cli
    from testing.faults import sample_or_die

    d = tmp_path / "shoot"
    d.mkdir()
    for k, name in enumerate(("a", "b", "c")):
        scene_dng(d / f"{name}.dng", "Nikon 5100 (NPL)", "D65", 120, 160, seed=k)
    out = tmp_path / "out"
    info: dict = {}
    rows = cli.run_batch(str(d), str(out), jobs.batch_options(format="png", lighting="shared"), workers=2,
                         quiet=True, info=info, sample_fn=sample_or_die({"b.dng"}, delay_s=0.2))
    by = {r["name"]: r for r in rows}
    assert by["b.dng"]["status"] == "failed" and by["b.dng"]["error"].startswith("worker_killed:"), by["b.dng"]
    assert info["shared_light"] is not None
    for n in ("a.dng", "c.dng"):
        assert by[n]["status"] == "done", by[n]
        assert (out / n.replace(".dng", ".png")).is_file()
