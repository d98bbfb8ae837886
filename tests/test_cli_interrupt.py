"""Issue 19, item 1: ``wandell batch`` interrupted by Ctrl-C, once or twice.

A real ``wandell batch`` subprocess on a folder of real-looking DNGs
(testing.dngwriter), in its own process group; SIGINT is sent to the whole
group, as a terminal's Ctrl-C is (the pool workers get it too). It must stop
promptly, keep what finished, print the summary so far and how to resume,
leave no process and no partial file behind, print no traceback, and the
same command run again must finish the rest, skipping what was kept.
"""

from __future__ import annotations

import glob
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from testing.dngwriter import scene_dng

ROOT = Path(__file__).resolve().parents[1]
N_FILES = 10


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    d = tmp_path_factory.mktemp("ctrl-c-shoot")
    for i in range(N_FILES):
        scene_dng(d / f"im{i}.dng", "Nikon 5100 (NPL)", "D4000", 800, 1200, seed=i)
    return d


def _live_in_group(pgid: int) -> list[str]:
    """Processes of the group still alive (zombies, already dead and only
    waiting for a parent to reap them, do not count)."""
    alive = []
    for stat in glob.glob("/proc/[0-9]*/stat"):
        try:
            text = Path(stat).read_text()
        except OSError:
            continue
        fields = text.rsplit(")", 1)[1].split()
        state, group = fields[0], int(fields[2])
        if group == pgid and state != "Z":
            alive.append(text[:80])
    return alive


def _command(folder, out):
    return [sys.executable, "-m", "service.cli", "batch", str(folder), str(out), "--workers", "2",
            "--format", "png"]


@pytest.mark.parametrize("presses", [1, 2])
def test_ctrl_c_stops_promptly_keeps_what_finished_and_says_how_to_resume(folder, tmp_path, presses):
    out = tmp_path / "out"
    proc = subprocess.Popen(_command(folder, out), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        t_end = time.monotonic() + 180
        while not glob.glob(str(out / "*.png")):  # one item finished: others are running or queued
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < t_end, "no output within 180 s"
            time.sleep(0.05)
        for _ in range(presses):
            os.killpg(proc.pid, signal.SIGINT)
            time.sleep(0.05)
        t0 = time.monotonic()
        stdout, stderr = proc.communicate(timeout=30)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 130, (proc.returncode, stdout, stderr)
    assert took < 15, f"took {took:.1f} s to stop"
    assert "Traceback" not in stdout + stderr, stdout + stderr
    # the summary so far, and how to resume
    rows = dict(re.findall(r"^(im\d+\.dng)\s+(\w+)", stdout, re.M))
    assert len(rows) == N_FILES, stdout
    done = {n for n, s in rows.items() if s == "done"}
    assert done and set(rows.values()) <= {"done", "stopped"}, rows
    assert "stopped" in rows.values(), "everything finished before the Ctrl-C: the test proves nothing"
    assert "To resume, run the same command again" in stderr and f"batch {folder} {out}" in stderr, stderr
    # nothing left running, nothing partial, every kept output complete
    t_end = time.monotonic() + 5
    while _live_in_group(proc.pid) and time.monotonic() < t_end:
        time.sleep(0.1)
    assert not _live_in_group(proc.pid), _live_in_group(proc.pid)
    assert not list(out.rglob("*.part")), list(out.rglob("*.part"))
    assert {p.stem + ".dng" for p in out.glob("*.png")} == done
    # the same command again finishes the rest and skips what was kept
    again = subprocess.run(_command(folder, out), cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    rows2 = dict(re.findall(r"^(im\d+\.dng)\s+(\w+)", again.stdout, re.M))
    assert {n for n, s in rows2.items() if s == "skipped"} == done
    assert {n for n, s in rows2.items() if s == "done"} == set(rows) - done
    assert len(list(out.glob("*.png"))) == N_FILES


def test_a_ctrl_c_between_two_items_closes_the_batch_without_a_traceback(tmp_path, monkeypatch):
    """A Ctrl-C that lands in the batch's loop while the generator of finished items waits at its yield
    closed that generator, whose ``except BaseException`` (a lost worker) took the GeneratorExit and
    yielded again: "Exception ignored ... RuntimeError: generator ignored GeneratorExit" with a traceback
    on stderr (seen once in the suite's Ctrl-C test, which depends on where the signal lands). Here the
    interrupt is raised deterministically by the progress line after the first finished item."""
    import gc
    import io

    from service import cli, jobs

    d = tmp_path / "shoot"
    d.mkdir()
    for k in range(3):
        scene_dng(d / f"im{k}.dng", "Nikon 5100 (NPL)", "D65", 64, 96, seed=k)

    class CtrlCOnSecondLine(io.StringIO):
        lines = 0

        def write(self, s):
            self.lines += 1
            if self.lines == 2:           # the first line is the bar before any item; the second after one
                raise KeyboardInterrupt
            return super().write(s)

    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: unraisable.append(u))
    with pytest.raises(cli.BatchInterrupted):
        cli.run_batch(str(d), str(tmp_path / "out"), jobs.batch_options(format="png"), workers=1,
                      stream=CtrlCOnSecondLine())
    gc.collect()
    assert not unraisable, [(u.exc_type, u.exc_value) for u in unraisable]
