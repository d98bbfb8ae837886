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
    data = tempfile.mkdtemp(prefix="wandell-webpage-data-")    # never the user's ~/.cache/wandell (issue 29)
    proc = subprocess.Popen([sys.executable, "-m", "uvicorn", "service.app:app", "--host", "127.0.0.1",
                             "--port", str(port), "--log-level", "warning"],
                            cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                            env={**os.environ, "WANDELL_DATA_DIR": data})
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
        shutil.rmtree(data, ignore_errors=True)


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
    # the previews are the 2x2-binned image: 180 x 120 for a 360 x 240 file
    assert page.eval_on_selector("#img-corrected", "i => [i.naturalWidth, i.naturalHeight]") == [180, 120]

    # the numbers on the page are the API's (same file, same default options)
    est = httpx.post(server + "/v1/analyze", files={"file": ("scene.dng", dng.read_bytes())}, timeout=60).json()
    assert page.inner_text("#cct") == f"{round(est['illuminant']['cct'])} K"
    assert re.fullmatch(r"[+-]\d\.\d{4}", page.inner_text("#duv"))

    # the spectrum: one vertex per wavelength of the estimate
    d = page.get_attribute("#spectrum-svg #spectrum-path", "d")
    assert d and d.startswith("M")
    assert len(re.findall(r"[ML]", d)) == len(est["illuminant"]["wavelengths"])

    summary = page.inner_text("#diag-summary")
    assert summary.startswith("The light was estimated by ")
    from recovery.methods import METHODS                 # the registry's words, served by /v1/models

    used = est.get("method") or est["diagnostics"].get("method")
    assert summary.startswith(f"The light was estimated by {METHODS[used].words}."), (used, summary)
    if est["diagnostics"].get("confidence") is not None:
        assert f"({round(100 * est['diagnostics']['confidence'])} %)" in summary
    assert "Camera: Nikon 5100 (NPL), with measured spectral sensitivities." in page.inner_text("#diag-details")

    shot = _screenshot(page, tmp_path, "wandell-webpage.png")
    assert shot.stat().st_size > 10_000

    # downloads: the corrected PNG at full resolution, and the JSON estimate
    with page.expect_download(timeout=90_000) as dl:
        page.click("#dl-png")
    png = cv2.imdecode(np.frombuffer(Path(dl.value.path()).read_bytes(), np.uint8), cv2.IMREAD_UNCHANGED)
    assert dl.value.suggested_filename == "scene-corrected.png"
    assert png.shape == (240, 360, 3) and png.dtype == np.uint8
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
    img = pg.locator("#img-corrected")
    img.scroll_into_view_if_needed()
    box = img.bounding_box()
    img.click(position={"x": box["width"] * 0.3, "y": box["height"] * 0.3})
    for _ in range(180):
        if (pg.locator("#neutral-note").text_content() or "").startswith("White fixed"):
            break
        pg.wait_for_timeout(500)
    assert pg.locator("#neutral-note").text_content().startswith("White fixed")
    assert pg.locator("#neutral-clear").is_visible()
    assert pg.evaluate("document.documentElement.scrollWidth") <= 375
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
    assert page.eval_on_selector("#batch-progress", "p => [p.value, p.max]") == [len(files), len(files)]
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
    if width > 700:   # side by side: both images start at the same height
        tops = pg.eval_on_selector_all("#img-original, #img-corrected",
                                       "is => is.map(i => Math.round(i.getBoundingClientRect().top))")
        assert tops[0] == tops[1], tops
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
