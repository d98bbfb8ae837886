"""Round 6 of probing the newest features as a new user and as a hostile
client (docs/probe_round6.md): each test is the minimal reproduction of one
fault found, through the command line as users run it (``python -m
service.cli``) or the real ASGI stack (FastAPI's TestClient), and holds once
the fault is fixed."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from .conftest import isolated_app_client, scene_dng_bytes

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def dng() -> bytes:
    return scene_dng_bytes(64, 96)


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    yield from isolated_app_client(tmp_path_factory.mktemp("store"), base_url="http://127.0.0.1")


def _cli(*args: str):
    env = dict(os.environ, PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True,
                          timeout=300, env=env, cwd=ROOT)


def _strict(text: str):
    def bad(name):
        raise ValueError(f"non-finite JSON constant {name}")
    return json.loads(text, parse_constant=bad)


# --- 1. wandell batch --xmp, run again ---------------------------------------------------

def test_a_rerun_of_batch_xmp_does_not_take_its_own_dng_copies_as_photographs(tmp_path, dng):
    """``wandell batch --xmp IN OUT`` writes, for each DNG, a copy with the
    white balance inside beside it (``IMG.wandell.dng``). Run again (a
    rerun, as after Ctrl-C or to add photographs), the copies were new
    inputs: 2 more outputs (``OUT/a.wandell.png``), 2 copies of the copies
    (``IN/a.wandell.wandell.dng``) and their sidecars, one generation more at
    each run. Now the copies are left out and the summary says so; the
    rerun skips the finished photographs and writes nothing new."""
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    for name in ("a.dng", "b.dng"):
        (src / name).write_bytes(dng)
    r = _cli("batch", "--xmp", "--format", "png", "--workers", "1", str(src), str(out))
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert sorted(p.name for p in src.iterdir()) == ["a.dng", "a.wandell.dng", "a.xmp", "b.dng", "b.wandell.dng",
                                                     "b.xmp"]
    first = sorted(p.name for p in out.iterdir())
    r = _cli("batch", "--xmp", "--format", "png", "--workers", "1", str(src), str(out))
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert sorted(p.name for p in src.iterdir()) == ["a.dng", "a.wandell.dng", "a.xmp", "b.dng", "b.wandell.dng",
                                                     "b.xmp"], "copies of the copies were written"
    assert sorted(p.name for p in out.iterdir()) == first, "the copies were processed as photographs"
    assert "0 done, 2 skipped" in r.stdout, r.stdout
    assert "2 files written by --xmp" in r.stdout and "a.wandell.dng" in r.stdout, r.stdout
    # a .wandell.dng whose original is not there is a photograph like any other
    (src / "a.dng").rename(tmp_path / "a.dng")
    (src / "a.xmp").unlink()
    r = _cli("batch", "--format", "png", "--workers", "1", str(src), str(out))
    assert r.returncode == 0 and "a.wandell.png" in {p.name for p in out.iterdir()}, (r.stdout, r.stderr)
