"""Issue 19, items 4 and 9: the page's light facts, a scanner NEF's error and
a click on a dark tree, before and after, at 1280 and 375 px (element
screenshots). Run with two servers up: before on 8021, after on 8022
(``nice .venv/bin/python docs/screenshots/issue19_ux.py OUT_DIR``)."""
import json
import sys

from playwright.sync_api import sync_playwright

DNG = "/work/shared/data/raw/Blackmagic.dng"
NEF = "/work/shared/data/raw/Nikon_uncompressed.nef"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync"]
OUT = sys.argv[1] if len(sys.argv) > 1 else "."
res = {}
with sync_playwright() as p:
    b = p.chromium.launch(executable_path="/usr/bin/chromium", args=ARGS)
    for label, base in (("before", "http://127.0.0.1:8021"), ("after", "http://127.0.0.1:8022")):
        for dev, vp in (("desktop", (1280, 900)), ("phone", (375, 812))):
            pg = b.new_context(viewport={"width": vp[0], "height": vp[1]}).new_page()
            pg.goto(base + "/")
            pg.set_input_files("#file", DNG)
            pg.wait_for_selector("#result", state="visible", timeout=120_000)
            pg.locator(".light").screenshot(path=f"{OUT}/issue19_light_{label}_{dev}.png")
            facts = pg.inner_text("#light-facts")
            # a click on the dark trees (1.9 % of the white level there), left of centre, lower third
            img = pg.locator("#img-corrected")
            img.scroll_into_view_if_needed()
            box = img.bounding_box()
            img.click(position={"x": box["width"] * 0.30, "y": box["height"] * 0.70})
            for _ in range(240):
                if (pg.locator("#neutral-note").text_content() or "").startswith("White fixed") \
                        and pg.is_visible("#result"):
                    break
                pg.wait_for_timeout(500)
            pg.locator("#diagnostics").screenshot(path=f"{OUT}/issue19_dark_click_{label}_{dev}.png")
            diag = pg.inner_text("#diagnostics")
            pg.set_input_files("#file", NEF)
            pg.wait_for_selector("#error", state="visible", timeout=120_000)
            pg.locator("#error").screenshot(path=f"{OUT}/issue19_nef_error_{label}_{dev}.png")
            res[f"{label}_{dev}"] = {"light_facts": facts, "diagnostics": diag, "nef_error": pg.inner_text("#error")}
            print(label, dev, json.dumps(res[f"{label}_{dev}"]), flush=True)
            pg.context.close()
    b.close()
json.dump(res, open(f"{OUT}/issue19_ux.json", "w"), indent=1)
