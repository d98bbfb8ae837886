"""``/v1/batches`` through the ASGI app, and a real uvicorn server killed
with SIGKILL mid-batch then restarted (issue 6). Real DNGs from
testing.dngwriter with known truth."""

from __future__ import annotations

import io
import json
import os
import signal
import socket
import subprocess
import sys
import time
import zipfile

import cv2
import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from recovery import angular_error
from testing.dngwriter import scene_dng
from service.settings import get_settings

from .test_jobs import in_model_surfaces


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    """Settings for this module: own data dir, a batch root, 2 workers."""
    base = tmp_path_factory.mktemp("batches")
    root = base / "root"
    (root / "shoot").mkdir(parents=True)
    truths = []
    for i in range(3):
        truths.append(scene_dng(root / "shoot" / f"im{i}.dng", "Nikon 5100 (NPL)", "D4000", 160, 240, seed=i,
                                grid=(4, 6), surfaces=in_model_surfaces(0.03 * (i - 1)),
                                noise_multiplicative=0, noise_additive=0))
    (root / "shoot" / "broken.dng").write_bytes(b"II*\x00" + b"\x13" * 500)
    old = dict(os.environ)
    os.environ.update(WANDELL_DATA_DIR=str(base / "data"), WANDELL_BATCH_ROOT=str(root),
                      WANDELL_BATCH_WORKERS="2", WANDELL_MAX_BATCH_ITEMS="20",
                      WANDELL_MAX_UPLOAD_BYTES="100000")  # a 160x240 DNG is about 77 kB
    get_settings.cache_clear()
    yield {"base": base, "root": root, "truths": truths}
    os.environ.clear()
    os.environ.update(old)
    get_settings.cache_clear()


@pytest.fixture(scope="module")
def client(env):
    from service.app import app

    with TestClient(app) as c:  # the lifespan starts (and stops) the runner
        yield c


def _files(root, names):
    return [("files", (n, (root / "shoot" / n).read_bytes(), "application/octet-stream")) for n in names]


def _wait(client, bid, timeout=180):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        doc = client.get(f"/v1/batches/{bid}").json()
        if doc["status"] not in ("queued", "running"):
            return doc
        time.sleep(0.2)
    raise AssertionError(f"batch {bid} not finished in {timeout} s: {doc}")


OPTS = {"format": "png", "method": "maloney-wandell", "surface_model": "fourier"}


def test_upload_batch_end_to_end_with_a_corrupt_file(client, env):
    root, truths = env["root"], env["truths"]
    names = ["im0.dng", "broken.dng", "im1.dng", "im2.dng"]
    r = client.post("/v1/batches", files=_files(root, names), data=OPTS)
    assert r.status_code == 202, r.text
    bid = r.json()["id"]
    doc = _wait(client, bid)
    assert doc["status"] == "done"
    assert doc["counts"]["done"] == 3 and doc["counts"]["failed"] == 1 and doc["counts"]["pending"] == 0
    assert doc["rate_per_minute"] > 0 and doc["time_left_s"] == 0
    by = {it["name"]: it for it in doc["items"]}
    assert by["broken.dng"]["status"] == "failed" and by["broken.dng"]["error"].startswith("corrupt_file")
    assert "'broken.dng'" in by["broken.dng"]["error"]  # the user's name, not the stored file's
    for i in range(3):
        it = by[f"im{i}.dng"]
        # in-model surfaces and daylight, no noise: within 0.25 degree (see test_api)
        assert angular_error(it["illuminant"]["camera_rgb"], truths[i].light_rgb) < 0.25
    # one by name, one by index; both the full-resolution corrected PNG
    a = client.get(f"/v1/batches/{bid}/items/im0.dng")
    b = client.get(f"/v1/batches/{bid}/items/0")
    assert a.status_code == b.status_code == 200 and a.content == b.content
    assert a.headers["content-type"] == "image/png"
    img = cv2.imdecode(np.frombuffer(a.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape == (160, 240, 3)
    bad = client.get(f"/v1/batches/{bid}/items/broken.dng")
    assert bad.status_code == 409 and "corrupt_file" in bad.json()["detail"]
    # a failed item's result will never come: its own code, not not_ready (which says "wait"; probe round 7)
    assert bad.json()["error"] == "item_failed" and "new batch" in bad.json()["detail"], bad.text
    assert client.get(f"/v1/batches/{bid}/items/nope.dng").status_code == 404
    z = client.get(f"/v1/batches/{bid}/zip")
    assert z.status_code == 200 and z.headers["content-type"] == "application/zip"
    with zipfile.ZipFile(io.BytesIO(z.content)) as zf:
        assert sorted(zf.namelist()) == ["FAILURES.txt", "batch.json", "im0.png", "im1.png", "im2.png", "manifest.json"]
        assert zf.read("im0.png") == a.content
        assert zf.testzip() is None
        # the zip says what is missing from it and why (issue 19, item 11)
        failures = zf.read("FAILURES.txt").decode()
        assert "1 of the 4 items" in failures and "broken.dng\tfailed\tcorrupt_file" in failures
        manifest = json.loads(zf.read("manifest.json"))
        assert manifest["counts"]["done"] == 3 and manifest["counts"]["failed"] == 1
        by_m = {it["name"]: it for it in manifest["items"]}
        assert by_m["im0.dng"]["output"] == "im0.png" and by_m["broken.dng"]["output"] is None
        assert by_m["broken.dng"]["error"].startswith("corrupt_file")


def test_folder_batch_shared_light_is_one_light_close_to_the_truth(client, env):
    """All images under one daylight with in-model surfaces: pooling keeps
    eq. 30 exact, so the shared light is within the single-image bound."""
    r = client.post("/v1/batches", data={**OPTS, "folder": "shoot", "lighting": "shared"})
    assert r.status_code == 202, r.text
    doc = _wait(client, r.json()["id"])
    assert doc["status"] == "done" and doc["lighting"] == "shared"
    assert (doc["counts"]["done"], doc["counts"]["failed"]) == (3, 1)
    rgbs = np.array([it["illuminant"]["camera_rgb"] for it in doc["items"] if it["status"] == "done"])
    assert np.ptp(rgbs, axis=0).max() == 0  # one light for every image
    assert doc["shared_light"]["images"] == 3
    assert angular_error(rgbs[0], env["truths"][0].light_rgb) < 0.25


def test_folder_outside_root_and_bad_requests_are_4xx(client, env):
    for folder in ("../", "shoot/../../", "/etc", str(env["base"])):
        r = client.post("/v1/batches", data={"folder": folder})
        assert r.status_code == 403 and r.json()["error"] == "path_outside_root", (folder, r.text)
    r = client.post("/v1/batches", data={"folder": "missing"})
    assert r.status_code == 404
    r = client.post("/v1/batches", data={"format": "png"})
    assert r.status_code == 422 and "files" in r.json()["detail"]
    r = client.post("/v1/batches", data={"folder": "shoot", "lighting": "global"})
    assert r.status_code == 422 and "lighting" in r.json()["detail"]
    r = client.post("/v1/batches", files=_files(env["root"], ["im0.dng"] * 21), data=OPTS)
    assert r.status_code == 413 and r.json()["error"] == "too_many_items"
    for method, path in (("get", "/v1/batches/nope"), ("get", "/v1/batches/nope/zip"),
                         ("get", "/v1/batches/nope/items/0"), ("delete", "/v1/batches/nope")):
        r = client.request(method, path)
        assert r.status_code == 404 and r.json()["error"] == "not_found"


def test_folder_mode_without_a_root_is_refused(client, env, monkeypatch):
    monkeypatch.setenv("WANDELL_BATCH_ROOT", "")
    get_settings.cache_clear()
    try:
        r = client.post("/v1/batches", data={"folder": "shoot"})
    finally:
        monkeypatch.undo()
        get_settings.cache_clear()
    assert r.status_code == 403 and r.json()["error"] == "folder_mode_disabled"
    assert "WANDELL_BATCH_ROOT" in r.json()["detail"]


def test_upload_limit_is_per_file_for_batches(client, env):
    big = [("files", ("big.dng", b"II*\x00" + b"\x00" * 150_000, "application/octet-stream"))]
    r = client.post("/v1/batches", files=_files(env["root"], ["im0.dng"]) + big, data=OPTS)
    assert r.status_code == 413 and "big.dng" in r.json()["detail"]


def test_cancel_stops_pending_items(client, env):
    # 16 files of ~77 kB: more than the 100 kB per-file limit plus 1 MB of
    # framing in all, accepted because the limit is per file for batches
    r = client.post("/v1/batches", files=_files(env["root"], ["im0.dng"] * 16), data=OPTS)
    assert r.status_code == 202, r.text
    bid = r.json()["id"]
    d = client.delete(f"/v1/batches/{bid}")
    assert d.status_code == 200 and d.json()["status"] == "cancelled"
    time.sleep(1.0)
    doc = _wait(client, bid)
    c = doc["counts"]
    # at most one in flight per worker plus one queued per worker (2 x 2)
    # could have started before the cancel; the rest never run
    assert doc["status"] == "cancelled" and c["cancelled"] >= 12 and c["done"] + c["cancelled"] + c["failed"] == 16
    t_end = time.monotonic() + 60
    while doc["counts"]["running"] and time.monotonic() < t_end:  # started items finish and are kept
        time.sleep(0.2)
        doc = client.get(f"/v1/batches/{bid}").json()
    assert doc["counts"]["running"] == 0 and doc["counts"]["pending"] == 0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _serve(env_vars: dict, port: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "uvicorn", "service.app:app", "--host", "127.0.0.1",
                             "--port", str(port), "--log-level", "warning"], env=env_vars,
                            start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _ready(base: str, proc, timeout=120) -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        assert proc.poll() is None, "server exited"
        try:
            if httpx.get(base + "/health", timeout=2).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise AssertionError("server did not start")


def _group_members(pgid: int) -> list[int]:
    """Live (non-zombie) processes of a process group."""
    out = []
    for p in os.listdir("/proc"):
        if p.isdigit():
            try:
                with open(f"/proc/{p}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[2]) == pgid and fields[0] != "Z":
                out.append(int(p))
    return out


def test_kill_9_mid_batch_then_restart_completes_every_item_once(env, tmp_path):
    """A real uvicorn server with one worker is SIGKILLed with items done and
    items pending; a new server on the same data dir resumes. Every item
    ends done, and the batch's write log (one line per rename into place)
    names every output exactly once: nothing lost, nothing written twice,
    even though the killed server's pool worker may still finish its item."""
    truth_dir = env["root"] / "shoot"
    vars_ = {**os.environ, "WANDELL_DATA_DIR": str(tmp_path / "data"), "WANDELL_BATCH_WORKERS": "1",
             "WANDELL_BATCH_ROOT": ""}
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    n = 12
    first = _serve(vars_, port)
    second = None
    try:
        _ready(base, first)
        files = [("files", (f"shot{i:02d}.dng", (truth_dir / f"im{i % 3}.dng").read_bytes(), "image/x-adobe-dng"))
                 for i in range(n)]
        r = httpx.post(base + "/v1/batches", files=files, data={"format": "tiff"}, timeout=60)
        assert r.status_code == 202, r.text
        bid = r.json()["id"]
        t_end = time.monotonic() + 180
        while time.monotonic() < t_end:
            doc = httpx.get(f"{base}/v1/batches/{bid}", timeout=10).json()
            if doc["counts"]["done"] >= 2:
                break
            time.sleep(0.05)
        assert doc["counts"]["done"] < n, "the batch finished before the kill; make it bigger"
        os.kill(first.pid, signal.SIGKILL)  # the server only: its pool worker is orphaned
        first.wait()
        second = _serve(vars_, port)
        _ready(base, second)
        t_end = time.monotonic() + 240
        while time.monotonic() < t_end:
            doc = httpx.get(f"{base}/v1/batches/{bid}", timeout=10).json()
            if doc["status"] != "running":
                break
            time.sleep(0.2)
        assert doc["status"] == "done" and doc["counts"]["done"] == n, doc["counts"]
        log = tmp_path / "data" / "batches" / bid / "writes.log"
        written = [json.loads(line)["name"] for line in log.read_text().splitlines()]
        assert sorted(written) == sorted(f"shot{i:02d}.dng" for i in range(n))  # each exactly once
        out = tmp_path / "data" / "batches" / bid / "out"
        assert sorted(p for p in os.listdir(out) if not p.startswith(".")) == [f"shot{i:02d}.tif" for i in range(n)]
        z = httpx.get(f"{base}/v1/batches/{bid}/zip", timeout=60)
        with zipfile.ZipFile(io.BytesIO(z.content)) as zf:
            assert sorted(zf.namelist()) == ["batch.json"] + [f"shot{i:02d}.tif" for i in range(n)]
        # the killed server's pool worker noticed its parent was gone and exited
        t_end = time.monotonic() + 10
        while _group_members(first.pid) and time.monotonic() < t_end:
            time.sleep(0.2)
        assert _group_members(first.pid) == []
    finally:
        for p in (first, second):
            if p is not None:
                try:
                    os.killpg(p.pid, signal.SIGKILL)  # the server and any pool worker it started
                except ProcessLookupError:
                    pass
                p.wait()


def test_batch_items_carry_the_learnt_estimates_confidence_and_flag(client, env):
    """Issue 12: batches flag low-confidence images. With the default
    estimator every item reports its confidence (a probability) and
    ``low_confidence`` exactly when it is under the documented threshold,
    with the estimate's warning saying so."""
    from recovery.api import LOW_CONFIDENCE
    from recovery.confidence import load_flag_model

    root = env["root"]
    r = client.post("/v1/batches", files=_files(root, ["im0.dng", "im1.dng"]), data={"format": "png"})
    assert r.status_code == 202, r.text
    doc = _wait(client, r.json()["id"])
    assert doc["counts"]["done"] == 2
    for it in doc["items"]:
        ill = it["illuminant"]
        # auto: the learnt estimator, or the light posterior for a scene of uniform patches (issue 16)
        assert ill["method"] in ("learned", "bayes") and 0.0 <= ill["confidence"] <= 1.0
        # the learnt estimator's threshold is its confidence law's (issue 27), the posterior's LOW_CONFIDENCE
        threshold = load_flag_model().threshold if ill["method"] == "learned" else LOW_CONFIDENCE
        assert ill["low_confidence"] == (ill["confidence"] < threshold)
        assert any(w.startswith("low confidence") for w in ill["warnings"]) == ill["low_confidence"]
