"""Screenshots of the issue-19 page problems, before and after (see README.md).

    nice python docs/screenshots/shoot_issue19.py LABEL BASE_URL OUT_DIR

LABEL is "before" or "after", BASE_URL a running server (uvicorn
service.app:app), OUT_DIR where the PNGs and LABEL.json (what was measured)
go. Debian's chromium through playwright, desktop 1280x900 and phone
375x812. Scenes:

* single: the real CinemaDNG with method maloney-wandell (its own tests fail
  on this image, so the red "not trustworthy" flag shows): the two previews,
  their caption and the flag;
* keyboard: Tab from the top of the page to the one-file drop zone, then
  Enter: is the zone focused and visible, does a file chooser open;
* batch: three real-looking DNGs and a truncated one, run to the end: the
  table (words broken mid-word?) and the status line ("About 0 s left"?);
* cancel: twelve larger DNGs (1400x2100), Cancel once one is done and others run; the
  page 3 s after the API says every count is final, beside the API's counts;
* docs: /docs, POST /v1/analyze, "Try it out", a file, "Execute".
"""

import json
import sys
import time
from pathlib import Path

import httpx
from playwright.sync_api import sync_playwright

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from testing.dngwriter import scene_dng  # noqa: E402

LABEL, BASE, OUT = sys.argv[1], sys.argv[2].rstrip("/"), Path(sys.argv[3])
DNG = "/work/shared/data/raw/Blackmagic.dng"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync"]
WORK = OUT / "inputs"


def inputs():
    WORK.mkdir(parents=True, exist_ok=True)
    small = []
    for i, name in enumerate(["DSC_0412_lakeside.dng", "DSC_0413_lakeside.dng", "DSC_0414_portrait_window.dng"]):
        p = WORK / name
        if not p.exists():
            scene_dng(p, "Nikon 5100 (NPL)", ["D4000", "A", "D65"][i], 240, 360, seed=i)
        small.append(p)
    bad = WORK / "DSC_0415_card_error.dng"
    bad.write_bytes(small[0].read_bytes()[:2000])
    big = []
    for i in range(12):
        p = WORK / f"IMG_{2040 + i}.dng"
        if not p.exists():
            scene_dng(p, "Nikon 5100 (NPL)", "D4000", 1400, 2100, seed=10 + i)
        big.append(p)
    return small + [bad], big


def shot(pg, locator, name):
    path = OUT / f"issue19_{name}_{LABEL}_{pg.dev}.png"
    if locator is None:
        pg.screenshot(path=str(path), full_page=False)
    else:
        locator.scroll_into_view_if_needed()
        locator.screenshot(path=str(path))
    return path.name


def scene_single(pg, m):
    pg.select_option("#opt-method", "maloney-wandell")
    pg.set_input_files("#file", DNG)
    pg.wait_for_selector("#result", state="visible", timeout=300_000)
    for _ in range(120):
        if pg.eval_on_selector_all("#img-original, #img-corrected",
                                   "is => is.every(i => i.complete && i.naturalWidth > 0)"):
            break
        pg.wait_for_timeout(500)
    m["caption"] = pg.inner_text("#corrected-note")
    m["preview_natural"] = pg.eval_on_selector("#img-corrected", "i => [i.naturalWidth, i.naturalHeight]")
    m["flag_visible"] = pg.is_visible("#corrected-flag")
    tops = pg.eval_on_selector_all("#img-original, #img-corrected",
                                   "is => is.map(i => Math.round(i.getBoundingClientRect().top))")
    m["image_tops"] = tops
    m["shot"] = shot(pg, pg.locator("#result .images"), "single")


def scene_keyboard(pg, m):
    seen = []
    for _ in range(40):
        pg.keyboard.press("Tab")
        seen.append(pg.evaluate("document.activeElement.id || document.activeElement.tagName"))
        if seen[-1] == "drop":
            break
    m["tab_order_to_drop"] = seen
    m["drop_focused"] = seen[-1] == "drop"
    m["outline"] = pg.eval_on_selector("#drop", "e => getComputedStyle(e).outlineStyle + ' ' + "
                                       "getComputedStyle(e).outlineWidth")
    m["shot"] = shot(pg, pg.locator("#single"), "keyboard")
    opened = False
    if m["drop_focused"]:
        try:
            with pg.expect_file_chooser(timeout=3000):
                pg.keyboard.press("Enter")
            opened = True
        except Exception:
            opened = False
    m["enter_opens_file_chooser"] = opened
    # the batch chooser: is any element of the batch drop zone reachable?
    seen = []
    for _ in range(40):
        pg.keyboard.press("Tab")
        seen.append(pg.evaluate("document.activeElement.id || document.activeElement.tagName"))
        if seen[-1] == "batch-drop":
            break
    opened = False
    if seen[-1] == "batch-drop":
        try:
            with pg.expect_file_chooser(timeout=3000):
                pg.keyboard.press(" ")
            opened = True
        except Exception:
            opened = False
    m["batch_space_opens_file_chooser"] = opened


def wait_batch(pg, bid, timeout=300):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        doc = httpx.get(f"{BASE}/v1/batches/{bid}", timeout=30).json()
        c = doc["counts"]
        if doc["status"] in ("done", "cancelled") and not c.get("running") and not c.get("pending"):
            return doc
        time.sleep(0.3)
    return doc


def batch_id(pg):
    return pg.inner_text("#batch-status").split(":")[0].replace("Batch ", "").strip()


def scene_batch(pg, m, files):
    pg.set_input_files("#batch-files", [str(f) for f in files])
    pg.click("#batch-run")
    pg.wait_for_selector("#batch-view", state="visible", timeout=60_000)
    pg.wait_for_timeout(500)
    doc = wait_batch(pg, batch_id(pg))
    pg.wait_for_timeout(3000)
    m["api_counts"] = doc["counts"]
    m["status_line"] = pg.inner_text("#batch-status")
    m["table_overflow_wrap"] = pg.eval_on_selector("#batch-table td", "e => getComputedStyle(e).overflowWrap")
    # cells whose text wraps inside a word: a word's characters on two lines
    m["cells_broken_mid_word"] = pg.eval_on_selector_all("#batch-table td", """tds => tds.filter(td => {
        const r = document.createRange(); const t = td.firstChild;
        if (!t || t.nodeType !== 3) return false;
        const words = t.textContent.split(/(\\s+|-)/); let off = 0;   // a hyphen is a break opportunity
        for (const w of words) {
          if (w.trim()) { r.setStart(t, off); r.setEnd(t, off + w.length);
            const tops = new Set(Array.from(r.getClientRects(), x => Math.round(x.top))); if (tops.size > 1) return true; }
          off += w.length;
        }
        return false; }).map(td => td.innerText)""")
    m["shot"] = shot(pg, pg.locator("#batch-view"), "batch")


def scene_cancel(pg, m, files):
    pg.set_input_files("#batch-files", [str(f) for f in files])
    pg.click("#batch-run")
    pg.wait_for_selector("#batch-view", state="visible", timeout=120_000)
    pg.wait_for_timeout(500)
    bid = batch_id(pg)
    t_end = time.monotonic() + 300
    while time.monotonic() < t_end:
        c = httpx.get(f"{BASE}/v1/batches/{bid}", timeout=30).json()["counts"]
        if c["done"] >= 1:
            break
        time.sleep(0.1)
    m["api_counts_at_cancel"] = c
    pg.click("#batch-cancel")
    doc = wait_batch(pg, bid, 120)
    pg.wait_for_timeout(3000)
    m["api_final"] = {"status": doc["status"], "counts": doc["counts"]}
    m["status_line"] = pg.inner_text("#batch-status")
    m["page_rows"] = pg.eval_on_selector_all("#batch-table tbody tr", "rs => rs.map(r => r.cells[1].innerText)")
    m["shot"] = shot(pg, pg.locator("#batch-view"), "cancel")


def scene_docs(pg, m, small):
    pg.goto(BASE + "/docs")
    pg.wait_for_selector(".opblock", timeout=30_000)
    op = pg.locator("#operations-default-analyze_v1_analyze_post")
    op.locator(".opblock-summary").click()
    op.locator(".try-out__btn").click()
    op.locator("input[type=file]").first.set_input_files(str(small))
    m["shot_form"] = shot(pg, op.locator(".opblock-section-request-body"), "docs-form")
    with pg.expect_response(lambda r: "/v1/analyze" in r.url, timeout=120_000) as resp:
        op.locator(".execute").click()
    op.locator(".live-responses-table .response-col_status").first.wait_for(timeout=60_000)
    pg.wait_for_timeout(500)
    m["status"] = resp.value.status
    m["curl"] = op.locator(".curl-command").inner_text()
    # the curl command Swagger ran and the server's answer (not the documented responses below)
    top = op.locator(".curl-command").bounding_box()
    end = op.locator(".live-responses-table").bounding_box()
    scroll = pg.evaluate("[window.scrollX, window.scrollY]")
    clip = {"x": top["x"] + scroll[0], "y": top["y"] + scroll[1], "width": max(top["width"], end["width"]),
            "height": min(900, end["y"] + end["height"] - top["y"])}
    path = OUT / f"issue19_docs_{LABEL}_{pg.dev}.png"
    pg.screenshot(path=str(path), clip=clip, full_page=True)
    m["shot"] = path.name


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    small, big = inputs()
    res = {}
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path="/usr/bin/chromium", args=ARGS)
        for dev, vp in (("desktop", (1280, 900)), ("phone", (375, 812))):
            for name in (sys.argv[4].split(",") if len(sys.argv) > 4 else
                         ["single", "keyboard", "batch", "cancel", "docs"]):
                ctx = b.new_context(viewport={"width": vp[0], "height": vp[1]})
                pg = ctx.new_page()
                pg.dev = dev
                pg.on("filechooser", lambda chooser: None)   # interception on before any key press
                errs = []
                pg.on("pageerror", lambda e: errs.append(str(e)))
                pg.goto(BASE + "/")
                m = {}
                try:
                    if name == "single":
                        scene_single(pg, m)
                    elif name == "keyboard":
                        scene_keyboard(pg, m)
                    elif name == "batch":
                        scene_batch(pg, m, small)
                    elif name == "cancel":
                        scene_cancel(pg, m, big)
                    else:
                        scene_docs(pg, m, small[0])
                except Exception as e:  # record and go on with the next scene
                    m["failed"] = f"{type(e).__name__}: {e}"[:400]
                m["page_errors"] = errs
                m["scrollWidth"] = pg.evaluate("document.documentElement.scrollWidth")
                res[f"{name}_{dev}"] = m
                print(LABEL, name, dev, json.dumps(m)[:1500], flush=True)
                ctx.close()
        b.close()
    path = OUT / f"{LABEL}.json"
    old = json.loads(path.read_text()) if path.exists() else {}
    old.update(res)
    path.write_text(json.dumps(old, indent=1))


if __name__ == "__main__":
    main()
