import json, sys, time
from playwright.sync_api import sync_playwright
DNG = "/work/shared/data/raw/Blackmagic.dng"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync"]
targets = [("before", "http://127.0.0.1:8011"), ("after", "http://127.0.0.1:8012")]
if len(sys.argv) > 1:
    targets = [t for t in targets if t[0] in sys.argv[1:]]
res = {}
with sync_playwright() as p:
    b = p.chromium.launch(executable_path="/usr/bin/chromium", args=ARGS)
    for label, base in targets:
        for dev, vp in (("desktop", (1280, 900)), ("phone", (375, 812))):
            ctx = b.new_context(viewport={"width": vp[0], "height": vp[1]})
            pg = ctx.new_page()
            errs = []
            pg.on("pageerror", lambda e: errs.append(str(e)))
            pg.on("console", lambda m: errs.append(m.text) if m.type == "error" else None)
            pg.goto(base + "/")
            t0 = time.monotonic()
            pg.set_input_files("#file", DNG)
            for _ in range(600):
                if pg.is_visible("#result") or pg.is_visible("#error"): break
                pg.wait_for_timeout(500)
            # both images loaded
            for _ in range(600):
                ok = pg.eval_on_selector_all("#img-original, #img-corrected",
                                             "is => is.every(i => i.complete && i.naturalWidth > 0)")
                if ok: break
                pg.wait_for_timeout(500)
            pg.wait_for_timeout(1000)
            dt = time.monotonic() - t0
            m = {"scrollWidth": pg.evaluate("document.documentElement.scrollWidth"),
                 "clientWidth": pg.evaluate("document.documentElement.clientWidth"),
                 "scrollHeight": pg.evaluate("document.documentElement.scrollHeight"),
                 "error_visible": pg.is_visible("#error"),
                 "error": pg.inner_text("#error") if pg.is_visible("#error") else None,
                 "cct": pg.inner_text("#cct") if pg.is_visible("#cct") else None,
                 "images_loaded": ok, "seconds": round(dt, 1), "console_errors": errs}
            if dev == "phone":
                m["wider"] = pg.evaluate("""() => Array.from(document.querySelectorAll('body *'))
                    .filter(e => e.getBoundingClientRect().right > document.documentElement.clientWidth + 0.5)
                    .slice(0, 8).map(e => (e.tagName + (e.id ? '#' + e.id : '') + (e.className ? '.' + e.className : '')
                      + ' right=' + Math.round(e.getBoundingClientRect().right) + ' w=' + Math.round(e.getBoundingClientRect().width)))""")
            pg.screenshot(path=f"/tmp/shots/raw_{label}_{dev}.png", full_page=True)
            res[f"{label}_{dev}"] = m
            print(label, dev, json.dumps(m), flush=True)
            ctx.close()
    b.close()
json.dump(res, open("/tmp/shots/measure_%s.json" % "_".join(t[0] for t in targets), "w"), indent=1)
