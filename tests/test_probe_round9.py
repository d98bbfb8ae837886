"""Round 9 of probing (docs/probe_round9.md): concurrency, odd but valid image
containers, batches over REST and the web page. Each test is the minimal
reproduction of a fault a user would hit, through the real ASGI stack
(FastAPI's TestClient), and holds once the fault is fixed."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from .conftest import isolated_app_client, mondrian_u16, strict_json, tiff_bytes


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    yield from isolated_app_client(tmp_path_factory.mktemp("store"), base_url="http://127.0.0.1")

_strict = strict_json


_mondrian, _tiff = mondrian_u16, tiff_bytes


# --- 1. CMYK and CIELab TIFFs read as RGB ----------------------------------------------------------

@pytest.mark.parametrize("photometric, planes, name", [("separated", 4, "CMYK"), ("cielab", 3, "CIELab")])
def test_a_cmyk_or_cielab_tiff_is_refused_not_read_as_rgb(client, photometric, planes, name):
    """A 16-bit CMYK TIFF was analysed as RGB with its K plane taken for an
    alpha channel ("fourth (alpha) channel ignored"), a 16-bit CIELab TIFF as
    RGB without a word: a light and a corrected picture made of C, M, Y or
    L*, a*, b*. Both are now a 415 ``unsupported_format`` naming the
    photometric interpretation, on every endpoint."""
    img = _mondrian()
    data = _tiff(np.dstack([img, img[..., :1]])[..., :planes], photometric=photometric)
    for ep, form in [("/v1/analyze", {}), ("/v1/white-balance", {"format": "png"}),
                     ("/v1/surfaces", {"grid": "2x2"}), ("/v1/preview", {"wb": "corrected"})]:
        r = client.post(ep, files={"file": ("a.tif", data)}, data=form)
        assert r.status_code == 415, (ep, r.status_code, r.text[:300])
        body = _strict(r.text)
        assert body["error"] == "unsupported_format" and name in body["detail"], body


def test_an_rgb_tiff_with_an_alpha_channel_is_still_read(client):
    """What holds: RGB with an alpha channel (and a 3-sample BlackIsZero
    TIFF) are read as before, the alpha ignored with a warning."""
    img = _mondrian()
    rgba = _tiff(np.dstack([img, np.full(img.shape[:2], 65535, np.uint16)]), photometric="rgb", extrasamples=[2])
    r = client.post("/v1/analyze", files={"file": ("a.tif", rgba)})
    assert r.status_code == 200 and "fourth (alpha) channel ignored" in r.json()["warnings"], r.text[:300]
    r = client.post("/v1/analyze", files={"file": ("a.tif", _tiff(img, photometric="minisblack",
                                                                   planarconfig="contig"))})
    assert r.status_code == 200, r.text[:300]


# --- 2. a TIFF's Orientation tag ---------------------------------------------------------------------

_TURN = {3: lambda a: a[::-1, ::-1], 6: lambda a: np.rot90(a, 3), 8: lambda a: np.rot90(a, 1)}


@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_a_tiffs_orientation_is_applied_as_for_a_raw(client, orientation):
    """A linear TIFF with Orientation 6 (a portrait from a camera or an
    editor) came back corrected on its side: the service read the stored
    pixels, ignored the tag and wrote its output with Orientation 1, so
    every viewer showed it turned; ``image.width``/``height`` and the
    ``points`` were in the stored frame, while for a RAW they are in the
    displayed one (LibRaw orients it). The tag is now applied as LibRaw
    applies it to a RAW: the answer is the upright file's answer turned,
    pixel for pixel, and a point names the same surface in the displayed
    frame."""
    import cv2

    img = _mondrian()
    upright = _tiff(_TURN[orientation](img).copy(), photometric="rgb")
    stored = _tiff(img, photometric="rgb", extratags=[(274, "H", 1, orientation, True)])
    answers = []
    for data in (upright, stored):
        r = client.post("/v1/white-balance", files={"file": ("a.tif", data)}, data={"format": "png16"})
        assert r.status_code == 200, r.text[:300]
        answers.append(cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED))
    np.testing.assert_array_equal(answers[1], answers[0])
    a = client.post("/v1/analyze", files={"file": ("a.tif", stored)}).json()
    b = client.post("/v1/analyze", files={"file": ("a.tif", upright)}).json()
    assert (a["image"]["width"], a["image"]["height"]) == (b["image"]["width"], b["image"]["height"])
    assert a["illuminant"]["camera_rgb"] == b["illuminant"]["camera_rgb"]
    pts = json.dumps([[3, 5], [40, 20]])
    s = [client.post("/v1/surfaces", files={"file": ("a.tif", d)}, data={"points": pts}).json()
         for d in (stored, upright)]
    assert [x["reflectance"] for x in s[0]["surfaces"]] == [x["reflectance"] for x in s[1]["surfaces"]]


def test_the_python_loader_says_a_tiffs_orientation(tmp_path):
    """``service.loader.load`` of the same TIFF: the picture upright and
    ``Photo.orientation`` the flip applied (LibRaw's code, as for a RAW)."""
    from service.loader import ORIENTATIONS, load

    img = _mondrian()
    path = tmp_path / "portrait.tif"
    path.write_bytes(_tiff(img, photometric="rgb", extratags=[(274, "H", 1, 6, True)]))
    photo = load(str(path))
    assert photo.full_shape == (img.shape[1], img.shape[0])
    assert ORIENTATIONS[photo.orientation] == "rotated 90 degrees clockwise"


# --- 3. queued requests held their uploads in memory --------------------------------------------------

def test_a_request_queued_for_a_work_slot_holds_no_copy_of_its_upload(env_settings, monkeypatch):
    """Heavy work runs ``WANDELL_MAX_CONCURRENT_WORK`` at a time and the
    rest queue (docs/robustness.md), but each queued request had already
    read its whole upload into memory: against ``python -m service``, 16
    simultaneous 60 MB TIFFs raised the server's memory by 1.3 GB where 2
    raised it by 0.4 GB, and the default connection limit lets hundreds
    queue (up to 200 MB each). The bytes are now read in the worker thread
    once the slot is held; until then the upload stays in the file the
    form parser spooled it to. Here, with the only slot held, four 8 MB
    uploads queue: the memory Python allocated meanwhile is under one of
    them, and each job still gets its whole file."""
    import asyncio
    import threading
    import tracemalloc

    import httpx

    from service import workers
    from service.app import app
    from service.errors import ServiceError
    from service.routers import analysis

    env_settings(max_concurrent_work=1)
    gate, sizes = threading.Event(), []

    def probe(data, *args, **kwargs):
        sizes.append(len(data))
        gate.wait(30)
        raise ServiceError(422, "probe", "stopped by the test")

    monkeypatch.setattr(analysis, "analyze_upload", probe)
    size, n = 8 << 20, 4
    payloads = [bytes([k + 1]) * size for k in range(n)]

    async def scenario():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t", timeout=60) as c:
            first = asyncio.create_task(c.post("/v1/analyze", files={"file": ("a.tif", b"II*\0" + bytes(64))}))
            while not sizes:
                await asyncio.sleep(0.01)
            tracemalloc.start()
            base = tracemalloc.get_traced_memory()[0]
            queued = [asyncio.create_task(c.post("/v1/analyze", files={"file": ("b.tif", p)})) for p in payloads]
            limiter = workers._LIMITERS[asyncio.get_running_loop()]
            for _ in range(3000):
                if limiter.statistics().tasks_waiting == n:
                    break
                await asyncio.sleep(0.01)
            waiting = limiter.statistics().tasks_waiting
            held = tracemalloc.get_traced_memory()[0] - base
            tracemalloc.stop()
            gate.set()
            return waiting, held, await asyncio.gather(first, *queued)

    waiting, held, answers = asyncio.run(scenario())
    assert waiting == n
    assert [r.status_code for r in answers] == [422] * (n + 1)
    assert sorted(sizes[1:]) == [size] * n                    # each job read its whole upload
    assert held < size, f"{n} queued requests hold {held / 2**20:.0f} MiB of Python memory"


# --- 4. a TIFF that starts with its thumbnail ----------------------------------------------------------

def test_a_tiff_starting_with_its_thumbnail_is_read_at_full_resolution(client):
    """A valid TIFF may hold a reduced-resolution copy (NewSubfileType 1, a
    thumbnail) before the full image. The service read the first page only:
    the light was estimated on the 16 x 12 thumbnail and the corrected
    picture was the thumbnail, without a word. The full-resolution image is
    now read, and the answer says which of the file's images it is; a
    multi-page TIFF says that its first image was used."""
    import cv2
    import tifffile

    img = _mondrian()
    buf = io.BytesIO()
    with tifffile.TiffWriter(buf) as tw:
        tw.write(np.ascontiguousarray(img[::4, ::4]), photometric="rgb", subfiletype=1)
        tw.write(img, photometric="rgb")
    r = client.post("/v1/white-balance", files={"file": ("a.tif", buf.getvalue())}, data={"format": "png16"})
    assert r.status_code == 200, r.text[:300]
    out = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert out.shape == img.shape
    plain = client.post("/v1/white-balance", files={"file": ("a.tif", _tiff(img, photometric="rgb"))},
                        data={"format": "png16"})
    np.testing.assert_array_equal(out, cv2.imdecode(np.frombuffer(plain.content, np.uint8), cv2.IMREAD_UNCHANGED))
    a = _strict(client.post("/v1/analyze", files={"file": ("a.tif", buf.getvalue())}).text)
    assert (a["image"]["height"], a["image"]["width"]) == img.shape[:2]
    assert any("image 2" in w and "reduced-resolution" in w for w in a["warnings"]), a["warnings"]
    buf = io.BytesIO()
    with tifffile.TiffWriter(buf) as tw:
        tw.write(img, photometric="rgb")
        tw.write(np.ascontiguousarray(img[::-1]), photometric="rgb")
    a = _strict(client.post("/v1/analyze", files={"file": ("a.tif", buf.getvalue())}).text)
    assert any("holds 2 images; image 1" in w for w in a["warnings"]), a["warnings"]


# --- 5. the page stopped following a batch after one failed poll ---------------------------------------

_PAGE_HARNESS = r"""
const fs = require("fs"), vm = require("vm");
function element() {
  const el = {textContent: "", hidden: true, disabled: false, className: "", value: "", dataset: {}, style: {},
              classList: {toggle() {}, add() {}, remove() {}}, addEventListener() {}, appendChild() {},
              setAttribute() {}, removeAttribute() {}};
  el.tBodies = [{set textContent(v) {}, insertRow: () => ({insertCell: () => element()})}];
  return el;
}
const els = {};
const $ = (id) => (els[id] = els[id] || element());
const timers = [];
const answers = JSON.parse(process.argv[3]);
const fetched = [];
const ctx = {
  console, JSON, Math, Number, String, Array, Object, Promise, Error, TypeError, isFinite, encodeURIComponent,
  document: {addEventListener() {}, getElementById: $,
             createElement: () => element(), querySelectorAll: () => []},
  setTimeout: (fn, ms) => { timers.push([fn, ms]); return timers.length; }, clearTimeout() {},
  fetch: async (url) => {
    fetched.push(url);
    const a = answers.shift();
    if (a === "network") throw new TypeError("Failed to fetch");
    return {ok: a.status < 400, status: a.status, statusText: "",
            headers: {get: (h) => (a.headers || {})[h.toLowerCase()] || null},
            json: async () => a.body};
  },
};
vm.createContext(ctx);
vm.runInContext(fs.readFileSync(process.argv[2], "utf8") +
  "\n;globalThis.startFollowing = (id) => { batch = {id, timer: null}; return poll(); };", ctx);
(async () => {
  await ctx.startFollowing("0123456789abcdef");
  const log = [];
  for (let k = 0; k < 10 && timers.length; k++) {
    const [fn, ms] = timers.shift();
    log.push({wait_ms: ms, error: $("batch-error").hidden ? null : $("batch-error").textContent,
              status: $("batch-status").textContent});
    await fn();
  }
  log.push({error: $("batch-error").hidden ? null : $("batch-error").textContent,
            status: $("batch-status").textContent, fetched: fetched.length});
  console.log(JSON.stringify(log));
})();
"""


def test_the_page_keeps_following_a_batch_through_a_busy_or_restarting_server(tmp_path):
    """The page polls a batch every 0.5 s; one failed poll stopped it for
    good: a 503 ``job_store_busy`` (whose ``Retry-After`` says to try again
    in a few seconds), the server's 503 ``too_many_connections``, or the
    server restarting (README: a batch cut short resumes when it starts
    again) left the page showing the error and a batch "running" for ever,
    with no way back to it but starting over. It now tries again (after
    ``Retry-After``, or 2, 4, ... up to 30 s), says so, and when the
    service answers again clears the error and follows the batch to its
    end; a 404 (the batch removed) is still final. Runs app.js under node
    with a stand-in for the page and for ``fetch``."""
    import shutil
    import subprocess
    from pathlib import Path

    node = shutil.which("node") or shutil.which("nodejs")
    if node is None:
        pytest.skip("node is not installed (apt-get install nodejs): the page's script cannot be run")
    app_js = Path(__file__).resolve().parents[1] / "service" / "static" / "app.js"
    harness = tmp_path / "harness.js"
    harness.write_text(_PAGE_HARNESS)
    running = {"id": "0123456789abcdef", "status": "running", "settled": False,
               "counts": {"done": 1, "failed": 0, "pending": 1, "running": 1, "total": 2}, "items": []}
    done = dict(running, status="done", settled=True,
                counts={"done": 2, "failed": 0, "pending": 0, "running": 0, "total": 2})
    busy = {"status": 503, "headers": {"retry-after": "5"},
            "body": {"error": "job_store_busy", "detail": "the batch job store is locked by another process"}}
    answers = [{"status": 200, "body": running}, busy, "network", {"status": 200, "body": running},
               {"status": 200, "body": done}]

    def run(answers):
        out = subprocess.run([node, str(harness), str(app_js), json.dumps(answers)], capture_output=True,
                             text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        return json.loads(out.stdout)

    log = run(answers)
    assert [step.get("wait_ms") for step in log[:4]] == [500, 5000, 4000, 500], log
    assert "locked by another process" in log[1]["error"] and "Trying again in 5 s" in log[1]["error"]
    assert "Could not reach the service" in log[2]["error"] and log[3]["error"] is None
    assert log[-1]["error"] is None and "finished" in log[-1]["status"] and log[-1]["fetched"] == 5, log
    gone = {"status": 404, "body": {"error": "not_found", "detail": "no batch '0123456789abcdef'"}}
    log = run([{"status": 200, "body": running}, gone])
    assert len(log) == 2 and "no batch" in log[-1]["error"] and log[-1]["fetched"] == 2, log   # no retry


# --- 6. a float TIFF on another scale -------------------------------------------------------------------

def test_a_float_tiff_above_full_scale_is_refused_saying_why(client):
    """Float samples are read with 1.0 as full scale (saturation). A float
    TIFF on another scale (an HDR merge's, here 33..763) has every pixel
    saturated and was a 422 "no usable pixels (all masked as dark,
    saturated or non-finite)": the rule was said nowhere, so the user could
    not tell what to change. The 422 (same code) now names the rule, the
    image's range and what to do, on every endpoint and for a batch item;
    the same picture scaled into 0..1 is analysed."""
    import time

    img = _mondrian().astype(np.float32) / 65535
    big = _tiff(img * 1000, photometric="rgb")
    for ep, form in [("/v1/analyze", {}), ("/v1/white-balance", {}), ("/v1/surfaces", {"grid": "2x2"}),
                     ("/v1/preview", {"wb": "corrected"})]:
        r = client.post(ep, files={"file": ("hdr.tif", big)}, data=form)
        body = _strict(r.text)
        assert r.status_code == 422 and body["error"] == "insufficient_surface_variation", (ep, r.text[:300])
        assert "full scale (saturation) of float samples" in body["detail"] and "into 0..1" in body["detail"]
    r = client.post("/v1/batches", files=[("files", ("hdr.tif", big))], data={"format": "png"})
    assert r.status_code == 202, r.text
    bid = r.json()["id"]
    for _ in range(600):
        doc = client.get(f"/v1/batches/{bid}").json()
        if doc["settled"]:
            break
        time.sleep(0.1)
    error = doc["items"][0]["error"]
    assert "full scale (saturation) of float samples" in json.dumps(error), doc["items"][0]
    ok = client.post("/v1/analyze", files={"file": ("ldr.tif", _tiff(img, photometric="rgb"))})
    assert ok.status_code == 200, ok.text[:300]
