"""Round 9c (docs/probe_round9.md, "Round 9c: round 9a's leftovers"): the
faults round 9a noticed and left, each fixed and reproduced through the real
ASGI app (FastAPI's TestClient) as a user meets it."""

from __future__ import annotations

import io
import json
import struct
import zlib

import numpy as np
import pytest

from .conftest import isolated_app_client, mondrian_u16, tiff_bytes


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    yield from isolated_app_client(tmp_path_factory.mktemp("store"), base_url="http://127.0.0.1")


_mondrian, _tiff = mondrian_u16, tiff_bytes


# --- 1. a 16-bit PNG's eXIf orientation --------------------------------------------------------------

_TURN = {6: lambda a: np.rot90(a, 3), 8: lambda a: np.rot90(a, 1)}


def _png16(rgb: np.ndarray, orientation: int | None = None) -> bytes:
    """A 16-bit RGB PNG (OpenCV's encoder) with, if asked, an ``eXIf`` chunk
    before its first IDAT holding an EXIF Orientation (Pillow's EXIF writer;
    the chunk holds the TIFF layout without the ``Exif\\0\\0`` of a JPEG)."""
    import cv2
    from PIL import Image

    ok, enc = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    assert ok
    data = enc.tobytes()
    if orientation is None:
        return data
    exif = Image.Exif()
    exif[274] = orientation
    body = exif.tobytes()
    body = body[6:] if body.startswith(b"Exif\0\0") else body
    chunk = struct.pack(">I", len(body)) + b"eXIf" + body + struct.pack(">I", zlib.crc32(b"eXIf" + body))
    at = data.index(b"IDAT") - 4
    return data[:at] + chunk + data[at:]


@pytest.mark.parametrize("orientation", [6, 8])
def test_a_pngs_exif_orientation_is_applied_as_a_tiffs(client, orientation):
    """A 16-bit PNG whose eXIf chunk says Orientation 6 or 8 (a portrait)
    was analysed and written on its side: OpenCV reads the pixels as stored,
    while a TIFF's Orientation tag is applied since round 9a. It is now
    applied the same way: the answer is the upright file's, pixel for pixel,
    with ``image.width``/``height`` and ``points`` in the displayed frame."""
    import cv2

    img = _mondrian()
    upright = _png16(_TURN[orientation](img).copy())
    stored = _png16(img, orientation)
    answers = []
    for data in (upright, stored):
        r = client.post("/v1/white-balance", files={"file": ("a.png", data)}, data={"format": "png16"})
        assert r.status_code == 200, r.text[:300]
        answers.append(cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED))
    assert answers[1].shape == answers[0].shape == (64, 48, 3)
    np.testing.assert_array_equal(answers[1], answers[0])
    a = client.post("/v1/analyze", files={"file": ("a.png", stored)}).json()
    b = client.post("/v1/analyze", files={"file": ("a.png", upright)}).json()
    assert (a["image"]["width"], a["image"]["height"]) == (b["image"]["width"], b["image"]["height"]) == (48, 64)
    assert a["illuminant"]["camera_rgb"] == b["illuminant"]["camera_rgb"]
    pts = json.dumps([[3, 5], [40, 20]])
    s = [client.post("/v1/surfaces", files={"file": ("a.png", d)}, data={"points": pts}).json()
         for d in (stored, upright)]
    assert [x["reflectance"] for x in s[0]["surfaces"]] == [x["reflectance"] for x in s[1]["surfaces"]]


def test_the_python_loader_says_a_pngs_orientation(tmp_path):
    """``service.loader.load`` of the same PNG says the flip, as for a TIFF
    (``Photo.orientation``, LibRaw's code)."""
    from service.loader import ORIENTATIONS, load

    img = _mondrian()
    path = tmp_path / "portrait.png"
    path.write_bytes(_png16(img, 6))
    photo = load(str(path))
    assert photo.full_shape == (img.shape[1], img.shape[0])
    assert ORIENTATIONS[photo.orientation] == "rotated 90 degrees clockwise"


def test_a_pngs_unreadable_exif_chunk_is_said_and_the_pixels_used_as_stored(client):
    """An eXIf chunk that is not EXIF (its CRC right) does not refuse the
    file: the pixels are used as stored and a warning says why."""
    import cv2

    img = _mondrian()
    data = _png16(img)
    body = b"not a TIFF header"
    chunk = struct.pack(">I", len(body)) + b"eXIf" + body + struct.pack(">I", zlib.crc32(b"eXIf" + body))
    at = data.index(b"IDAT") - 4
    r = client.post("/v1/white-balance", files={"file": ("a.png", data[:at] + chunk + data[at:])},
                    data={"format": "png16", "response": "json"})
    assert r.status_code == 200, r.text[:300]
    assert any("eXIf chunk cannot be read" in w for w in r.json()["warnings"]), r.json()["warnings"]
    r = client.post("/v1/white-balance", files={"file": ("a.png", data[:at] + chunk + data[at:])},
                    data={"format": "png16"})
    assert cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED).shape == img.shape


# --- 4. a three-sample BlackIsZero TIFF --------------------------------------------------------------

def test_a_three_sample_blackiszero_tiff_is_read_as_rgb_with_a_warning(client):
    """A TIFF whose PhotometricInterpretation is BlackIsZero (grey) with
    three samples a pixel was read as camera RGB without a word. It is
    still read (scientific files are RGB in all but the tag), and every
    answer's warnings now say what the tag said and how it was read; an RGB
    TIFF of the same pixels gets no such warning and the same light."""
    img = _mondrian()
    grey = _tiff(img, photometric="minisblack", planarconfig="contig")
    rgb = _tiff(img, photometric="rgb")
    a = client.post("/v1/analyze", files={"file": ("a.tif", grey)})
    b = client.post("/v1/analyze", files={"file": ("a.tif", rgb)})
    assert a.status_code == b.status_code == 200, a.text[:300]
    said = [w for w in a.json()["warnings"] if "BlackIsZero" in w]
    assert said and "grey" in said[0] and "three channels of camera RGB" in said[0], a.json()["warnings"]
    assert not [w for w in b.json()["warnings"] if "BlackIsZero" in w]
    assert a.json()["illuminant"]["camera_rgb"] == b.json()["illuminant"]["camera_rgb"]
    r = client.post("/v1/white-balance", files={"file": ("a.tif", grey)}, data={"response": "json"})
    assert r.status_code == 200 and any("BlackIsZero" in w for w in r.json()["warnings"]), r.text[:300]


# --- 2. counts.pending: one meaning on both batch endpoints ------------------------------------------

def _dng(seed=1) -> bytes:
    from testing.dngwriter import scene_dng

    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D65", 48, 64, seed=seed)
    return buf.getvalue()


def test_both_batch_endpoints_count_pending_alike_with_an_item_running(app_with, tmp_path):
    """``counts.pending`` was "pending or running" in ``GET /v1/batches/{id}``
    and "pending" alone in ``GET /v1/batches``, so the same batch had two
    pending counts, and the progress document's disagreed with its own
    items' statuses. Both now count the items of each status (``running``
    apart): pending + running + done + failed + cancelled = total. The batch
    is frozen with one item running (its runner stopped, as a kill -9 leaves
    a batch until the restart resumes it)."""
    from service.routers import batches
    from service.schemas.options import BatchOptions

    client, _ = app_with()
    runner = batches.get_runner()
    runner.stop()                                  # nothing moves while the counts are read
    src = tmp_path / "a.dng"
    src.write_bytes(_dng())
    bid = runner.store.new_batch_id()
    runner.store.create_batch(bid, BatchOptions(), [(f"im{i}.dng", str(src)) for i in range(3)])
    runner.store.start_batch(bid)
    assert len(runner.store.claim(bid, 1)) == 1    # item 0 running, items 1 and 2 pending

    doc = client.get(f"/v1/batches/{bid}").json()
    listed = next(b for b in client.get("/v1/batches").json()["batches"] if b["id"] == bid)
    statuses = [it["status"] for it in doc["items"]]
    assert statuses.count("running") == 1 and statuses.count("pending") == 2, statuses
    assert doc["counts"]["pending"] == listed["counts"]["pending"] == 2, (doc["counts"], listed["counts"])
    assert doc["counts"]["running"] == listed["counts"]["running"] == 1
    assert doc["counts"] == listed["counts"]
    c = doc["counts"]
    assert c["done"] + c["failed"] + c["pending"] + c["running"] + c["cancelled"] == c["total"] == 3
    assert doc["settled"] is False and doc["status"] == "running"

    # the page (app.js under node, round 9's stand-in for the page) says what each count is
    import shutil
    import subprocess
    from pathlib import Path

    from .test_probe_round9 import _PAGE_HARNESS

    node = shutil.which("node") or shutil.which("nodejs")
    if node is None:
        return
    harness = tmp_path / "harness.js"
    harness.write_text(_PAGE_HARNESS)
    app_js = Path(__file__).resolve().parents[1] / "service" / "static" / "app.js"
    out = subprocess.run([node, str(harness), str(app_js), json.dumps([{"status": 200, "body": doc}])],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    said = json.loads(out.stdout)[0]["status"]
    assert "0 done, 0 failed, 2 pending, 1 running of 3." in said, said


# --- 3. a batch past its retention says so ------------------------------------------------------------

def _settled(client, bid, timeout=120):
    import time

    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        r = client.get(f"/v1/batches/{bid}")
        if r.status_code != 200 or r.json()["settled"]:
            return r
        time.sleep(0.2)
    raise AssertionError(f"batch {bid} not settled in {timeout} s")


def _gone(client, bid, timeout=60):
    import time

    t_end = time.monotonic() + timeout
    while client.get(f"/v1/batches/{bid}").status_code != 404:
        assert time.monotonic() < t_end, f"batch {bid} not removed in {timeout} s"
        time.sleep(0.2)


def test_a_batch_past_its_retention_says_it_was_removed_when_and_by_which_setting(app_with, monkeypatch):
    """A batch past ``WANDELL_BATCH_RESULT_RETENTION`` was a plain 404 "no
    batch 'ID'" on every URL, the same as a mistyped id: the store kept
    nothing of it. It keeps a tombstone now, so its progress, item
    downloads (by index, by name, either), zip, cancel and DELETE answer
    404 (as before: clients and the page take a 404 as final) with
    ``batch_expired``, a detail naming the setting, and ``removed`` /
    ``retention_s`` / ``setting``; an unknown id is still ``not_found``. The
    tombstones are bounded: past ``TOMBSTONES_KEPT`` the oldest go."""
    import time

    from service.batch import store as store_mod

    monkeypatch.setattr(store_mod, "TOMBSTONES_KEPT", 2, raising=False)   # (absent before the fix)
    client, _ = app_with(batch_result_retention=0.5)
    t0 = time.time()
    ids = []
    for seed in (1, 2, 3):       # one after the other: the oldest tombstone is the first batch's
        r = client.post("/v1/batches", files=[("files", ("a.dng", _dng(seed)))], data={"format": "jpeg"})
        assert r.status_code == 202, r.text[:300]
        ids.append(r.json()["id"])
        assert _settled(client, ids[-1]).status_code == 200
        _gone(client, ids[-1])
    bid = ids[-1]
    for method, url in [("GET", f"/v1/batches/{bid}"), ("GET", f"/v1/batches/{bid}/items/by-index/0"),
                        ("GET", f"/v1/batches/{bid}/items/by-name/a.dng"), ("GET", f"/v1/batches/{bid}/items/0"),
                        ("GET", f"/v1/batches/{bid}/zip"), ("POST", f"/v1/batches/{bid}/cancel"),
                        ("DELETE", f"/v1/batches/{bid}?remove=true")]:
        r = client.request(method, url)
        assert r.status_code == 404, (method, url, r.status_code, r.text[:300])
        body = r.json()
        assert body["error"] == "batch_expired", (url, body)
        assert "WANDELL_BATCH_RESULT_RETENTION" in body["detail"] and "removed" in body["detail"], body
        assert body["setting"] == "WANDELL_BATCH_RESULT_RETENTION" and body["retention_s"] == 0.5, body
        assert t0 <= body["removed"] <= time.time(), body
    assert client.get(f"/v1/batches/{ids[1]}").json()["error"] == "batch_expired"
    # bounded: the first batch's tombstone made room for the last one's
    first = client.get(f"/v1/batches/{ids[0]}")
    assert first.status_code == 404 and first.json() == {"error": "not_found", "detail": f"no batch {ids[0]!r}"}
    r = client.get("/v1/batches/0123456789abcdef")
    assert r.status_code == 404 and r.json()["error"] == "not_found"
