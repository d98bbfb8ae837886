"""Regenerate ``service/schemas/examples.json``: the examples ``/openapi.json``
and ``/docs`` show for the JSON answers, taken from real answers of the real
app (issue 29, item 4).

Run from the repository root::

    .venv/bin/python -m testing.response_examples

It posts the real CinemaDNG (``../shared/data/raw/Blackmagic.dng``) to
``/v1/analyze``, ``/v1/white-balance`` (``response=json``, and a JPEG and an
XMP sidecar for their ``X-Illuminant`` headers) and ``/v1/surfaces``; the
ColorChecker's reflectances (BabelColor average, 4 x 6 patches) to
``/v1/render`` (JSON, and a PNG for its ``X-Render-Report``); runs a batch of the CinemaDNG and the scanner's NEF (which
fails: not a camera RAW), lists, removes and cancels batches; asks ``/health``, ``/v1/cameras``, ``/v1/models``, ``/v1/sampling``
and ``/v1/preview`` (its ``X-Preview`` header); and keeps an
error answer of each kind the document declares (413 with
``WANDELL_MAX_PIXELS`` lowered). The answers are trimmed, never invented:
numbers rounded to 4 significant digits, spectra kept every 20 nm, long
lists cut to their first entries, and the diagnostics of the answers after
the first cut to the few that differ (``SHORT_DIAGNOSTICS``).
Batch store: a temporary directory (``WANDELL_DATA_DIR``).
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
OUT = ROOT / "service" / "schemas" / "examples.json"

#: The diagnostics kept in the answers after the first (which keeps them all).
SHORT_DIAGNOSTICS = ("decision", "confidence", "low_confidence", "region90_deg", "spatial_decision",
                     "spatial_reason", "lights_found", "light_map_range_deg")

#: A list longer than this is cut to its first entries (spectra are subsampled instead).
MAX_LIST = 6


def _round(x):
    if isinstance(x, float) and abs(x) > 1e8:      # epoch seconds: tenths
        return round(x, 1)
    if isinstance(x, float) and math.isfinite(x) and x != 0:
        return float(f"{x:.4g}")
    return x


def trim(doc, key: str = ""):
    """Round floats to 4 significant digits, keep spectra every 20 nm (every
    other sample of a 10 nm grid; wavelengths alike) and cut other long
    lists of numbers to their first ``MAX_LIST`` entries."""
    if isinstance(doc, dict):
        out = {}
        wl = doc.get("wavelengths")
        step = 2 if isinstance(wl, list) and len(wl) > 16 else 1
        for k, v in doc.items():
            if step > 1 and isinstance(v, list) and len(v) == len(wl) and k in ("wavelengths", "spectrum",
                                                                                  "reflectance", "reflectance_std"):
                v = v[::step]
            out[k] = trim(v, k)
        if step > 1:
            for s in out.get("surfaces", []):
                for k in ("reflectance", "reflectance_std"):
                    if isinstance(s.get(k), list) and len(s[k]) == len(wl):
                        s[k] = s[k][::step]
        return out
    if isinstance(doc, list):
        if len(doc) > MAX_LIST and key not in ("wavelengths", "spectrum", "reflectance", "reflectance_std",
                                               "nodes_nm", "items", "batches", "surfaces"):
            doc = doc[:MAX_LIST]
        return [trim(v) for v in doc]
    return _round(doc)


def collect() -> dict:
    os.environ["WANDELL_DATA_DIR"] = tempfile.mkdtemp(prefix="wandell-examples-")
    os.environ.setdefault("WANDELL_ALLOWED_HOSTS", "testserver")   # the TestClient's host
    from fastapi.testclient import TestClient

    from models import reflectance_set
    from service.app import app

    dng = (SHARED / "data" / "raw" / "Blackmagic.dng").read_bytes()
    nef = (SHARED / "data" / "raw" / "Nikon_uncompressed.nef").read_bytes()
    f = {"file": ("Blackmagic.dng", dng)}
    ex: dict = {}
    with TestClient(app) as c:
        def ok(r, code=200):
            assert r.status_code == code, (r.status_code, r.text[:500])
            return r

        ex["AnalyzeResult"] = ok(c.post("/v1/analyze", files=f)).json()
        ex["AnalyzeResult (light map)"] = ok(c.post("/v1/analyze", files=f, data={"spatial": "true"})).json()
        ex["WhiteBalanceResult"] = ok(c.post("/v1/white-balance", files=f, data={"response": "json"})).json()
        r = ok(c.post("/v1/white-balance", files=f, data={"format": "jpeg"}))
        ex["IlluminantHeader"] = json.loads(r.headers["X-Illuminant"])
        r = ok(c.post("/v1/white-balance", files=f, data={"format": "xmp"}))
        ex["EstimateSummary"] = json.loads(r.headers["X-Illuminant"])
        ex["SurfacesResult"] = ok(c.post("/v1/surfaces", files=f, data={
            "points": "[[1500, 1000]]", "rects": "[[1900, 200, 2100, 600]]"})).json()
        wl = list(range(400, 710, 10))
        cube = reflectance_set("colorchecker", np.array(wl, float)).reshape(4, 6, len(wl))
        buf = io.BytesIO()
        np.save(buf, cube)
        ex["RenderReport"] = ok(c.post("/v1/render", files={"file": ("colorchecker.npy", buf.getvalue())},
                                       data={"wavelengths": ",".join(map(str, wl)), "illuminant": "D65",
                                             "response": "json"})).json()
        r = ok(c.post("/v1/render", files={"file": ("colorchecker.npy", buf.getvalue())},
                      data={"wavelengths": ",".join(map(str, wl)), "illuminant": "D65", "format": "png"}))
        ex["RenderReport (header)"] = json.loads(r.headers["X-Render-Report"])
        r = ok(c.post("/v1/batches", files=[("files", ("Blackmagic.dng", dng)),
                                            ("files", ("Nikon_uncompressed.nef", nef))],
                      data={"format": "jpeg"}), 202)
        ex["BatchCreated"] = r.json()
        bid = r.json()["id"]
        t_end = time.monotonic() + 600
        while not (doc := c.get(f"/v1/batches/{bid}").json())["settled"]:
            assert time.monotonic() < t_end, doc
            time.sleep(0.5)
        ex["BatchProgress"] = doc
        ex["BatchList"] = ok(c.get("/v1/batches")).json()
        ex["BatchProgress (DELETE without remove)"] = ok(c.delete(f"/v1/batches/{bid}")).json()
        ex["BatchDeleted"] = ok(c.delete(f"/v1/batches/{bid}", params={"remove": "true"})).json()
        ex["Health"] = ok(c.get("/health")).json()
        ex["CameraList"] = ok(c.get("/v1/cameras")).json()
        ex["ModelsInfo"] = ok(c.get("/v1/models")).json()
        ex["SamplingRule"] = ok(c.get("/v1/sampling", params={"strategy": "gauss-ac1c2", "n": 4})).json()
        ex["SamplingRule (undefined)"] = ok(c.get("/v1/sampling", params={"strategy": "quasi-gauss-xyz",
                                                                          "degrees": "4,4,4"})).json()
        for wb, key in (("corrected", "PreviewInfo"), ("camera", "PreviewInfo (camera)")):
            ex[key] = json.loads(ok(c.post("/v1/preview", files=f, data={"wb": wb})).headers["X-Preview"])
        ex["ErrorBody 422"] = ok(c.post("/v1/white-balance", files=f, data={"taget": "A"}), 422).json()
        ex["ErrorBody 415"] = ok(c.post("/v1/analyze", files={"file": ("Nikon_uncompressed.nef", nef)}), 415).json()
        ex["ErrorBody 404"] = ok(c.get(f"/v1/batches/{bid}"), 404).json()
        from service.settings import get_settings

        os.environ["WANDELL_MAX_PIXELS"] = "4000000"      # the CinemaDNG has 8.98 million
        get_settings.cache_clear()
        try:
            ex["ErrorBody 413"] = ok(c.post("/v1/analyze", files=f), 413).json()
        finally:
            del os.environ["WANDELL_MAX_PIXELS"]
            get_settings.cache_clear()
    shutil.rmtree(os.environ["WANDELL_DATA_DIR"], ignore_errors=True)
    for k in ("AnalyzeResult (light map)", "WhiteBalanceResult"):    # the first shows them all
        ex[k]["diagnostics"] = {d: v for d, v in ex[k]["diagnostics"].items() if d in SHORT_DIAGNOSTICS}
    return {k: trim(v) for k, v in ex.items()}


def main() -> None:
    ex = collect()
    OUT.write_text(json.dumps(ex, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    print(f"wrote {OUT} ({OUT.stat().st_size} bytes): {', '.join(ex)}")


if __name__ == "__main__":
    main()
