"""Batch items by index and by name, store recovery and stale temporaries
(issue 17, items 5, 6, 7 and 12): the reproductions ``item_lookup.py``,
``item_index_name.py``, ``store_recovery_names.py`` and
``kill9_part_file.py`` through the ASGI app with its lifespan (the runner),
plus the job store and the temporary clean-up on their own."""

from __future__ import annotations

import io

import cv2
import numpy as np
from fastapi.testclient import TestClient

from service import jobs
from service.app import app
from testing.dngwriter import scene_dng

from .test_batch_robustness import OPTS, _wait, batch_env  # noqa: F401 - batch_env is a fixture


def _dng(h=48, w=64, seed=1) -> bytes:
    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D50", h, w, seed=seed)
    return buf.getvalue()


def _shape(content: bytes):
    img = cv2.imdecode(np.frombuffer(content, np.uint8), cv2.IMREAD_UNCHANGED)
    return None if img is None else img.shape[:2]


def test_odd_item_keys_are_404_not_500(batch_env):
    """item_lookup.py: items/² (str.isdigit() is true, int() refuses it) was a
    500 ValueError and items/99999999999999999999 (beyond SQLite's 64-bit
    integers) a 500 OverflowError. Both are 404, under every item URL."""
    batch_env()
    with TestClient(app, raise_server_exceptions=False) as c:
        r = c.post("/v1/batches", files=[("files", ("a.dng", _dng()))], data=OPTS)
        bid = r.json()["id"]
        assert _wait(c, bid)["counts"]["done"] == 1
        assert c.get(f"/v1/batches/{bid}/items/0").status_code == 200
        for key in ("%C2%B2", "99999999999999999999", "9" * 400, "-1", "%20" + "0", "0x0", "%D9%A0"):
            for path in ("items", "items/by-index", "items/by-name"):
                got = c.get(f"/v1/batches/{bid}/{path}/{key}")
                assert got.status_code == 404 and got.json()["error"] == "not_found", (path, key, got.text)
    store = jobs.JobStore(str(batch_env() / "data"))
    assert store.item(bid, "\u00b2") is None and store.item_by_index(bid, 10 ** 20) is None
    assert store.item_by_index(bid, "0")["name"] == "a.dng"


def test_a_file_named_like_an_index_never_takes_another_items_url(batch_env):
    """item_index_name.py: in a batch of holiday.dng (item 0) and a file
    named "0" (item 1), item 0's advertised url (items/0, looked up by name
    first) served item 1's image. The url is now items/by-index/N, which
    only ever means that index; items/by-name/NAME only that name; the older
    items/KEY still serves unambiguous keys and answers 409 ambiguous_item
    when KEY is one item's name and another's index."""
    batch_env()
    sizes = {"holiday.dng": (48, 64), "0": (40, 56)}
    files = [("files", (n, _dng(h, w, seed=i))) for i, (n, (h, w)) in enumerate(sizes.items())]
    with TestClient(app) as c:
        r = c.post("/v1/batches", files=files, data=OPTS)
        bid = r.json()["id"]
        doc = _wait(c, bid)
        assert [(it["index"], it["name"], it["status"]) for it in doc["items"]] == \
            [(0, "holiday.dng", "done"), (1, "0", "done")]
        for it in doc["items"]:
            assert it["url"] == f"/v1/batches/{bid}/items/by-index/{it['index']}"
            got = c.get(it["url"])
            assert got.status_code == 200 and _shape(got.content) == sizes[it["name"]], it
            by_name = c.get(f"/v1/batches/{bid}/items/by-name/{it['name']}")
            assert by_name.status_code == 200 and by_name.content == got.content
        base = f"/v1/batches/{bid}/items"
        amb = c.get(f"{base}/0")
        assert amb.status_code == 409 and amb.json()["error"] == "ambiguous_item", amb.text
        assert "by-index/0" in amb.json()["detail"] and "by-name/0" in amb.json()["detail"]
        assert _shape(c.get(f"{base}/holiday.dng").content) == sizes["holiday.dng"]
        assert _shape(c.get(f"{base}/1").content) == sizes["0"]
        assert c.get(f"{base}/by-name/1").status_code == 404
        assert c.get(f"{base}/by-index/2").status_code == 404
