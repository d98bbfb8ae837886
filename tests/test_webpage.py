"""The web page at ``GET /``: a unit test of what is served, and tests in a
real headless browser (Debian's chromium driven by playwright) against a real
uvicorn server on loopback.

Without chromium (or playwright) the browser tests skip, saying why, unless
the environment variable ``CI`` is set: then they fail, because CI must run
them (``.ci/run`` installs chromium and sets ``CI=1``).
"""

from __future__ import annotations

import base64
import io
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import rawpy
from fastapi.testclient import TestClient

from service.app import app
from testing.dngwriter import scene_dng

CHROMIUM = os.environ.get("WANDELL_CHROMIUM", "/usr/bin/chromium")
ROOT = Path(__file__).resolve().parents[1]
STATIC = ROOT / "service" / "static"
#: Copies of the screenshots land here (the pytest tmp dir has the originals).
SCREENSHOT_DIR = Path(os.environ.get("WANDELL_SCREENSHOT_DIR", tempfile.gettempdir()))
#: The one absolute URL the page's files may contain: the SVG namespace name
#: given to ``document.createElementNS`` (an identifier, never fetched).
ALLOWED_URLS = {"http://www.w3.org/2000/svg"}


# ---------------------------------------------------------------------------
# What is served (no browser)
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def client():
    return TestClient(app)


def test_page_and_its_files_are_served_with_their_types(client):
    r = client.get("/")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/html")
    html = r.text
    assert '<input type="file" id="file"' in html and 'id="batch-files" multiple' in html
    refs = re.findall(r'(?:src|href)="([^"]+)"', html)
    local = [u for u in refs if u.startswith("/")]
    assert "/static/app.js" in local and "/static/style.css" in local
    types = {".js": "text/javascript", ".css": "text/css"}
    for url in local:
        if url.startswith("/static/"):
            s = client.get(url)
            assert s.status_code == 200, url
            assert s.headers["content-type"].startswith(types[Path(url).suffix]), url
    assert client.get("/docs").status_code == 200   # the page links to it
    bad = client.get("/static/../settings.py")
    assert bad.status_code == 404 and bad.json()["error"] == "not_found"


def test_page_fetches_nothing_from_another_host(client):
    texts = {name: client.get(url).text for name, url in
             (("index.html", "/"), ("app.js", "/static/app.js"), ("style.css", "/static/style.css"))}
    for name, text in texts.items():
        urls = set(re.findall(r"(?:https?:)?//[A-Za-z0-9][^\s\"'<>)`]*", text))
        # "//" in a JavaScript comment is not a URL: keep only host-like ones
        urls = {u for u in urls if re.match(r"(?:https?:)?//[\w-]+\.[\w.-]+", u)}
        assert urls <= ALLOWED_URLS, (name, urls - ALLOWED_URLS)
    html = texts["index.html"]
    for url in re.findall(r'(?:src|href|action)="([^"]+)"', html):
        assert url.startswith(("/", "#")) or url == "data:,", url   # data:, = no favicon request
    assert "@import" not in texts["style.css"]
    assert all(u.startswith("#") for u in re.findall(r"url\(([^)]*)\)", texts["style.css"] + texts["app.js"]))
    assert "fetch(\"http" not in texts["app.js"] and "import(" not in texts["app.js"]


def test_every_element_the_script_uses_is_on_the_page():
    html = (STATIC / "index.html").read_text()
    js = (STATIC / "app.js").read_text()
    ids = set(re.findall(r'\bid="([\w-]+)"', html))
    used = set(re.findall(r'\$\("([\w-]+)"\)', js))
    assert used, "the script looks up no elements: the pattern is stale"
    assert used <= ids, used - ids


# ---------------------------------------------------------------------------
# The API the page's white balance uses (no browser)
# ---------------------------------------------------------------------------

def _tiny_dng(illuminant="A", **kw) -> bytes:
    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", illuminant, 120, 180, seed=4, **kw)
    return buf.getvalue()


@pytest.mark.parametrize("source", ["synthetic DNG, measured camera", "the real CinemaDNG, its matrices"])
def test_white_given_as_temperature_tint_renders_that_white(client, source):
    """``white=T/tint`` on /v1/white-balance and /v1/preview: the light used
    has that Temperature/Tint, and the estimate's own Temperature/Tint given
    back renders the estimate's white. Bounds: the DNG SDK's conversions
    (Robertson's table, interpolated one way in ``Get_xy_coord`` and the
    other in ``Set_xy_coord``) are not exact inverses: measured 0.20 K and
    0.0008 tint on both files, 0.0016 degrees of camera RGB for the measured
    camera (3e-5 through the CinemaDNG's matrices); the bounds are 0.5 K,
    0.05 and 0.05 degrees."""
    from recovery import angular_error

    from .conftest import shared_file

    data = _tiny_dng("A") if source.startswith("synthetic") else shared_file("data/raw/Blackmagic.dng").read_bytes()
    files = {"file": ("x.dng", data)}
    est = client.post("/v1/analyze", files=files).json()
    il = est["illuminant"]
    for t, tint in ((3200, 0), (6500, 10), (9000, -20)):
        got = client.post("/v1/white-balance", files=files,
                          data={"white": f"{t}/{tint:+d}", "response": "json"}).json()["illuminant"]
        assert got["temperature"] == pytest.approx(t, abs=0.5) and got["tint"] == pytest.approx(tint, abs=0.05)
    back = client.post("/v1/white-balance", files=files, data={
        "white": f"{il['temperature']:.4f}/{il['tint']:+.4f}", "response": "json"}).json()["illuminant"]
    assert angular_error(np.array(back["camera_rgb"]), np.array(il["camera_rgb"])) < 0.05
    r = client.post("/v1/preview", files=files, data={"wb": "corrected", "white": "5000/+5"})
    assert r.status_code == 200 and json.loads(r.headers["X-Preview"])["white"] == "5000/+5"
    # as-shot given as Temperature/Tint in /v1/analyze is the as-shot white's
    shot = client.post("/v1/white-balance", files=files, data={"white": "as-shot", "response": "json"}).json()
    assert est["as_shot"]["temperature"] == pytest.approx(shot["illuminant"]["temperature"], rel=1e-9)


@pytest.mark.parametrize("white,words", [("hot", "estimate, as-shot or TEMPERATURE/TINT"),
                                         ("1500/0", "2000..50000 K"), ("5000/+200", "tint in -150..+150"),
                                         ("5000", "TEMPERATURE/TINT"), ("nan/0", "TEMPERATURE/TINT")])
def test_a_bad_white_is_a_422_naming_the_forms(client, white, words):
    files = {"file": ("x.dng", _tiny_dng())}
    for path, extra in (("/v1/white-balance", {}), ("/v1/preview", {"wb": "corrected"})):
        r = client.post(path, files=files, data={"white": white, **extra})
        assert r.status_code == 422 and r.json()["error"] == "invalid_parameter", (path, r.text)
        assert words in r.json()["detail"], r.json()["detail"]


def test_preview_white_and_neutral_together_is_a_422(client):
    r = client.post("/v1/preview", files={"file": ("x.dng", _tiny_dng())},
                    data={"wb": "corrected", "white": "as-shot", "neutral": "[10, 10]"})
    assert r.status_code == 422 and "neutral" in r.json()["detail"]


# ---------------------------------------------------------------------------
# A real server and a real browser
# ---------------------------------------------------------------------------

def _unavailable(reason: str):
    if os.environ.get("CI"):
        pytest.fail(f"{reason}; CI is set, so the browser tests must run")
    pytest.skip(reason)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def server():
    """``uvicorn service.app:app`` in a subprocess on a free loopback port."""
    import httpx

    port = _free_port()
    log = tempfile.TemporaryFile()
    # the server's batch store in a temporary directory, never the user's (issue 29)
    store = tempfile.TemporaryDirectory(prefix="wandell-webpage-")
    env = dict(os.environ, WANDELL_DATA_DIR=store.name)
    proc = subprocess.Popen([sys.executable, "-m", "uvicorn", "service.app:app", "--host", "127.0.0.1",
                             "--port", str(port), "--log-level", "warning"],
                            cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, env=env)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            if proc.poll() is not None:
                log.seek(0)
                pytest.fail(f"uvicorn exited with {proc.returncode}: {log.read().decode(errors='replace')}")
            try:
                if httpx.get(base + "/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                pytest.fail("uvicorn did not answer /health within 60 s")
            time.sleep(0.2)
        yield base
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()
        store.cleanup()


@pytest.fixture(scope="module")
def browser():
    if not os.path.exists(CHROMIUM):
        _unavailable(f"chromium is not installed at {CHROMIUM} (apt-get install chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        _unavailable("the playwright package is not installed (pip install -e '.[test]')")
    with sync_playwright() as p:
        # Debian's chromium, never a downloaded one; --no-sandbox because CI
        # runs as root, where chromium's sandbox refuses to start
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        try:
            yield b
        finally:
            b.close()


@pytest.fixture
def page(browser, server):
    ctx = browser.new_context(viewport={"width": 1280, "height": 1000}, accept_downloads=True)
    pg = ctx.new_page()
    problems = []
    pg.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    pg.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
    pg.problems = problems
    pg.goto(server + "/")
    yield pg
    ctx.close()


def _screenshot(pg, tmp_path: Path, name: str) -> Path:
    path = tmp_path / name
    pg.screenshot(path=str(path), full_page=True)
    SCREENSHOT_DIR.mkdir(parents=True, exist_ok=True)
    shutil.copy(path, SCREENSHOT_DIR / name)
    return path


def _dng(path: Path, illuminant="A", seed=2) -> Path:
    scene_dng(path, "Nikon 5100 (NPL)", illuminant, 240, 360, seed=seed)
    return path


def test_upload_shows_both_images_the_light_and_the_diagnostics(page, server, tmp_path):
    import cv2
    import httpx

    dng = _dng(tmp_path / "scene.dng")
    page.set_input_files("#file", str(dng))           # choosing a file starts the analysis
    page.wait_for_selector("#result", state="visible", timeout=90_000)

    for sel in ("#img-original", "#img-corrected"):
        w = page.eval_on_selector(sel, "img => img.complete ? img.naturalWidth : 0")
        assert w > 0, f"{sel} shows no image"
    # the previews are the 2x2-binned image: 180 x 120 for a 360 x 240 file, both of the same frame
    assert page.eval_on_selector("#img-corrected", "i => [i.naturalWidth, i.naturalHeight]") == [180, 120]
    assert page.eval_on_selector("#img-original", "i => [i.naturalWidth, i.naturalHeight]") == [180, 120]

    # the numbers on the page are the API's (same file, same default options)
    est = httpx.post(server + "/v1/analyze", files={"file": ("scene.dng", dng.read_bytes())}, timeout=60).json()
    assert page.text_content("#cct") == f"{round(est['illuminant']['cct'])} K"      # under Technical details
    assert re.fullmatch(r"[+-]\d\.\d{4}", page.text_content("#duv"))

    # the spectrum: one vertex per wavelength of the estimate
    d = page.get_attribute("#spectrum-svg #spectrum-path", "d")
    assert d and d.startswith("M")
    assert len(re.findall(r"[ML]", d)) == len(est["illuminant"]["wavelengths"])

    summary = page.inner_text("#diag-summary")
    from recovery.methods import METHODS                 # the registry's words, served by /v1/models

    used = est.get("method") or est["diagnostics"].get("method")
    assert summary.startswith(f"Auto found a light of about {round(est['illuminant']['temperature'])} K, "
                              f"estimated by {METHODS[used].words}."), (used, summary)
    if est["diagnostics"].get("confidence") is not None:
        assert f"({round(100 * est['diagnostics']['confidence'])} %)" in summary
    # the jargon is folded away, and still there
    assert page.eval_on_selector("#diag-more", "d => d.open") is False
    assert "Camera: Nikon 5100 (NPL), with measured spectral sensitivities." in page.text_content("#diag-details")

    shot = _screenshot(page, tmp_path, "wandell-webpage.png")
    assert shot.stat().st_size > 10_000

    # downloads: the corrected PNG at full resolution, and the JSON estimate
    with page.expect_download(timeout=90_000) as dl:
        page.click("#dl-png")
    png = cv2.imdecode(np.frombuffer(Path(dl.value.path()).read_bytes(), np.uint8), cv2.IMREAD_UNCHANGED)
    assert dl.value.suggested_filename == "scene-corrected.png"
    assert png.shape == (240, 360, 3) and png.dtype == np.uint8
    with page.expect_download(timeout=90_000) as dl:       # JPEG too (the README's tour promises it)
        page.click("#dl-jpeg")
    data = Path(dl.value.path()).read_bytes()
    assert dl.value.suggested_filename == "scene-corrected.jpg" and data[:3] == b"\xff\xd8\xff"
    assert cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED).shape == (240, 360, 3)
    with page.expect_download(timeout=90_000) as dl:       # the DNG with the white balance inside (issue 30)
        page.click("#dl-dng")
    data = Path(dl.value.path()).read_bytes()
    assert dl.value.suggested_filename == "scene.wandell.dng" and data[:4] in (b"II*\x00", b"MM\x00*")
    with rawpy.imread(io.BytesIO(data)) as got, rawpy.imread(str(dng)) as orig:
        np.testing.assert_array_equal(got.raw_image_visible, orig.raw_image_visible)
    with page.expect_download() as dl:
        page.click("#dl-json")
    saved = json.loads(Path(dl.value.path()).read_text())
    assert saved["illuminant"]["cct"] == pytest.approx(est["illuminant"]["cct"], rel=1e-12)
    assert page.problems == []


def test_a_bad_upload_shows_the_error_in_words(page, tmp_path):
    # dropped onto the drop zone (the other way in), a text file
    text = b"this is not a photograph\n"
    page.evaluate("""([b64, name]) => {
        const bytes = Uint8Array.from(atob(b64), c => c.charCodeAt(0));
        const dt = new DataTransfer();
        dt.items.add(new File([bytes], name, {type: "text/plain"}));
        document.getElementById("drop").dispatchEvent(new DragEvent("drop", {dataTransfer: dt, bubbles: true}));
    }""", [base64.b64encode(text).decode(), "notes.txt"])
    page.wait_for_selector("#error", state="visible", timeout=30_000)
    msg = page.inner_text("#error")
    assert msg.startswith("This is not a file the service can read:"), msg
    assert "'notes.txt'" in msg and "415" in msg
    assert page.is_hidden("#result")
    _screenshot(page, tmp_path, "wandell-webpage-error.png")
    # the failed request is the only console error (the browser logs a 4xx)
    assert all("status of 415" in p for p in page.problems), page.problems


def test_batch_view_shows_progress_and_items(page, server, tmp_path):
    import httpx

    probe = httpx.post(server + "/v1/batches", timeout=30)
    if probe.status_code in (404, 405):
        pytest.skip(f"POST /v1/batches answers {probe.status_code}: the batch endpoints are not in this build")
    files = [_dng(tmp_path / "a.dng", "A", 3), _dng(tmp_path / "b.dng", "D65", 4), tmp_path / "bad.dng"]
    files[2].write_bytes(files[0].read_bytes()[:2000])   # truncated: fails its item only
    page.set_input_files("#batch-files", [str(f) for f in files])
    page.click("#batch-run")
    page.wait_for_selector("#batch-view", state="visible", timeout=30_000)
    # finished when the cancel button goes away (a hidden element: wait_for_selector's "hidden" state;
    # wait_for_function would need eval, which the page's Content-Security-Policy forbids)
    page.wait_for_selector("#batch-cancel", state="hidden", timeout=180_000)
    assert page.eval_on_selector("#batch-progress", "p => [p.value, p.max]") == [3, 3]
    rows = page.eval_on_selector_all("#batch-table tbody tr",
                                     "rs => rs.map(r => Array.from(r.cells, c => c.innerText))")
    by_name = {r[0]: r for r in rows}
    assert set(by_name) == {"a.dng", "b.dng", "bad.dng"}
    for n in ("a.dng", "b.dng"):
        assert by_name[n][1] == "done" and re.fullmatch(r"\d+ K", by_name[n][2]), by_name[n]
    assert by_name["bad.dng"][1] == "failed" and by_name["bad.dng"][3], by_name["bad.dng"]
    assert "2 done, 1 failed, 0 pending of 3" in page.inner_text("#batch-status")
    assert page.is_visible("#batch-zip")
    _screenshot(page, tmp_path, "wandell-webpage-batch.png")
    # issue 29, item 6: the page removes a settled batch (after a confirmation) and the server forgets it
    bid = httpx.get(server + "/v1/batches", timeout=30).json()["batches"]
    assert page.is_visible("#batch-remove")
    page.once("dialog", lambda d: d.accept())
    page.click("#batch-remove")
    page.wait_for_selector("#batch-view", state="hidden", timeout=30_000)
    assert "removed from the server" in page.inner_text("#batch-note")
    after = {b["id"] for b in httpx.get(server + "/v1/batches", timeout=30).json()["batches"]}
    assert len(after) == len(bid) - 1


def test_batch_form_offers_the_dng_with_the_white_balance_inside(page, server, tmp_path):
    """Issue 30, item 3: the batch's format choice offers DNG; a DNG's item
    downloads as NAME.dng (the bytes /v1/white-balance format=dng answers,
    which LibRaw reads), a linear TIFF's item fails alone, saying why."""
    import httpx
    import tifffile

    options = page.eval_on_selector_all("#opt-format option", "os => os.map(o => o.value)")
    assert options == ["tiff", "png", "png16", "jpeg", "dng"]
    page.select_option("#opt-format", "dng")
    tif = tmp_path / "linear.tif"
    tifffile.imwrite(tif, (np.random.default_rng(1).random((60, 90, 3)) * 60000).astype(np.uint16), photometric="rgb")
    dng = _dng(tmp_path / "a.dng", "A", 6)
    page.set_input_files("#batch-files", [str(dng), str(tif)])
    page.click("#batch-run")
    page.wait_for_selector("#batch-view", state="visible", timeout=30_000)
    page.wait_for_selector("#batch-cancel", state="hidden", timeout=180_000)
    rows = page.eval_on_selector_all("#batch-table tbody tr",
                                     "rs => rs.map(r => Array.from(r.cells, c => c.innerText))")
    by_name = {r[0]: r for r in rows}
    assert by_name["a.dng"][1] == "done", by_name
    assert by_name["linear.tif"][1] == "failed" and "not_a_raw" in by_name["linear.tif"][3], by_name
    assert "ask for tiff" in by_name["linear.tif"][3]
    with page.expect_download() as dl:
        page.click("#batch-table tbody tr.item-done a")
    assert dl.value.suggested_filename == "a.dng"
    got = tmp_path / "got.dng"
    dl.value.save_as(got)
    one = httpx.post(server + "/v1/white-balance", files={"file": ("a.dng", dng.read_bytes())},
                     data={"format": "dng"}, timeout=120)
    assert one.status_code == 200 and got.read_bytes() == one.content
    with rawpy.imread(str(dng)) as a, rawpy.imread(str(got)) as b:
        np.testing.assert_array_equal(b.raw_image_visible, a.raw_image_visible)
    _screenshot(page, tmp_path, "wandell-webpage-batch-dng.png")


def test_phone_width_has_no_horizontal_scroll_and_a_click_sets_the_white(browser, server, tmp_path):
    """Issue 13, items 4 and 7: at 375 px nothing is wider than the screen
    (before the fix the options' fieldset was 395 px), with the results
    shown; a click on the corrected image fixes the white from there."""
    ctx = browser.new_context(viewport={"width": 375, "height": 800})
    pg = ctx.new_page()
    pg.goto(server + "/")
    pg.set_input_files("#file", str(_dng(tmp_path / "scene.dng")))
    pg.wait_for_selector("#result", state="visible", timeout=90_000)
    assert pg.evaluate("document.documentElement.scrollWidth") <= 375
    # the options (two menus a row) leave room: the picture starts on the first screen
    assert pg.evaluate("document.querySelector('#viewer').getBoundingClientRect().top + scrollY") < 800
    viewer = pg.locator("#viewer")
    viewer.scroll_into_view_if_needed()
    box = viewer.bounding_box()
    viewer.click(position={"x": box["width"] * 0.3, "y": box["height"] * 0.3})
    for _ in range(180):
        if (pg.locator("#neutral-note").text_content() or "").startswith("White taken"):
            break
        pg.wait_for_timeout(500)
    assert pg.locator("#neutral-note").text_content().startswith("White taken")
    assert pg.locator("#neutral-clear").is_visible()
    # the mark sits where the click was
    mark = pg.locator("#pick-mark").bounding_box()
    assert abs(mark["x"] + mark["width"] / 2 - (box["x"] + 0.3 * box["width"])) <= 1.5, (mark, box)
    assert abs(mark["y"] + mark["height"] / 2 - (box["y"] + 0.3 * box["height"])) <= 1.5, (mark, box)
    assert pg.evaluate("document.documentElement.scrollWidth") <= 375
    pg.click("#zoom-100")                    # 100 % on a phone: the view pans, the page does not widen
    pg.wait_for_selector("#zoom-note:has-text('full size')", timeout=120_000)
    assert pg.evaluate("document.documentElement.scrollWidth") <= 375
    _screenshot(pg, tmp_path, "wandell-webpage-phone.png")
    ctx.close()


# ---------------------------------------------------------------------------
# Issue 19: /docs "Try it out", the batch's cancel, keyboard, layout
# ---------------------------------------------------------------------------

def _try_it_out(pg, operation_id: str, upload: Path):
    """Open an operation on /docs, "Try it out", choose ``upload`` for its
    file field, "Execute": the response, and the curl command Swagger shows."""
    op = pg.locator(f"#operations-default-{operation_id}")
    op.locator(".opblock-summary").click()
    op.locator(".try-out__btn").click()
    op.locator("input[type=file]").first.set_input_files(str(upload))
    with pg.expect_response(lambda r: r.request.method == "POST", timeout=120_000) as resp:
        op.locator(".execute").click()
    op.locator(".live-responses-table .response-col_status").first.wait_for(timeout=60_000)
    return resp.value, op.locator(".curl-command").inner_text()


def test_docs_try_it_out_runs_each_operation_with_its_defaults(browser, server, tmp_path):
    """Issue 19, item 3: Swagger UI filled the optional fields with their
    examples (neutral=1200,2040, surface_dim=2, ...) and every try was a
    422. Now "Try it out" + "Execute" with only a file runs as documented:
    the same answer as the API without options."""
    import httpx

    dng = _dng(tmp_path / "scene.dng")
    ctx = browser.new_context(viewport={"width": 1280, "height": 1000})
    pg = ctx.new_page()
    pg.goto(server + "/docs")
    pg.wait_for_selector(".opblock", timeout=30_000)
    resp, curl = _try_it_out(pg, "analyze_v1_analyze_post", dng)
    assert resp.status == 200, (resp.status, resp.text(), curl)
    for example in ("1200", "2040", "=matrix", "=balanced", "=pca", "=daylight", "=string", "=null"):
        assert example not in curl, (example, curl)
    got = resp.json()
    plain = httpx.post(server + "/v1/analyze", files={"file": ("scene.dng", dng.read_bytes())}, timeout=60).json()
    assert got["method"] == plain["method"] and got["illuminant"]["cct"] == pytest.approx(plain["illuminant"]["cct"])
    _screenshot(pg, tmp_path, "wandell-docs-try-it-out.png")
    resp, curl = _try_it_out(pg, "preview_v1_preview_post", dng)
    assert resp.status == 200 and resp.headers["content-type"] == "image/jpeg", (resp.status, curl)
    ctx.close()


def _batch_files(tmp_path: Path, n: int, shape=(240, 360)) -> list[Path]:
    out = []
    for i in range(n):
        p = tmp_path / f"IMG_{2040 + i}.dng"
        scene_dng(p, "Nikon 5100 (NPL)", "D4000", shape[0], shape[1], seed=10 + i)
        out.append(p)
    return out


def test_cancel_stops_running_items_and_the_page_shows_the_end_state(page, server, tmp_path):
    """Issue 19, item 2: Cancel while items run; the page keeps polling until
    the API says every count is final, and then shows exactly the API's
    counts and item states (it showed "cancelled, 0 done, 7 pending" for
    ever while the API said 7 done)."""
    import httpx

    files = _batch_files(tmp_path, 10, (1000, 1500))
    page.set_input_files("#batch-files", [str(f) for f in files])
    page.click("#batch-run")
    page.wait_for_selector("#batch-view", state="visible", timeout=60_000)
    bid = page.inner_text("#batch-status").split(":")[0].replace("Batch ", "").strip()
    t_end = time.monotonic() + 180
    while True:
        c = httpx.get(f"{server}/v1/batches/{bid}", timeout=30).json()["counts"]
        if c["done"] >= 1:
            break
        assert time.monotonic() < t_end, c
        time.sleep(0.05)
    assert c["done"] + c["failed"] < len(files), "finished before the cancel: the test proves nothing"
    page.click("#batch-cancel")
    page.wait_for_selector("#batch-cancel", state="hidden", timeout=60_000)   # the page saw it settle
    doc = httpx.get(f"{server}/v1/batches/{bid}", timeout=30).json()
    c = doc["counts"]
    assert doc["status"] == "cancelled" and doc["settled"] and c["running"] == 0 and c["pending"] == 0
    assert c["cancelled"] >= 1 and c["done"] + c["failed"] + c["cancelled"] == len(files)
    status = page.inner_text("#batch-status")
    assert f"{c['done']} done, {c['failed']} failed, 0 pending, {c['cancelled']} cancelled of {len(files)}" \
        in status, (status, c)
    assert "left" not in status, status
    rows = page.eval_on_selector_all("#batch-table tbody tr", "rs => rs.map(r => r.cells[1].innerText)")
    assert rows == [it["status"] for it in doc["items"]]
    page.wait_for_timeout(1500)   # and it stays so
    assert page.inner_text("#batch-status") == status
    # the bar shows the work done: done and failed items, not the cancelled ones
    assert page.eval_on_selector("#batch-progress", "p => [p.value, p.max]") == [c["done"] + c["failed"], len(files)]
    _screenshot(page, tmp_path, "wandell-webpage-batch-cancelled.png")


#: Cells of the batch table with a word broken across two lines although it
#: would fit on one (a hyphen or a space is a break opportunity; a word
#: longer than the whole line may only be broken).
_BROKEN_WORDS = """tds => tds.filter(td => {
    const t = td.firstChild;
    if (!t || t.nodeType !== 3) return false;
    const r = document.createRange();
    let off = 0;
    for (const w of t.textContent.split(/(\\s+|-)/)) {
      if (w.trim() && w !== "-") {
        r.setStart(t, off); r.setEnd(t, off + w.length);
        const rects = Array.from(r.getClientRects());
        const width = rects.reduce((a, x) => a + x.width, 0);
        if (new Set(rects.map(x => Math.round(x.top))).size > 1 && width < td.clientWidth - 16) return true;
      }
      off += w.length;
    }
    return false;
  }).map(td => td.innerText)"""


@pytest.mark.parametrize("width", [1280, 375])
def test_keyboard_opens_the_choosers_the_table_keeps_words_whole_and_the_flag_keeps_images_in_line(
        browser, server, tmp_path, width):
    """Issue 19, item 7: the drop zones are reached by Tab, show their focus
    and open the file chooser on Enter/Space; batch table words never break
    mid-word; a finished batch does not say "About 0 s left"; the red
    "not trustworthy" flag leaves the two images side by side in line."""
    ctx = browser.new_context(viewport={"width": width, "height": 900})
    pg = ctx.new_page()
    # intercept file choosers from the start (playwright turns interception on
    # without waiting for it: turned on at the key press, it can come too late)
    pg.on("filechooser", lambda chooser: None)
    pg.goto(server + "/")
    pg.select_option("#opt-method", "maloney-wandell")   # its own tests fail on this scene: the flag shows
    for _ in range(30):
        pg.keyboard.press("Tab")
        if pg.evaluate("document.activeElement.id") == "drop":
            break
    assert pg.evaluate("document.activeElement.id") == "drop"
    style = pg.eval_on_selector("#drop", "e => [getComputedStyle(e).outlineStyle, getComputedStyle(e).outlineWidth]")
    assert style[0] not in ("none", "auto") and float(style[1].rstrip("px")) >= 2, style
    with pg.expect_file_chooser(timeout=5000) as fc:
        pg.keyboard.press("Enter")
    fc.value.set_files(str(_dng(tmp_path / "scene.dng")))
    pg.wait_for_selector("#result", state="visible", timeout=90_000)
    assert pg.is_visible("#corrected-flag")
    # before and after are one picture split by the divider: the flag is below it, not between them
    tops = pg.eval_on_selector_all("#img-original, #img-corrected",
                                   "is => is.map(i => Math.round(i.getBoundingClientRect().top))")
    assert tops[0] == tops[1], tops
    assert pg.locator("#corrected-flag").bounding_box()["y"] >= pg.locator("#viewer").bounding_box()["y"] + \
        pg.locator("#viewer").bounding_box()["height"]
    _screenshot(pg, tmp_path, f"wandell-webpage-flag-{width}.png")

    for _ in range(60):
        pg.keyboard.press("Tab")
        if pg.evaluate("document.activeElement.id") == "batch-drop":
            break
    assert pg.evaluate("document.activeElement.id") == "batch-drop"
    files = _batch_files(tmp_path, 2)
    bad = tmp_path / "DSC_0415_card_error_with_a_long_name.dng"
    bad.write_bytes(files[0].read_bytes()[:2000])
    with pg.expect_file_chooser(timeout=5000) as fc:
        pg.keyboard.press(" ")
    fc.value.set_files([str(f) for f in files + [bad]])
    pg.click("#batch-run")
    pg.wait_for_selector("#batch-view", state="visible", timeout=30_000)
    pg.wait_for_selector("#batch-cancel", state="hidden", timeout=180_000)
    status = pg.inner_text("#batch-status")
    assert "2 done, 1 failed, 0 pending of 3" in status and "left" not in status, status
    assert pg.eval_on_selector_all("#batch-table td", _BROKEN_WORDS) == []
    assert pg.evaluate("document.documentElement.scrollWidth") <= width
    _screenshot(pg, tmp_path, f"wandell-webpage-batch-table-{width}.png")
    ctx.close()


def test_preview_shows_the_default_crop_and_says_the_output_size(page, tmp_path):
    """Issue 19, item 7: the real CinemaDNG (4128x2176, DefaultCrop
    4096x2160): the previews are of the crop the downloads hold, and the
    caption gives the downloads' size."""
    from .conftest import shared_file

    dng = shared_file("data/raw/Blackmagic.dng")
    page.set_input_files("#file", str(dng))
    page.wait_for_selector("#result", state="visible", timeout=300_000)
    assert "the downloads are 4096×2160" in page.inner_text("#corrected-note")
    for sel in ("#img-original", "#img-corrected"):
        w, h = page.eval_on_selector(sel, "i => [i.naturalWidth, i.naturalHeight]")
        assert abs(w / h - 4096 / 2160) < 0.004, (sel, w, h)   # uncropped: 4128 / 2176 = 1.8971 vs 1.8963
        assert w <= 1024


# ---------------------------------------------------------------------------
# Issue 29: the page as a place to work
# ---------------------------------------------------------------------------

#: The bytes of an <img> as the page holds them (the blob it made the image's URL of).
_IMG_BYTES = """sel => new Promise((resolve, reject) => {
    const f = new FileReader();
    f.onload = () => resolve(f.result.split(",")[1]);
    f.onerror = () => reject(f.error);
    f.readAsDataURL(document.querySelector(sel).blob);   // the page keeps the bytes it shows (no fetch: CSP)
})"""


def _img(pg, sel: str) -> np.ndarray:
    """The image an <img> shows, decoded by OpenCV (BGR, uint8)."""
    import cv2

    data = base64.b64decode(pg.evaluate(_IMG_BYTES, sel))
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)


def _wait_rendered(pg, timeout_s=120):
    """Until the white-balance panel says nothing is pending."""
    for _ in range(int(timeout_s * 4)):
        if not (pg.text_content("#wb-status") or "").strip():
            return
        pg.wait_for_timeout(250)
    raise AssertionError("the corrected image was not rendered again")


def _open(pg, server, path: Path):
    pg.goto(server + "/")
    pg.set_input_files("#file", str(path))
    pg.wait_for_selector("#result", state="visible", timeout=120_000)
    pg.wait_for_selector("#status:has-text('Done')", timeout=120_000)


def test_zoom_100_shows_the_downloads_pixels_one_to_one_and_pans(browser, server, tmp_path):
    """100 %: the full-size image (the download's rendering) with one image
    pixel per screen pixel: a screenshot of the view equals the image's own
    pixels at the place the view says it shows, and fits them worse one
    pixel off (so the comparison can tell); a drag pans by the drag."""
    import cv2

    dng = tmp_path / "big.dng"
    scene_dng(dng, "Nikon 5100 (NPL)", "D50", 900, 1600, seed=21)
    ctx = browser.new_context(viewport={"width": 1280, "height": 1000}, device_scale_factor=1)
    pg = ctx.new_page()
    _open(pg, server, dng)
    assert pg.eval_on_selector("#img-corrected", "i => i.naturalWidth") <= 800          # the binned preview
    pg.click("#view-after")
    pg.click("#zoom-100")
    pg.wait_for_selector("#zoom-note:has-text('full size')", timeout=120_000)
    assert pg.eval_on_selector("#img-corrected", "i => [i.naturalWidth, i.naturalHeight]") == [1600, 900]
    box = pg.eval_on_selector("#img-corrected", "i => { const b = i.getBoundingClientRect(); return [b.width, b.height]; }")
    assert box == pytest.approx([1600, 900], abs=0.01)

    def shown_vs_image():
        v = pg.locator("#viewer").bounding_box()
        s = pg.eval_on_selector("#img-corrected", "i => { const b = i.getBoundingClientRect(); return [b.left, b.top]; }")
        shot = cv2.imdecode(np.frombuffer(pg.screenshot(clip={"x": v["x"] + 100, "y": v["y"] + 60, "width": 300,
                                                                  "height": 200}), np.uint8), cv2.IMREAD_COLOR)
        full = _img(pg, "#img-corrected").astype(float)
        c0, r0 = round(v["x"] + 100 - s[0]), round(v["y"] + 60 - s[1])
        diffs = {}
        for dr, dc in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)):
            diffs[(dr, dc)] = float(np.abs(shot - full[r0 + dr:r0 + dr + 200, c0 + dc:c0 + dc + 300]).mean())
        return (r0, c0), diffs

    (r0, c0), diffs = shown_vs_image()
    off = min(v for k, v in diffs.items() if k != (0, 0))
    assert diffs[(0, 0)] < 0.5 * off, diffs             # aligned 1:1 fits better than any one-pixel shift
    _screenshot(pg, tmp_path, "wandell-webpage-100.png")

    # pan: drag the picture 200 px left and 100 px up: the view shows 200 columns and 100 rows further
    v = pg.locator("#viewer").bounding_box()
    pg.mouse.move(v["x"] + 600, v["y"] + 300)
    pg.mouse.down()
    pg.mouse.move(v["x"] + 500, v["y"] + 250, steps=5)
    pg.mouse.move(v["x"] + 400, v["y"] + 200, steps=5)
    pg.mouse.up()
    (r1, c1), diffs = shown_vs_image()
    assert (r1 - r0, c1 - c0) == (100, 200), ((r0, c0), (r1, c1))
    assert diffs[(0, 0)] < 0.5 * min(v for k, v in diffs.items() if k != (0, 0)), diffs
    assert not (pg.text_content("#neutral-note") or "").startswith("White taken")   # a drag picks no white
    ctx.close()


def test_split_divider_moves_and_shows_before_left_after_right(browser, server, tmp_path):
    """A scene under CIE A whose camera recorded a daylight white: before
    (as shot) is orange, after (Auto) is not; the divider splits the view
    where it is dragged, and the keyboard moves it too."""
    import cv2

    dng = tmp_path / "warm.dng"
    scene_dng(dng, "Nikon 5100 (NPL)", "A", 240, 360, seed=5, as_shot_neutral="D65")
    ctx = browser.new_context(viewport={"width": 1280, "height": 1000}, device_scale_factor=1)
    pg = ctx.new_page()
    _open(pg, server, dng)
    assert pg.get_attribute("#view-split", "aria-pressed") == "true"
    v = pg.locator("#viewer").bounding_box()
    d = pg.locator("#divider").bounding_box()
    assert abs(d["x"] + d["width"] / 2 - (v["x"] + v["width"] / 2)) <= 1

    def warmth(x_fraction):
        """R - B of a column strip of the view at ``x_fraction`` of its width (screenshot)."""
        shot = cv2.imdecode(np.frombuffer(pg.screenshot(clip={"x": v["x"] + x_fraction * v["width"] - 5,
                                                                  "y": v["y"] + 0.2 * v["height"], "width": 10,
                                                                  "height": 0.6 * v["height"]}), np.uint8),
                            cv2.IMREAD_COLOR).astype(float)
        return float(shot[..., 2].mean() - shot[..., 0].mean())

    # how much warmer before is than after, over the whole images
    rb = [float(i[..., 2].mean() - i[..., 0].mean()) for i in (_img(pg, "#img-original").astype(float),
                                                                _img(pg, "#img-corrected").astype(float))]
    assert rb[0] - rb[1] > 20, rb
    w15, w40 = warmth(0.15), warmth(0.40)
    # drag the divider to a quarter of the width: 40 % is now on the after side, 15 % still before
    pg.mouse.move(d["x"] + d["width"] / 2, d["y"] + d["height"] / 2)
    pg.mouse.down()
    pg.mouse.move(v["x"] + 0.25 * v["width"], d["y"] + d["height"] / 2, steps=8)
    pg.mouse.up()
    assert pg.get_attribute("#divider", "aria-valuenow") == "25"
    assert warmth(0.15) == w15
    assert w40 - warmth(0.40) > 0.5 * (rb[0] - rb[1]), (w40, warmth(0.40), rb)
    pg.focus("#divider")
    pg.keyboard.press("ArrowRight")
    assert pg.get_attribute("#divider", "aria-valuenow") == "30"
    pg.click("#view-before")
    assert pg.is_hidden("#after-layer") and pg.is_hidden("#divider")
    _screenshot(pg, tmp_path, "wandell-webpage-split.png")
    ctx.close()


def test_temperature_slider_re_renders_in_the_expected_direction(page, server, tmp_path):
    """Custom white: a higher Temperature is a bluer light corrected away,
    so the picture gets warmer (more red than blue), a lower one cooler;
    the image shown is the API's own rendering for that white (the same
    bytes as /v1/preview with white=T/tint); As shot and Auto show the
    API's Temperature/Tint."""
    import httpx

    dng = _dng(tmp_path / "scene.dng", "D50", 6)
    _open(page, server, dng)
    est = httpx.post(server + "/v1/analyze", files={"file": ("scene.dng", dng.read_bytes())}, timeout=60).json()
    il, shot = est["illuminant"], est["as_shot"]
    assert page.text_content("#auto-tt") == f"{round(il['temperature'])} K, tint {round(il['tint']):+d}"
    assert page.text_content("#asshot-tt").startswith(f"{round(shot['temperature'])} K, tint {round(shot['tint']):+d}")
    assert f"({shot['angle_to_estimate_deg']:.1f}° from Auto)" in page.text_content("#asshot-tt")

    def red_minus_blue():
        img = _img(page, "#img-corrected").astype(float)
        return float(img[..., 2].mean() - img[..., 0].mean())

    auto = red_minus_blue()
    results = {}
    for k in (3500, 9000):
        page.eval_on_selector("#temp", """(el, k) => {
            el.value = Math.round(1000 * (500 - 1e6 / k) / (500 - 20));
            el.dispatchEvent(new Event("input", {bubbles: true}));
        }""", k)
        assert page.get_attribute("#wb-custom", "aria-pressed") == "true"
        _wait_rendered(page)
        white = page.text_content("#dl-white").replace("Custom ", "")
        t = float(white.split("/")[0])
        assert abs(t - k) <= 0.01 * k, (white, k)                    # the slider's scale is the one shown
        results[k] = red_minus_blue()
        ref = httpx.post(server + "/v1/preview", files={"file": ("scene.dng", dng.read_bytes())},
                         data={"wb": "corrected", "white": white, "target": "D65", "format": "jpeg",
                               "max_side": "1024"}, timeout=60)
        assert ref.status_code == 200 and base64.b64decode(page.evaluate(_IMG_BYTES, "#img-corrected")) == ref.content
    assert results[3500] < auto < results[9000], (results, auto)
    page.click("#wb-auto")
    _wait_rendered(page)
    assert red_minus_blue() == pytest.approx(auto, abs=1e-9)
    assert page.problems == []


def test_histogram_and_clipping_are_the_images(page, server, tmp_path):
    """The histogram's counts are the corrected image's (decoded by OpenCV
    from the same bytes), and the clipping overlay marks exactly its
    clipped pixels; an over-exposed scene has some."""
    import cv2

    dng = tmp_path / "bright.dng"
    scene_dng(dng, "Nikon 5100 (NPL)", "D65", 240, 360, seed=8, exposure=1.0)
    _open(page, server, dng)
    img = _img(page, "#img-corrected")
    counts = json.loads(page.get_attribute("#histogram", "data-counts"))
    for k, ch in enumerate((2, 1, 0)):          # R, G, B in the page; OpenCV is BGR
        ours = np.bincount(img[..., ch].ravel(), minlength=256)
        # two JPEG decoders (Chromium's, OpenCV's): each pixel at most a level or two apart
        assert sum(counts[k]) == ours.sum()
        assert abs(np.dot(np.arange(256), counts[k]) - np.dot(np.arange(256), ours)) / ours.sum() < 0.5
    high = (img >= 254).any(axis=2)
    low = (img <= 1).all(axis=2) & ~high
    assert high.mean() > 0.001, "the scene has no clipped highlights: the test proves nothing"
    page.check("#show-clipping")
    marked = int(page.get_attribute("#clip-overlay", "data-marked"))
    assert abs(marked - int(high.sum() + low.sum())) <= 0.01 * high.size
    assert page.is_visible("#clip-overlay")
    assert float(page.get_attribute("#clip-stats", "data-high")) == pytest.approx(high.mean(), abs=0.01)
    _screenshot(page, tmp_path, "wandell-webpage-clipping.png")


def test_target_lights_the_api_takes(page, server, tmp_path):
    """Target light offers D50, A, a daylight or blackbody at a chosen
    kelvin and "as seen", and the page's request is one the API takes."""
    page.wait_for_selector("#opt-target option[value='FL11']", state="attached")   # GET /v1/models's names
    values = page.eval_on_selector_all("#opt-target option", "os => os.map(o => o.value)")
    for v in ("D65", "D50", "A", "estimate", "custom-D", "custom-BB", "FL11"):
        assert v in values, (v, values)
    dng = _dng(tmp_path / "scene.dng", "D50", 6)
    _open(page, server, dng)
    page.select_option("#opt-target", "custom-BB")
    page.fill("#target-k", "3200")
    page.dispatch_event("#target-k", "change")
    page.wait_for_selector("#corrected-target:has-text('BB3200')", timeout=120_000)
    page.wait_for_selector("#status:has-text('Done')", timeout=120_000)
    assert page.is_hidden("#error")


def test_an_unmeasured_dng_camera_is_a_quiet_note_once_not_a_warning(page, server, tmp_path):
    """The "approximate camera" of a DNG without measured sensitivities is
    information, said once: the first file notes it, a second says nothing
    of it outside the details; it is a warning only when the estimate is
    uncertain (not so here: the check below says which case ran)."""
    dng = tmp_path / "unknown.dng"
    scene_dng(dng, "Nikon 5100 (NPL)", "D50", 240, 360, seed=9, make="Acme", model="Unmeasured 1")
    _open(page, server, dng)
    import httpx

    est = httpx.post(server + "/v1/analyze", files={"file": ("u.dng", dng.read_bytes())}, timeout=60).json()
    assert est["camera"]["source"] == "matrix-derived" and "approximate: derived from colour matrix" in est["warnings"]
    assert not est["diagnostics"].get("low_confidence"), "the estimate is uncertain here: the case is the other one"
    assert "not measured" in page.text_content("#diag-notes")
    assert "approximate" not in page.text_content("#diag-warnings").lower()
    assert "not measured" not in page.text_content("#diag-warnings")
    page.set_input_files("#file", str(_dng(tmp_path / "second.dng", "D50", 10)))
    page.set_input_files("#file", str(dng))
    page.wait_for_selector("#status:has-text('Done')", timeout=120_000)
    assert "not measured" not in page.text_content("#diag-notes")
    assert "matrix-derived" in page.text_content("#diag-details")


def test_a_batch_cancelled_before_anything_ran_shows_an_empty_bar(page, server, tmp_path):
    files = _batch_files(tmp_path, 6, (1000, 1500))
    page.set_input_files("#batch-files", [str(f) for f in files])
    page.click("#batch-run")
    page.wait_for_selector("#batch-cancel", state="visible", timeout=60_000)
    page.click("#batch-cancel")
    page.wait_for_selector("#batch-cancel", state="hidden", timeout=120_000)
    import httpx

    bid = page.inner_text("#batch-status").split(":")[0].replace("Batch ", "").strip()
    c = httpx.get(f"{server}/v1/batches/{bid}", timeout=30).json()["counts"]
    value, mx = page.eval_on_selector("#batch-progress", "p => [p.value, p.max]")
    assert (value, mx) == (c["done"] + c["failed"], len(files)), c
    # and it looks so: the bar's right end is the light track unless every item was done
    import cv2

    bar = page.locator("#batch-progress").bounding_box()
    end = cv2.imdecode(np.frombuffer(page.screenshot(clip={"x": bar["x"] + bar["width"] - 12, "y": bar["y"] + 4,
                                                           "width": 8, "height": bar["height"] - 8}), np.uint8),
                       cv2.IMREAD_GRAYSCALE)
    if c["done"] + c["failed"] < len(files):
        assert end.mean() > 200, end.mean()       # the track (#e3e6ea), not the grey or blue of work done
    _screenshot(page, tmp_path, "wandell-webpage-batch-cancelled-early.png")


def _lights_in(grid, apart=3.0) -> int:
    """The lights of a light map as the page counts them: cells more than
    ``apart`` degrees from every earlier group start a group; a group within
    ``apart`` of a non-negative mixture of two others (light is additive)
    is not a light of its own."""
    from recovery import angular_error

    cells = [np.asarray(c, float) for row in grid for c in row]
    groups = []
    for c in cells:
        if not any(angular_error(g, c) <= apart for g in groups):
            groups.append(c)

    def mixed(g, a, b):
        w, *_ = np.linalg.lstsq(np.stack([a, b], axis=1), g, rcond=None)
        return bool(np.all(w >= 0)) and angular_error(g, np.stack([a, b], axis=1) @ w) <= apart

    pure = [g for i, g in enumerate(groups)
            if not any(mixed(g, a, b) for j, a in enumerate(groups) for k, b in enumerate(groups)
                       if len({i, j, k}) == 3)]
    return max(1, len(pure))


def test_a_light_map_is_shown_as_lights_found_and_a_picture(page, server, tmp_path):
    """With "always map the light" the API answers a light map; the page
    counts its lights as the API's map says (regions more than 3 degrees
    apart, counted here the same way from the API's own answer), gives the
    reason, and draws the map in the picture's proportions."""
    import httpx

    dng = _dng(tmp_path / "scene.dng", "D50", 12)
    page.select_option("#opt-spatial", "true")
    page.set_input_files("#file", str(dng))
    page.wait_for_selector("#status:has-text('Done')", timeout=120_000)
    est = httpx.post(server + "/v1/analyze", files={"file": ("scene.dng", dng.read_bytes())},
                     data={"spatial": "true"}, timeout=60).json()
    n = _lights_in(est["light_map"]["camera_rgb"])
    assert page.is_visible("#lights") and page.is_visible("#light-map")
    assert page.get_attribute("#light-map", "data-lights") == str(n)
    title = page.text_content("#lights-title")
    assert title.startswith(f"{n} lights found" if n > 1 else "One light, varying"), title
    assert page.text_content("#lights-reason") == est["diagnostics"]["spatial_reason"].replace(
        "spatial='map' asks for a light map", '"always map the light" under Options asks for a map')
    w, h = page.eval_on_selector("#light-map", "c => [c.width, c.height]")
    assert abs(w / h - 360 / 240) < 0.05


def test_several_picks_are_averaged(page, server, tmp_path):
    """A click picks white there (a mark shows it); Shift-click adds a
    pick: the page sends all picks to the API (``neutral`` a list), which
    averages them (the mean of each pick's white at unit length), so the
    page shows what the REST API answers for the same picks: the preview
    shown is byte for byte /v1/preview's with that list, and the white is
    the mean of the single picks' whites (1e-6 degrees: floating point)."""
    import httpx

    from recovery import angular_error

    dng = _dng(tmp_path / "scene.dng", "D50", 6)
    _open(page, server, dng)
    page.locator("#viewer").scroll_into_view_if_needed()
    v = page.locator("#viewer").bounding_box()
    img = page.eval_on_selector("#img-corrected", "i => { const b = i.getBoundingClientRect(); "
                                                  "return [b.left, b.top, b.width, b.height]; }")
    # two grey patches of the chart's bottom row (ColorChecker layout, 4 x 6)
    points = [(img[0] + img[2] * (c + 0.5) / 6 - v["x"], img[1] + img[3] * 3.5 / 4 - v["y"]) for c in (1, 3)]
    page.mouse.click(v["x"] + points[0][0], v["y"] + points[0][1])
    page.wait_for_selector("#neutral-note:has-text('White taken')", timeout=120_000)
    page.wait_for_selector("#status:has-text('Done')", timeout=120_000)
    page.keyboard.down("Shift")
    page.mouse.click(v["x"] + points[1][0], v["y"] + points[1][1])
    page.keyboard.up("Shift")
    page.wait_for_selector("#neutral-note:has-text('averaged from 2 picks')", timeout=120_000)
    page.wait_for_selector("#status:has-text('Done')", timeout=120_000)
    assert page.text_content("#dl-white") == "the mean of your 2 picks"
    assert page.eval_on_selector_all(".pick-mark", "ms => ms.filter(m => !m.hidden).length") == 2
    neutrals = page.evaluate("() => current.picks.map(p => p.neutral)")
    assert page.evaluate("() => current.neutral") == neutrals and len(neutrals) == 2
    files = {"file": ("scene.dng", dng.read_bytes())}
    singles = [np.array(httpx.post(server + "/v1/analyze", files=files, data={"neutral": json.dumps(n)},
                                   timeout=60).json()["illuminant"]["camera_rgb"]) for n in neutrals]
    both = httpx.post(server + "/v1/analyze", files=files, data={"neutral": json.dumps(neutrals)}, timeout=60).json()
    mean = np.mean([s / np.linalg.norm(s) for s in singles], axis=0)
    assert angular_error(np.array(both["illuminant"]["camera_rgb"]), mean) < 1e-6
    shown = page.evaluate("() => current.estimate.illuminant.camera_rgb")
    assert angular_error(np.array(shown), mean) < 1e-6
    api = httpx.post(server + "/v1/preview", files=files, timeout=60, data={
        "wb": "corrected", "white": "estimate", "target": "D65", "format": "jpeg", "max_side": "1024",
        "neutral": json.dumps(neutrals)})
    assert api.status_code == 200, api.text
    shown_bytes = base64.b64decode(page.evaluate(_IMG_BYTES, "#img-corrected"))
    assert shown_bytes == api.content
    assert page.get_attribute("#wb-auto", "aria-pressed") == "true"
    _screenshot(page, tmp_path, "wandell-webpage-picks.png")


def test_ctrl_wheel_zooms_about_the_pointer(page, server, tmp_path):
    """Ctrl + wheel (a trackpad's pinch) zooms by exp(-0.002 deltaY), the
    picture's point under the pointer staying under it; never below Fit."""
    _open(page, server, _dng(tmp_path / "scene.dng", "D50", 6))
    page.locator("#viewer").scroll_into_view_if_needed()
    v = page.locator("#viewer").bounding_box()
    rect = "i => { const b = i.getBoundingClientRect(); return [b.left, b.top, b.width]; }"
    x0, y0, w0 = page.eval_on_selector("#img-corrected", rect)
    px, py = v["x"] + 0.3 * v["width"], v["y"] + 0.4 * v["height"]
    page.mouse.move(px, py)
    page.keyboard.down("Control")
    page.mouse.wheel(0, -200)
    page.keyboard.up("Control")
    page.wait_for_selector("#viewer.zoomed")
    x1, y1, w1 = page.eval_on_selector("#img-corrected", rect)
    assert w1 / w0 == pytest.approx(np.exp(0.4), rel=1e-3)
    # the same picture point under the pointer: (p - left) / width unchanged
    assert (px - x1) / w1 == pytest.approx((px - x0) / w0, abs=0.5 / w1)
    assert (py - y1) / w1 == pytest.approx((py - y0) / w0, abs=0.5 / w1)
    page.keyboard.down("Control")
    page.mouse.wheel(0, 2000)                  # far out: stops at Fit
    page.keyboard.up("Control")
    page.wait_for_selector("#zoom-fit[aria-pressed='true']")
    assert page.eval_on_selector("#img-corrected", rect)[2] == pytest.approx(w0, rel=1e-6)


def _touch(cdp, kind: str, points) -> None:
    """A touch event with these fingers ``[(x, y), ...]`` (page CSS px), sent
    through Chromium's input pipeline (DevTools ``Input.dispatchTouchEvent``:
    the browser's gesture handling, touch-action and pointer events, as a
    phone's touchscreen sends them)."""
    cdp.send("Input.dispatchTouchEvent", {"type": kind, "touchPoints": [
        {"x": x, "y": y, "id": i, "radiusX": 5, "radiusY": 5} for i, (x, y) in enumerate(points)]})


def test_pinch_and_pan_by_touch_on_a_phone(browser, server, tmp_path):
    """Issue 29, item 3 (zoom, pan on a phone), at 375 px with a touch
    screen (device pixel ratio 2): two fingers pinching apart zoom by the
    ratio of their distances, the picture's point under their midpoint
    staying under it; two fingers moving together pan; one finger pans the
    zoomed picture by its own movement; none of it picks a white or zooms
    the page itself, and a pinch that starts on the split's divider (in the
    middle of the picture, where a thumb lands) zooms and leaves the divider
    where it was. Bounds: 1e-3 relative for the scale (the page computes it
    from the fingers' distance in floating point) and 0.5 px for positions
    (the touch points are CSS pixels)."""
    ctx = browser.new_context(viewport={"width": 375, "height": 800}, has_touch=True, is_mobile=True,
                              device_scale_factor=2)
    pg = ctx.new_page()
    problems = []
    pg.on("pageerror", lambda e: problems.append(str(e)))
    dng = tmp_path / "square.dng"
    scene_dng(dng, "Nikon 5100 (NPL)", "D50", 360, 360, seed=6)
    _open(pg, server, dng)
    pg.locator("#viewer").scroll_into_view_if_needed()
    v = pg.locator("#viewer").bounding_box()
    rect = "i => { const b = i.getBoundingClientRect(); return [b.left, b.top, b.width]; }"

    def picture_point(x, y):
        """The picture's point (fractions of its width) under page point (x, y)."""
        left, top, w = pg.eval_on_selector("#img-corrected", rect)
        return np.array([(x - left) / w, (y - top) / w]), w

    cdp = ctx.new_cdp_session(pg)
    divider = pg.locator("#divider").bounding_box()
    x0 = divider["x"] + divider["width"] / 2          # the first finger on the divider
    y = v["y"] + 0.5 * v["height"]
    mid = (x0 + 40, y)                                 # the second 80 px to its right
    before, w0 = picture_point(*mid)
    split0 = pg.evaluate("view.split")
    _touch(cdp, "touchStart", [(x0, y), (x0 + 80, y)])
    for d in range(45, 81, 5):                         # the fingers 80 -> 160 px apart, midpoint fixed
        _touch(cdp, "touchMove", [(mid[0] - d, y), (mid[0] + d, y)])
    _touch(cdp, "touchEnd", [])
    pg.wait_for_selector("#viewer.zoomed")
    after, w1 = picture_point(*mid)
    assert w1 / w0 == pytest.approx(2.0, rel=1e-3)
    assert np.abs(after - before).max() * w1 < 0.5, (before, after)
    assert pg.evaluate("view.split") == split0                   # the divider stayed
    assert pg.evaluate("visualViewport.scale") == 1              # the page itself did not zoom
    assert pg.evaluate("document.documentElement.scrollWidth") <= 375

    # two fingers moving together (same distance): the picture follows them
    v = pg.locator("#viewer").bounding_box()
    y = v["y"] + 0.5 * v["height"]
    a, b = (v["x"] + 120, y), (v["x"] + 220, y)
    start, _ = picture_point(170 + v["x"], y)
    _touch(cdp, "touchStart", [a, b])
    for k in range(1, 7):
        _touch(cdp, "touchMove", [(a[0] + 5 * k, y + 3 * k), (b[0] + 5 * k, y + 3 * k)])
    _touch(cdp, "touchEnd", [])
    moved, w2 = picture_point(170 + v["x"] + 30, y + 18)
    assert w2 == pytest.approx(w1, rel=1e-3) and np.abs(moved - start).max() * w2 < 0.5, (start, moved)

    # one finger: pans the zoomed picture by its movement
    l0, t0, _ = pg.eval_on_selector("#img-corrected", rect)
    p = (v["x"] + 300, v["y"] + 200)                  # away from the divider (which a finger would move)
    _touch(cdp, "touchStart", [p])
    for k in range(1, 9):
        _touch(cdp, "touchMove", [(p[0] - 5 * k, p[1] - 4 * k)])
    _touch(cdp, "touchEnd", [])
    l1, t1, _ = pg.eval_on_selector("#img-corrected", rect)
    assert (l1 - l0, t1 - t0) == (pytest.approx(-40, abs=0.5), pytest.approx(-32, abs=0.5))
    assert not (pg.text_content("#neutral-note") or "").startswith("White taken")   # no gesture picked a white
    _screenshot(pg, tmp_path, "wandell-webpage-pinch-phone.png")

    # pinching far in stops at Fit
    c = (v["x"] + v["width"] / 2 + 50, y)
    _touch(cdp, "touchStart", [(c[0] - 100, y), (c[0] + 100, y)])
    for d in range(90, 9, -10):
        _touch(cdp, "touchMove", [(c[0] - d, y), (c[0] + d, y)])
    _touch(cdp, "touchEnd", [])
    pg.wait_for_selector("#zoom-fit[aria-pressed='true']")
    assert pg.eval_on_selector("#img-corrected", rect)[2] == pytest.approx(w0, rel=1e-6)
    assert not problems, problems
    ctx.close()


def _two_light_dng(path: Path) -> Path:
    """A Mondrian half under CIE A, half under D65 (24 degrees apart for the
    Nikon 5100), :func:`testing.scenes.two_light_scene`, mosaicked into a
    DNG of the measured camera."""
    import cv2

    from testing.dngwriter import CAMERA_MAKE_MODEL, cfa_colour_indices, color_matrix_for_camera, mosaic, write_dng
    from testing.scenes import two_light_scene

    img, _, sep = two_light_scene(np.random.default_rng(3), 24, "Nikon 5100 (NPL)", "A", "D65", "halves", 256)
    assert sep > 20
    cfa = mosaic(cv2.resize(img, (768, 512), interpolation=cv2.INTER_NEAREST))
    make, model = CAMERA_MAKE_MODEL["Nikon 5100 (NPL)"]
    write_dng(path, np.round(np.clip(cfa, 0, 1) * 16000).astype(np.uint16), pattern=cfa_colour_indices("RGGB"),
              black_level=0, white_level=16383, color_matrix1=color_matrix_for_camera("Nikon 5100 (NPL)"),
              make=make, model=model)
    return path


def test_two_lights_found_and_drawn_where_they_are(page, server, tmp_path):
    """A scene lit half by a tungsten lamp and half by daylight: with the
    default options the API maps the light, the page says "2 lights found"
    with the API's reason, and its small picture is warmer where the API's
    map has the warmer light."""
    import httpx

    dng = _two_light_dng(tmp_path / "two.dng")
    _open(page, server, dng)
    est = httpx.post(server + "/v1/analyze", files={"file": ("two.dng", dng.read_bytes())}, timeout=60).json()
    lm = est.get("light_map")
    assert lm is not None, est["diagnostics"].get("spatial_reason")
    assert _lights_in(lm["camera_rgb"]) == 2
    assert page.text_content("#lights-title").startswith("2 lights found"), page.text_content("#lights-title")
    assert est["diagnostics"]["spatial_reason"] in page.text_content("#lights-reason")
    # the warmest and coolest cells of the API's map, and the picture's colour there
    cells = [(r, c, rgb) for r, row in enumerate(lm["camera_rgb"]) for c, rgb in enumerate(row)]
    warm = max(cells, key=lambda t: t[2][0] / t[2][2])
    cool = min(cells, key=lambda t: t[2][0] / t[2][2])
    pixel = """(c, [fy, fx]) => Array.from(c.getContext("2d").getImageData(
        Math.floor(fx * c.width), Math.floor(fy * c.height), 1, 1).data)"""
    pw = page.eval_on_selector("#light-map", pixel, [lm["centres_row_fraction"][warm[0]], lm["centres_col_fraction"][warm[1]]])
    pc = page.eval_on_selector("#light-map", pixel, [lm["centres_row_fraction"][cool[0]], lm["centres_col_fraction"][cool[1]]])
    assert pw[0] - pw[2] > pc[0] - pc[2] + 30, (pw, pc)
    _screenshot(page, tmp_path, "wandell-webpage-two-lights.png")


# ---------------------------------------------------------------------------
# Newcomer audit (2026-12-06; docs/web_page.md)
# ---------------------------------------------------------------------------

def test_always_one_light_reaches_the_picture_the_downloads_and_the_surfaces(page, server, tmp_path):
    """*Several lights: always one light* on a two-light scene: the words said
    one light, but the picture, the downloads and a surface read were still
    the light map's (only /v1/analyze got ``spatial``; /v1/preview did not
    take it). Now the picture shown is /v1/preview's one-light image, the
    JPEG downloaded is /v1/white-balance's with ``spatial=false``, and the
    surface is read under the one light."""
    import httpx

    dng = _two_light_dng(tmp_path / "two.dng")
    files = {"file": ("two.dng", dng.read_bytes())}
    page.select_option("#opt-spatial", "false")
    page.set_input_files("#file", str(dng))
    page.wait_for_selector("#status:has-text('Done')", timeout=120_000)
    _wait_rendered(page)
    assert page.is_hidden("#lights")
    one = httpx.post(server + "/v1/preview", files=files, timeout=120,
                     data={"wb": "corrected", "white": "estimate", "format": "jpeg", "max_side": "1024",
                           "target": "D65", "spatial": "false"})
    assert one.status_code == 200, one.text
    assert base64.b64decode(page.evaluate(_IMG_BYTES, "#img-corrected")) == one.content
    with page.expect_download(timeout=180_000) as dl:
        page.click("#dl-jpeg")
    full = httpx.post(server + "/v1/white-balance", files=files, timeout=180,
                      data={"format": "jpeg", "target": "D65", "white": "estimate", "spatial": "false"})
    assert Path(dl.value.path()).read_bytes() == full.content
    page.check("#pick-surface")
    page.locator("#viewer").scroll_into_view_if_needed()
    img = page.eval_on_selector("#img-corrected", "i => { const b = i.getBoundingClientRect(); "
                                                  "return [b.left, b.top, b.width, b.height]; }")
    with page.expect_response(lambda q: q.url.endswith("/v1/surfaces"), timeout=120_000) as resp:
        page.mouse.click(img[0] + img[2] * 0.7, img[1] + img[3] * 0.5)
    page.wait_for_selector("#surface-words:has-text('Expected error')", timeout=120_000)
    assert "light_map" not in resp.value.json()
    assert "under Auto's light" in page.text_content("#surface-words")


def test_technical_details_account_for_every_pixel_left_out(page, server, tmp_path):
    """The README's CinemaDNG: "It used 140,169 of 140,352 analysis pixels
    (84 dark or saturated left out)" left 99 pixels unexplained (those the
    loader masks: a clipped raw sample in their block). The reasons given
    now add up to what was left out."""
    import httpx

    from .conftest import shared_file

    dng = shared_file("data/raw/Blackmagic.dng")
    _open(page, server, dng)
    d = httpx.post(server + "/v1/analyze", files={"file": ("b.dng", dng.read_bytes())},
                   timeout=120).json()["diagnostics"]
    line = next(t for t in page.eval_on_selector_all("#diag-details li", "ls => ls.map((l) => l.textContent)")
                if t.startswith("It used"))
    used, total = (int(x.replace(",", "")) for x in re.findall(r"([\d,]+) of ([\d,]+)", line)[0])
    assert (used, total) == (d["pixels_used"], d["pixels_total"]), line
    counts = [int(x.replace(",", "")) for x in re.findall(r"([\d,]+) [a-z]", line.split("left out:", 1)[1])]
    assert sum(counts) == total - used and len(counts) >= 2, line
